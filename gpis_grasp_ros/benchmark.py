"""``gpis-grasp benchmark``: the paper's Table I, Fig. 4 and runtime scaling on the shipped bags.

    gpis-grasp benchmark [--bags bags/*.mcap] [--out out/benchmark] [--workers N] [--seeds 3]
                         [--grasp-samples 1000] [--shape-samples 1000] [--trials 20]
    gpis-grasp benchmark --scaling [--object A] [--sizes 25,40,55,70,100] [--repeats 3]

**Table I run.** For every bag the GPIS is built exactly as the ROS nodes build it
(:func:`~gpis_grasp_ros.pipeline.load_bag` + :func:`~gpis_grasp_ros.pipeline.posterior_from_scene`,
M = 25), then every method of :data:`METHODS` plans with the paper's settings (N_g = 20, λ = 2,
K = 1000 heuristic grasp samples, S = 1000 shape samples, σ_g = 0.5 cell) for ``--seeds`` seeds.
GP-P is run brute force (``gp_p_adaptive=False``, as in the paper) and, as an extra row, with
the default successive halving. Recorded per object × method × seed (``results.csv``):

* ``p_f`` ± ``p_f_std_error`` — the planners' own Monte-Carlo P_F of the chosen grasp on S shape
  samples and perturbations of the seed's *evaluation* stream (independent of the samples used
  for selection);
* ``q_f_mean`` — Ferrari–Canny Q_F of the grasp on the GPIS mean shape (planning grid);
* ``q_n`` — Ferrari–Canny Q_N of the *unperturbed* grasp on the TRUE shape of the bag
  (``/ground_truth/sdf``, 1 mm grid): contacts by :func:`~gpis_grasp_ros.contacts.find_contacts`
  on the true SDF, centre of mass = the bag's true centre of mass, ρ = radius of gyration of the
  true shape. A grasp without contact, with a jaw starting inside the true object or wider than
  w_g has no Q_N (NaN, reason in ``q_n_status``; counted as 0 in the tables' means);
* ``sim_successes`` of ``sim_trials`` executions by the simulated gripper on the true shape
  (:func:`~gpis_grasp_ros.planners.execute_grasp_trials`, σ_g = 0.5 planning cell, true COM);
* ``planning_time_s`` (time to choose the grasp, what the paper's runtime columns report) and
  ``evaluation_time_s`` (the final P_F estimate).

Per object (``objects.csv``): grid, resolution, GPIS fit time, the spread of the centre of mass
over ``com_samples`` joint shape samples (condition 1 of the P_F approximation, RMS and 95th
percentile of the distance to the mean shape's COM, in cells) and the IoU of the mean shape with
the true shape on the planning grid.

**Seeding (common random numbers).** The planner seed of a run is a deterministic function of
(``seed``, object) only, so within one seed every method draws from the same streams: GP-M, GP-P
and GP-P adaptive choose among the *same* 1000 heuristic candidates, GP-G and its re-ranked
variant start from the same initial grasps, and every method's P_F is estimated on the *same*
evaluation samples (what :mod:`~gpis_grasp_ros.planners` intends: "methods are comparable").
The simulated executions likewise use one perturbation stream per (seed, object), so all
methods face the same positioning errors. Seeds are derived with
``np.random.SeedSequence`` from CRC-32 hashes of the names — no process-dependent state — so a
parallel run gives exactly the numbers of a serial run (times excepted).

**Parallelism.** Objects are the unit of work: a ``ProcessPoolExecutor`` with the ``spawn``
context runs one object per worker (``--workers``, default ``os.cpu_count()``), each with
OpenBLAS/OMP/MKL limited to one thread (environment set before the workers start, plus
threadpoolctl). The serial path (``--workers 1``) also limits BLAS to one thread, so results are
bit-identical. Workers report finished (object, method) pairs through a queue; the parent draws a
plain-text progress bar with an estimate of the time left on stderr.

**Outputs** (``--out``): ``table1.md`` (Table I layout with the paper's values in parentheses, plus
Q_N, simulated success, Q_F on the mean, extra rows), ``results.csv``, ``objects.csv``,
``summary.json``, ``pf_bars.png`` (P_F per object and method), ``runtime.png`` (worst-case
planning time, log scale), ``fig4.png`` (objects A-D × GP-M/GP-P/GP-G on GPIS-Blur, as the
paper's Fig. 4) and ``objects/<object>.png`` (every method's grasp on the object's GPIS-Blur; the
green line is the true outline).

**Scaling run** (``--scaling``): on one object and grid sides M (``SensingParams(grid_size=M)``),
times of segmentation, GPIS fit (:func:`~gpis_grasp_ros.pipeline.posterior_from_grids`), drawing
S joint shape samples, GP-G (N_g = 20) and GP-P (brute force and adaptive, K × S as given by
``--grasp-samples`` / ``--shape-samples``; defaults 1000 × 1000). Each time is the shortest of
``--repeats`` runs (other processes on the machine only ever add time). Exponents k of
t = c M^k come from least squares on log t vs log M (:func:`fit_power_law`); the 70-vs-25 growth
is compared with the original (Matlab/CVX) implementation's published growth as ratios. Writes
``scaling.md``, ``scaling.csv`` and ``scaling.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import multiprocessing as mp
import os
import platform
import queue
import sys
import time
import zlib
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import AbstractContextManager, nullcontext
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .blur import gpis_blur
from .contacts import GripperParams, SdfBank, bilinear, find_contacts
from .gpis import GpisPosterior, center_of_mass
from .grid import GridGeometry
from .pipeline import load_bag, posterior_from_grids, publishable_grids
from .planners import PlannerParams, execute_grasp_trials, plan
from .quality import ferrari_canny_l1, torque_scale
from .sensing import SensingParams, segment_frames
from .viz import draw_grasp, metric_to_pixel, to_color

# ------------------------------------------------------------------------------------------
# Methods, reference numbers, settings
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MethodSpec:
    """A benchmarked planner: ``key`` (CSV), ``label`` (tables), ``planner`` (planners.plan name)."""

    key: str
    label: str
    planner: str
    gp_p_adaptive: bool = False  # only used by 'gp-p'
    color: tuple[int, int, int] = (0, 0, 0)  # BGR for the plots


METHODS: tuple[MethodSpec, ...] = (
    MethodSpec('gp-m', 'GP-M', 'gp-m', color=(40, 40, 220)),
    MethodSpec('gp-d', 'GP-D', 'gp-d', color=(0, 150, 250)),
    MethodSpec('gp-u', 'GP-U', 'gp-u', color=(170, 110, 30)),
    MethodSpec('gp-p', 'GP-P', 'gp-p', gp_p_adaptive=False, color=(180, 40, 160)),
    MethodSpec('gp-p-adaptive', 'GP-P adaptive', 'gp-p', gp_p_adaptive=True, color=(230, 150, 220)),
    MethodSpec('gp-g', 'GP-G', 'gp-gpis-opt', color=(30, 150, 30)),
    MethodSpec('gp-g-reranked', 'GP-G re-ranked', 'gp-gpis-opt-reranked', color=(120, 200, 120)),
)
METHOD_BY_KEY = {m.key: m for m in METHODS}
#: The paper's Table I columns, in order.
PAPER_COLUMNS = ('gp-m', 'gp-d', 'gp-u', 'gp-p', 'gp-g')

#: Mahler et al. ICRA 2015, Table I: P_F per method and worst-case runtime (s) of GP-P and GP-G
#: (Matlab 2014a + CVX on a 2.7 GHz laptop). Reference values printed next to ours, never used
#: in any computation other than the side-by-side columns.
PAPER_TABLE1: dict[str, dict[str, float]] = {
    'A': {'gp-m': 0.72, 'gp-d': 0.43, 'gp-u': 0.13, 'gp-p': 0.99, 'gp-g': 0.99, 'time_gp-p': 645.5, 'time_gp-g': 110.9},
    'B': {'gp-m': 0.75, 'gp-d': 0.00, 'gp-u': 0.02, 'gp-p': 0.88, 'gp-g': 0.99, 'time_gp-p': 955.8, 'time_gp-g': 284.3},
    'C': {'gp-m': 0.18, 'gp-d': 0.22, 'gp-u': 0.02, 'gp-p': 0.60, 'gp-g': 0.31, 'time_gp-p': 921.9, 'time_gp-g': 253.8},
    'D': {'gp-m': 0.38, 'gp-d': 0.12, 'gp-u': 0.57, 'gp-p': 0.98, 'gp-g': 0.79, 'time_gp-p': 715.8, 'time_gp-g': 72.4},
    'E': {'gp-m': 0.40, 'gp-d': 0.24, 'gp-u': 0.32, 'gp-p': 0.78, 'gp-g': 0.57, 'time_gp-p': 1197.3,
          'time_gp-g': 253.8},
    'F': {'gp-m': 0.50, 'gp-d': 0.39, 'gp-u': 0.23, 'gp-p': 0.64, 'gp-g': 0.67, 'time_gp-p': 897.6, 'time_gp-g': 215.3},
    'G': {'gp-m': 0.75, 'gp-d': 0.00, 'gp-u': 0.01, 'gp-p': 0.91, 'gp-g': 0.37, 'time_gp-p': 848.7, 'time_gp-g': 84.3},
    'H': {'gp-m': 0.42, 'gp-d': 0.47, 'gp-u': 0.00, 'gp-p': 0.99, 'gp-g': 0.93, 'time_gp-p': 715.0, 'time_gp-g': 85.5},
}

#: Growth of the original implementation between M = 25 and M = 70 (seconds at 25, at 70), as
#: quoted in issue #7: one SCP initialisation, and drawing 1000 shape samples.
PAPER_SCALING: dict[str, tuple[float, float]] = {
    'gp_g_per_init_s': (8.4, 187.9),
    'sample_s': (1.5, 392.8),
}

#: Columns of results.csv that hold wall-clock times (excluded from serial/parallel identity).
TIME_COLUMNS = ('planning_time_s', 'evaluation_time_s')
OBJECT_TIME_COLUMNS = ('sensing_time_s', 'gpis_fit_time_s', 'object_wall_time_s')

REPO_ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class BenchmarkSettings:
    """Settings of the Table I run (paper defaults; lengths in metres, counts dimensionless)."""

    seeds: int = 3  # seeds 0 .. seeds-1
    grasp_samples: int = 1000  # K heuristic candidates of GP-M / GP-P
    shape_samples: int = 1000  # S shape samples for every Monte-Carlo P_F
    trials: int = 20  # simulated executions per grasp and seed
    n_initial_grasps: int = 20  # N_g
    uncertainty_penalty: float = 2.0  # λ per cell² of SDF variance
    grid_size: int = 25  # M of the GPIS grid
    blur_samples: int = 1000  # joint samples for the GPIS-Blur figures
    com_samples: int = 1000  # joint samples for the centre-of-mass spread

    def planner_params(self, spec: MethodSpec) -> PlannerParams:
        """:class:`~gpis_grasp_ros.planners.PlannerParams` of ``spec`` with these settings."""
        return PlannerParams(n_initial_grasps=self.n_initial_grasps, n_grasp_samples=self.grasp_samples,
                             n_shape_samples=self.shape_samples, uncertainty_penalty=self.uncertainty_penalty,
                             gp_p_adaptive=spec.gp_p_adaptive)


def derive_seed(*keys: int | str) -> int:
    """A 64-bit seed from integers and strings (strings hashed with CRC-32), process independent."""
    words = [int(k) if isinstance(k, (int, np.integer)) else zlib.crc32(str(k).encode('utf-8')) for k in keys]
    state = np.random.SeedSequence(words).generate_state(2, dtype=np.uint32)
    return (int(state[0]) << 32) | int(state[1])


def object_letter(name: str) -> str:
    """'A_tape_dispenser' → 'A' (the paper's object letter); other names are returned unchanged."""
    head = name.split('_', 1)[0]
    return head if len(head) == 1 and head.isalpha() else name


def default_bags() -> list[Path]:
    """The shipped bags (``bags/*.mcap`` of the repository, else of the working directory)."""
    for base in (REPO_ROOT / 'bags', Path('bags')):
        found = sorted(base.glob('*.mcap'))
        if found:
            return found
    return []


# ------------------------------------------------------------------------------------------
# Evaluation on the true shape
# ------------------------------------------------------------------------------------------


class TrueShape:
    """Ground truth of a bag prepared for Q_N: SDF bank (m), centre of mass (m) and ρ (m)."""

    def __init__(self, sdf: np.ndarray, geometry: GridGeometry, center_of_mass: np.ndarray | None) -> None:
        self.sdf = np.asarray(sdf, dtype=np.float64)
        self.geometry = geometry
        self.com = (center_of_mass(self.sdf[None], geometry)[0] if center_of_mass is None
                    else np.asarray(center_of_mass, dtype=np.float64).reshape(2))
        self.rho = torque_scale(self.sdf, geometry, self.com)
        self.bank = SdfBank(self.sdf, geometry)

    def nominal_quality(self, jaw1: np.ndarray, jaw2: np.ndarray, gripper: GripperParams) -> tuple[float, str]:
        """Q_N: Ferrari–Canny L1 of the unperturbed grasp (m) on the true shape, and a status.

        Status 'ok' (Q_N may still be <= 0: no force closure), else 'no_contact', 'start_inside'
        or 'opening_exceeded' with Q_N = NaN.
        """
        j1 = np.asarray(jaw1, dtype=np.float64).reshape(1, 2)
        j2 = np.asarray(jaw2, dtype=np.float64).reshape(1, 2)
        if not (np.all(np.isfinite(j1)) and np.all(np.isfinite(j2))):
            return float('nan'), 'no_grasp'
        con = find_contacts(self.bank, j1, j2, gripper)
        for name in ('opening_exceeded', 'start_inside', 'no_contact'):
            if bool(getattr(con, name)[0]):
                return float('nan'), name
        q = ferrari_canny_l1(con.c1, con.c2, con.n1, con.n2, self.com, gripper.friction_coef, self.rho)
        return float(q[0]), 'ok'

    def outline(self) -> list[np.ndarray]:
        """Boundary polylines of {sdf < 0} in metres (outer outlines and holes)."""
        mask = (self.sdf < 0).astype(np.uint8)
        contours, _ = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
        return [self.geometry.to_metric(c.reshape(-1, 2).astype(np.float64)) for c in contours if len(c) >= 3]

    def iou_on(self, geometry: GridGeometry, mean_sdf: np.ndarray) -> float:
        """IoU of {mean_sdf < 0} with the true shape sampled at the cell centres of ``geometry``."""
        true_inside = bilinear(self.sdf, self.geometry, geometry.cell_centers()) < 0
        mean_inside = np.asarray(mean_sdf) < 0
        union = np.count_nonzero(true_inside | mean_inside)
        return float(np.count_nonzero(true_inside & mean_inside) / union) if union else float('nan')


def com_statistics(posterior: GpisPosterior, n: int, rng: np.random.Generator, chunk: int = 250) -> tuple[float, float]:
    """RMS and 95th percentile (m) of |z(f_i) − z(μ)| over ``n`` joint shape samples f_i.

    The RMS is :func:`~gpis_grasp_ros.gpis.com_spread`'s definition (condition 1 of section
    VI-A); the percentile is the radius of the paper's 95 % confidence region of the COM.
    """
    ref = posterior.center_of_mass()
    dist = []
    for start in range(0, n, chunk):
        m = min(chunk, n - start)
        com = center_of_mass(posterior.sample(m, rng), posterior.geometry)
        dist.append(np.linalg.norm(com - ref[None], axis=1))
    d = np.concatenate(dist)
    return float(np.sqrt(np.mean(d ** 2))), float(np.percentile(d, 95))


# ------------------------------------------------------------------------------------------
# One object (runs in a worker process)
# ------------------------------------------------------------------------------------------


@dataclass
class ObjectTask:
    """Work unit of a worker: one bag with the run's settings."""

    bag: str
    settings: BenchmarkSettings
    index: int = 0


@dataclass
class ObjectResult:
    """Everything the parent needs from one object (rows of results.csv, figure data)."""

    object: str
    letter: str
    bag: str
    rows: list[dict[str, Any]]
    info: dict[str, Any]
    geometry: GridGeometry
    blur: np.ndarray  # (H, W) uint8 GPIS-Blur on the planning grid
    outline: list[np.ndarray]  # true outline polylines (m)
    jaw_width: float  # m, for drawing
    grasps: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # first seed's grasps


_PROGRESS_QUEUE: Any = None  # set in workers by _worker_init


def _worker_init(progress_queue: Any) -> None:
    """Worker start-up: one BLAS thread (belt and braces: the environment already says so)."""
    global _PROGRESS_QUEUE
    _PROGRESS_QUEUE = progress_queue
    _limit_blas_threads_globally()


def _limit_blas_threads_globally() -> None:
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - optional dependency
        return
    threadpool_limits(limits=1)


def _run_object_in_worker(task: ObjectTask) -> ObjectResult:
    q = _PROGRESS_QUEUE
    return run_object(task, None if q is None else q.put)


def run_object(task: ObjectTask, report: Callable[[tuple[str, str]], None] | None = None) -> ObjectResult:
    """Build the GPIS of one bag and run every method for every seed (see the module docstring).

    ``report((object, method_key))`` is called after all seeds of a method are done.
    """
    t_object = time.perf_counter()
    s = task.settings
    bag = Path(task.bag)
    name = bag.stem
    letter = object_letter(name)
    scene = load_bag(bag)
    # posterior_from_scene, split in its two stages to time them separately.
    t0 = time.perf_counter()
    sensing = segment_frames(scene.rgb_frames, scene.depth_frames, scene.intrinsics,
                             SensingParams(grid_size=s.grid_size), frame_id=scene.frame_id)
    occ, noise, geometry = publishable_grids(sensing)
    t1 = time.perf_counter()
    posterior = posterior_from_grids(occ, noise, geometry)
    t2 = time.perf_counter()
    res = geometry.resolution
    truth = (TrueShape(scene.true_sdf, scene.true_geometry, scene.true_center_of_mass)
             if scene.true_sdf is not None and scene.true_geometry is not None else None)
    com_rms, com_p95 = com_statistics(posterior, s.com_samples, np.random.default_rng(derive_seed('com', name)))
    info: dict[str, Any] = {
        'object': name, 'letter': letter, 'bag': str(bag), 'grid_size': s.grid_size, 'resolution_m': res,
        'rank': int(posterior.rank), 'signal_std_m': math.sqrt(posterior.params.signal_variance),
        'length_scale_m': posterior.params.length_scale,
        'max_std_cells': float(np.sqrt(np.max(posterior.variance)) / res),
        'com_spread_rms_cells': com_rms / res, 'com_spread_p95_cells': com_p95 / res,
        'mean_shape_iou': truth.iou_on(geometry, posterior.mean) if truth is not None else float('nan'),
        'sensing_time_s': t1 - t0, 'gpis_fit_time_s': t2 - t1,
    }
    rows: list[dict[str, Any]] = []
    grasps: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    base_gripper = s.planner_params(METHODS[0]).gripper
    # σ_g and the contact-patch tolerance = 0.5 planning cell, fixed in metres for the true grid
    exec_gripper = base_gripper.resolved(geometry)
    for spec in METHODS:
        params = s.planner_params(spec)
        for seed in range(s.seeds):
            planner_seed = derive_seed('planner', seed, name)
            r = plan(spec.planner, posterior, params, seed=planner_seed)
            row: dict[str, Any] = {
                'object': name, 'letter': letter, 'method': spec.key, 'label': spec.label, 'seed': seed,
                'planner_seed': planner_seed, 'success': bool(r.success), 'message': r.message,
                'jaw1_x': float(r.jaw1[0]), 'jaw1_y': float(r.jaw1[1]),
                'jaw2_x': float(r.jaw2[0]), 'jaw2_y': float(r.jaw2[1]), 'width_m': float(r.width),
                'p_f': float(r.p_f), 'p_f_std_error': float(r.p_f_std_error), 'n_shape_samples': s.shape_samples,
                'q_f_mean': float(r.q_mean), 'objective': float(r.objective), 'iterations': int(r.iterations),
                'n_candidates': int(r.n_candidates),
            }
            if truth is not None and r.success:
                q_n, status = truth.nominal_quality(r.jaw1, r.jaw2, exec_gripper)
                gripper_seed = derive_seed('gripper', seed, name)
                succ = execute_grasp_trials(truth.sdf, truth.geometry, r.jaw1, r.jaw2, exec_gripper, s.trials,
                                            np.random.default_rng(gripper_seed), center_of_mass=truth.com)
            else:
                q_n, status, succ = float('nan'), 'no_grasp' if truth is not None else 'no_ground_truth', 0
            row.update({'q_n': q_n, 'q_n_status': status, 'sim_successes': int(succ), 'sim_trials': s.trials,
                        'sim_success_rate': succ / s.trials if s.trials > 0 else float('nan'),
                        'planning_time_s': float(r.planning_time), 'evaluation_time_s': float(r.evaluation_time)})
            rows.append(row)
            if seed == 0 and r.success:
                grasps[spec.key] = (np.asarray(r.jaw1, dtype=np.float64), np.asarray(r.jaw2, dtype=np.float64))
        if report is not None:
            report((name, spec.key))
    blur = gpis_blur(posterior, n_samples=s.blur_samples, rng=np.random.default_rng(derive_seed('blur', name)))
    info['object_wall_time_s'] = time.perf_counter() - t_object
    return ObjectResult(object=name, letter=letter, bag=str(bag), rows=rows, info=info, geometry=geometry,
                        blur=blur, outline=truth.outline() if truth is not None else [],
                        jaw_width=base_gripper.jaw_width, grasps=grasps)


# ------------------------------------------------------------------------------------------
# Running all objects (serial or in worker processes) with a progress bar
# ------------------------------------------------------------------------------------------


class ProgressBar:
    """Plain-text progress bar on a stream: done / total steps, elapsed time and estimated time left.

    On a terminal the line is redrawn in place; otherwise one line is written per step.
    """

    def __init__(self, total: int, unit: str = 'objects x methods', stream: Any = None, width: int = 28,
                 enabled: bool = True) -> None:
        self.total = max(int(total), 1)
        self.unit = unit
        self.stream = sys.stderr if stream is None else stream
        self.width = width
        self.enabled = enabled
        self.done = 0
        self.t0 = time.perf_counter()
        self._tty = bool(getattr(self.stream, 'isatty', lambda: False)())

    @staticmethod
    def _fmt(seconds: float) -> str:
        seconds = max(0, int(round(seconds)))
        return f'{seconds // 60:d}:{seconds % 60:02d}'

    def advance(self, label: str = '', steps: int = 1) -> None:
        self.done = min(self.total, self.done + steps)
        if not self.enabled:
            return
        elapsed = time.perf_counter() - self.t0
        left = elapsed / self.done * (self.total - self.done) if self.done else float('nan')
        fill = int(round(self.width * self.done / self.total))
        text = (f'[{"#" * fill}{"." * (self.width - fill)}] {self.done}/{self.total} {self.unit} '
                f'elapsed {self._fmt(elapsed)} left ~{self._fmt(left) if math.isfinite(left) else "?"} {label}')
        if self._tty:
            self.stream.write('\r' + text.ljust(110))
        else:
            self.stream.write(text + '\n')
        self.stream.flush()

    def close(self) -> None:
        if self.enabled and self._tty:
            self.stream.write('\n')
            self.stream.flush()


class _SingleThreadEnvironment(AbstractContextManager):
    """Temporarily set OPENBLAS/OMP/MKL thread counts to 1 (inherited by spawned workers)."""

    VARS = ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS', 'VECLIB_MAXIMUM_THREADS',
            'NUMEXPR_NUM_THREADS')

    def __enter__(self) -> _SingleThreadEnvironment:
        self._saved = {k: os.environ.get(k) for k in self.VARS}
        for k in self.VARS:
            os.environ[k] = '1'
        return self

    def __exit__(self, *exc: object) -> None:
        for k, v in self._saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _blas_one_thread() -> AbstractContextManager:
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover
        return nullcontext()
    return threadpool_limits(limits=1)


@dataclass
class BenchmarkResult:
    """All objects' results, the settings and the run's wall time (s)."""

    objects: list[ObjectResult]
    settings: BenchmarkSettings
    workers: int
    wall_time_s: float

    @property
    def rows(self) -> list[dict[str, Any]]:
        return [row for obj in self.objects for row in obj.rows]


def run_benchmark(bags: Sequence[str | os.PathLike[str]], settings: BenchmarkSettings = BenchmarkSettings(),
                  workers: int | None = None, progress: bool = True) -> BenchmarkResult:
    """Run :func:`run_object` for every bag, in ``workers`` spawned processes (1 = in this process)."""
    bags = [str(b) for b in bags]
    if not bags:
        raise ValueError('no bags to benchmark')
    tasks = [ObjectTask(b, settings, i) for i, b in enumerate(bags)]
    workers = max(1, min(int(workers or os.cpu_count() or 1), len(tasks)))
    bar = ProgressBar(len(tasks) * len(METHODS), enabled=progress)
    t0 = time.perf_counter()
    results: dict[int, ObjectResult] = {}
    if workers == 1:
        with _blas_one_thread():
            for task in tasks:
                results[task.index] = run_object(task, lambda item: bar.advance(f'{item[0]} {item[1]}'))
    else:
        ctx = mp.get_context('spawn')
        with _SingleThreadEnvironment():
            progress_queue = ctx.Queue()
            with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init,
                                     initargs=(progress_queue,)) as pool:
                futures: dict[Future, ObjectTask] = {pool.submit(_run_object_in_worker, t): t for t in tasks}
                pending = set(futures)
                while pending:
                    done, pending = wait(pending, timeout=0.25, return_when=FIRST_COMPLETED)
                    _drain(progress_queue, bar)
                    for fut in done:
                        results[futures[fut].index] = fut.result()
                _drain(progress_queue, bar, final=True)
            progress_queue.close()
            progress_queue.join_thread()
    bar.close()
    return BenchmarkResult([results[i] for i in range(len(tasks))], settings, workers, time.perf_counter() - t0)


def _drain(progress_queue: Any, bar: ProgressBar, final: bool = False) -> None:
    while True:
        try:
            item = progress_queue.get(timeout=0.2) if final and bar.done < bar.total else progress_queue.get_nowait()
        except queue.Empty:
            return
        bar.advance(f'{item[0]} {item[1]}')


# ------------------------------------------------------------------------------------------
# Aggregation and tables
# ------------------------------------------------------------------------------------------


@dataclass
class Cell:
    """Aggregate over seeds of one object × method."""

    p_f: float
    p_f_min: float
    p_f_max: float
    p_f_se: float  # mean Monte-Carlo standard error of one seed's estimate
    q_f_mean: float
    q_n: float  # mean over seeds, degenerate grasps counted as 0
    q_n_fc: int  # seeds whose grasp is in force closure on the true shape (Q_N > 0)
    sim_successes: int
    sim_trials: int
    time_worst: float
    time_median: float
    n_seeds: int
    failures: int  # seeds without a grasp


def aggregate(rows: Iterable[dict[str, Any]]) -> dict[tuple[str, str], Cell]:
    """(object, method) → :class:`Cell` over the seeds in ``rows``."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault((row['object'], row['method']), []).append(row)
    out = {}
    for key, rs in groups.items():
        p = np.array([r['p_f'] for r in rs], dtype=np.float64)
        qn = np.array([r['q_n'] for r in rs], dtype=np.float64)
        qf = np.array([r['q_f_mean'] for r in rs], dtype=np.float64)
        t = np.array([r['planning_time_s'] for r in rs], dtype=np.float64)
        out[key] = Cell(p_f=float(p.mean()), p_f_min=float(p.min()), p_f_max=float(p.max()),
                        p_f_se=float(np.mean([r['p_f_std_error'] for r in rs])),
                        q_f_mean=float(np.nanmean(qf)) if np.isfinite(qf).any() else float('nan'),
                        q_n=float(np.mean(np.nan_to_num(qn, nan=0.0))), q_n_fc=int(np.count_nonzero(qn > 0)),
                        sim_successes=int(sum(r['sim_successes'] for r in rs)),
                        sim_trials=int(sum(r['sim_trials'] for r in rs)),
                        time_worst=float(t.max()), time_median=float(np.median(t)), n_seeds=len(rs),
                        failures=sum(1 for r in rs if not r['success']))
    return out


def goal_figures(result: BenchmarkResult) -> dict[str, Any]:
    """The issue's goal figures, measured (reported, not asserted)."""
    cells = aggregate(result.rows)
    objs = [o.object for o in result.objects]
    by = {o.object: o for o in result.objects}
    n = len(objs)
    within = [o for o in objs if cells[(o, 'gp-g')].p_f >= cells[(o, 'gp-p')].p_f - 0.05]
    above_m = [o for o in objs if cells[(o, 'gp-g')].p_f > cells[(o, 'gp-m')].p_f]
    ratios = {by[o].letter: cells[(o, 'gp-p')].time_worst / max(cells[(o, 'gp-g')].time_worst, 1e-9) for o in objs}
    med = [cells[(o, 'gp-p')].time_median / max(cells[(o, 'gp-g')].time_median, 1e-9) for o in objs]
    out: dict[str, Any] = {
        'time_ratio_median_mean': float(np.mean(med)) if med else float('nan'),
        'n_objects': n,
        'gp_g_within_0.05_of_gp_p': [by[o].letter for o in within],
        'gp_g_above_gp_m': [by[o].letter for o in above_m],
        'time_ratio_gp_p_over_gp_g_worst': ratios,
        'time_ratio_mean': float(np.mean(list(ratios.values()))) if ratios else float('nan'),
        'time_ratio_median_per_object': {by[o].letter: cells[(o, 'gp-p')].time_median
                                         / max(cells[(o, 'gp-g')].time_median, 1e-9) for o in objs},
        'time_ratio_of_mean_times': float(np.mean([cells[(o, 'gp-p')].time_worst for o in objs])
                                          / max(np.mean([cells[(o, 'gp-g')].time_worst for o in objs]), 1e-9)),
    }
    a = [o for o in objs if by[o].letter == 'A']
    if a:
        for key in ('gp-m', 'gp-p', 'gp-g', 'gp-g-reranked'):
            c = cells[(a[0], key)]
            out[f'A_sim_success_{key}'] = c.sim_successes / max(c.sim_trials, 1)
    return out


def _f2(x: float) -> str:
    return '—' if not math.isfinite(x) else f'{x:.2f}'


def _ratio(x: float) -> str:
    return f'{x:.1f}x' if x < 10 else f'{x:.0f}x'


def _rate(successes: int, trials: int) -> str:
    return f'{successes}/{trials} ({successes / max(trials, 1):.2f})'


def _time(x: float) -> str:
    if not math.isfinite(x):
        return '—'
    return f'{x:.3f}' if x < 1 else f'{x:.2f}' if x < 100 else f'{x:.0f}'


def _table(header: Sequence[str], rows: Sequence[Sequence[str]], align: str | None = None) -> list[str]:
    align = align or 'l' + 'r' * (len(header) - 1)
    sep = ['---:' if a == 'r' else '---' for a in align]
    lines = ['| ' + ' | '.join(header) + ' |', '| ' + ' | '.join(sep) + ' |']
    lines += ['| ' + ' | '.join(r) + ' |' for r in rows]
    return lines


def table1_markdown(result: BenchmarkResult) -> str:
    """The contents of ``table1.md`` (see the module docstring)."""
    s = result.settings
    cells = aggregate(result.rows)
    objs = result.objects
    lines = [
        '# Table I — probability of force closure and runtime (ours vs. the paper)', '',
        f'{len(objs)} objects (simulated Carmine bags), GPIS on {s.grid_size} x {s.grid_size} cells built as the '
        f'nodes build it; N_g = {s.n_initial_grasps}, λ = {s.uncertainty_penalty:g}, K = {s.grasp_samples} grasp '
        f'samples, S = {s.shape_samples} shape samples, σ_g = 0.5 cell, {s.seeds} seed(s). GP-P is brute force '
        '(every candidate scored on all S samples), as in the paper.', '',
        f'P_F: mean over seeds of the Monte-Carlo estimate on S = {s.shape_samples} evaluation shape samples '
        f'(std error of one estimate ≤ {0.5 / math.sqrt(max(s.shape_samples, 1)):.3f}); the paper\'s value in '
        'parentheses. Runtime: worst case over seeds of the planning time (s) on this machine, one core per '
        'object; the paper\'s worst-case runtime (Matlab, 2.7 GHz laptop) and time ratio in parentheses.', '',
    ]
    header = ['Object'] + [METHOD_BY_KEY[k].label for k in PAPER_COLUMNS] + ['GP-P time (s)', 'GP-G time (s)',
                                                                                 'GP-P / GP-G']
    rows = []
    for o in objs:
        paper = PAPER_TABLE1.get(o.letter, {})
        r = [o.letter]
        for k in PAPER_COLUMNS:
            c = cells[(o.object, k)]
            ref = f' ({paper[k]:.2f})' if k in paper else ''
            r.append(f'{_f2(c.p_f)}{ref}' + (f' [{c.failures} failed]' if c.failures else ''))
        tp, tg = cells[(o.object, 'gp-p')].time_worst, cells[(o.object, 'gp-g')].time_worst
        r.append(_time(tp) + (f' ({paper["time_gp-p"]:g})' if paper else ''))
        r.append(_time(tg) + (f' ({paper["time_gp-g"]:g})' if paper else ''))
        ratio_ref = f' ({paper["time_gp-p"] / paper["time_gp-g"]:.1f}x)' if paper else ''
        r.append(f'{tp / max(tg, 1e-9):.1f}x{ratio_ref}')
        rows.append(r)
    lines += _table(header, rows)
    g = goal_figures(result)
    n = g['n_objects']
    lines += ['', f'GP-G P_F ≥ GP-P − 0.05 on {len(g["gp_g_within_0.05_of_gp_p"])} of {n} objects '
              f'({", ".join(g["gp_g_within_0.05_of_gp_p"]) or "none"}); GP-G P_F > GP-M on '
              f'{len(g["gp_g_above_gp_m"])} of {n} ({", ".join(g["gp_g_above_gp_m"]) or "none"}). '
              f'Worst-case time ratio GP-P / GP-G: mean over objects {g["time_ratio_mean"]:.1f}x '
              f'(ratio of the mean worst-case times {g["time_ratio_of_mean_times"]:.1f}x; mean over objects of the '
              f'median-time ratio {g["time_ratio_median_mean"]:.1f}x; paper: 5.7x).', '']

    extra = [METHOD_BY_KEY[k] for k in ('gp-m', 'gp-d', 'gp-u', 'gp-p', 'gp-p-adaptive', 'gp-g', 'gp-g-reranked')]
    lines += ['## Beyond the paper: re-ranked GP-G, adaptive GP-P, centre-of-mass spread', '',
              'P_F (mean over seeds; min–max over seeds in brackets), median / worst planning time (s), COM spread '
              'over 1000 joint shape samples (RMS and 95th percentile of the distance to the mean shape\'s COM, '
              'in cells; the paper\'s condition 1 asks for < 1 cell), IoU of the mean shape with the true shape.', '']
    header = ['Object', 'GP-G P_F', 'GP-G re-ranked P_F', 'GP-G re-ranked time', 'GP-P adaptive P_F',
              'GP-P adaptive time', 'GP-G time', 'COM spread RMS / p95 (cells)', 'mean-shape IoU']
    rows = []
    for o in objs:
        g_, rr, pa = (cells[(o.object, k)] for k in ('gp-g', 'gp-g-reranked', 'gp-p-adaptive'))
        rows.append([o.letter, f'{_f2(g_.p_f)} [{_f2(g_.p_f_min)}–{_f2(g_.p_f_max)}]',
                     f'{_f2(rr.p_f)} [{_f2(rr.p_f_min)}–{_f2(rr.p_f_max)}]',
                     f'{_time(rr.time_median)} / {_time(rr.time_worst)}',
                     f'{_f2(pa.p_f)} [{_f2(pa.p_f_min)}–{_f2(pa.p_f_max)}]',
                     f'{_time(pa.time_median)} / {_time(pa.time_worst)}',
                     f'{_time(g_.time_median)} / {_time(g_.time_worst)}',
                     f'{o.info["com_spread_rms_cells"]:.2f} / {o.info["com_spread_p95_cells"]:.2f}',
                     _f2(o.info['mean_shape_iou'])])
    lines += _table(header, rows)

    lines += ['', '## Q_N — Ferrari–Canny quality of the planned grasp on the true shape', '',
              'Mean over seeds of Q_N (unperturbed grasp, true SDF, true centre of mass; a grasp that misses the '
              'true object or starts inside it counts as 0); in brackets the number of seeds whose grasp is in '
              'force closure on the true shape (Q_N > 0).', '']
    header = ['Object'] + [m.label for m in extra]
    rows = [[o.letter] + [f'{_f2(cells[(o.object, m.key)].q_n)} [{cells[(o.object, m.key)].q_n_fc}/'
                          f'{cells[(o.object, m.key)].n_seeds}]' for m in extra] for o in objs]
    lines += _table(header, rows)

    lines += ['', '## Simulated gripper on the true shape', '',
              f'Force-closure successes / executions ({s.trials} per seed, σ_g = 0.5 planning cell, true centre of '
              'mass), summed over seeds.', '']
    rows = [[o.letter] + [_rate(cells[(o.object, m.key)].sim_successes, cells[(o.object, m.key)].sim_trials)
                          for m in extra] for o in objs]
    lines += _table(header, rows)

    lines += ['', '## Q_F on the GPIS mean shape', '', 'Mean over seeds (— : degenerate on the mean).', '']
    rows = [[o.letter] + [_f2(cells[(o.object, m.key)].q_f_mean) for m in extra] for o in objs]
    lines += _table(header, rows)

    lines += ['', '## Planning time (s): median / worst case over seeds', '']
    rows = [[o.letter] + [f'{_time(c.time_median)} / {_time(c.time_worst)}'
                          for c in (cells[(o.object, m.key)] for m in extra)] for o in objs]
    lines += _table(header, rows)
    lines += ['', f'Wall time of the run: {result.wall_time_s:.1f} s with {result.workers} worker process(es) '
              f'on {os.cpu_count()} CPU core(s).', '']
    return '\n'.join(lines)


def write_results_csv(path: Path, rows: Sequence[dict[str, Any]]) -> Path:
    """One row per object × method × seed (columns in the order of the first row)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, 'w', newline='') as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0].keys()))
        writer.writeheader()
        for r in rows:
            writer.writerow({k: (f'{v:.10g}' if isinstance(v, float) else v) for k, v in r.items()})
    return path


def write_outputs(result: BenchmarkResult, out: Path, figures: bool = True) -> list[Path]:
    """Write table1.md, results.csv, objects.csv, summary.json and (optionally) the PNG figures."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = [write_results_csv(out / 'results.csv', result.rows),
             write_results_csv(out / 'objects.csv', [o.info for o in result.objects])]
    (out / 'table1.md').write_text(table1_markdown(result))
    paths.append(out / 'table1.md')
    summary = {'settings': asdict(result.settings), 'workers': result.workers, 'wall_time_s': result.wall_time_s,
               'cpu_count': os.cpu_count(), 'platform': platform.platform(), 'python': platform.python_version(),
               'goal_figures': goal_figures(result)}
    (out / 'summary.json').write_text(json.dumps(summary, indent=2))
    paths.append(out / 'summary.json')
    if figures:
        paths.append(_write_png(out / 'pf_bars.png', pf_bar_chart(result)))
        paths.append(_write_png(out / 'runtime.png', runtime_chart(result)))
        paths.append(_write_png(out / 'fig4.png', fig4_figure(result)))
        for o in result.objects:
            paths.append(_write_png(out / 'objects' / f'{o.object}.png', object_figure(o, aggregate(o.rows))))
    return paths


def _write_png(path: Path, img_bgr: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), img_bgr, [cv2.IMWRITE_PNG_COMPRESSION, 9]):
        raise OSError(f'could not write {path}')
    return path


# ------------------------------------------------------------------------------------------
# Plotting with cv2 primitives
# ------------------------------------------------------------------------------------------

FONT = cv2.FONT_HERSHEY_SIMPLEX
WHITE = (255, 255, 255)
BLACK = (0, 0, 0)
GREY = (200, 200, 200)


def _text(img: np.ndarray, s: str, org: tuple[float, float], scale: float = 0.42, color: tuple[int, int, int] = BLACK,
          anchor: str = 'left', thickness: int = 1) -> None:
    """Text with its baseline at ``org``; ``anchor`` 'left', 'center' or 'right' (horizontal)."""
    (w, _h), _ = cv2.getTextSize(s, FONT, scale, thickness)
    x = org[0] - (w / 2 if anchor == 'center' else w if anchor == 'right' else 0)
    cv2.putText(img, s, (int(round(x)), int(round(org[1]))), FONT, scale, color, thickness, cv2.LINE_AA)


def _vtext(img: np.ndarray, s: str, center: tuple[int, int], scale: float = 0.42) -> None:
    """Text rotated by 90° (reading bottom-up) centred at ``center``."""
    (w, h), base = cv2.getTextSize(s, FONT, scale, 1)
    tile = np.full((h + base + 4, w + 4, 3), 255, np.uint8)
    cv2.putText(tile, s, (2, h + 1), FONT, scale, BLACK, 1, cv2.LINE_AA)
    tile = cv2.rotate(tile, cv2.ROTATE_90_COUNTERCLOCKWISE)
    th, tw = tile.shape[:2]
    y0, x0 = max(0, center[1] - th // 2), max(0, center[0] - tw // 2)
    y1, x1 = min(img.shape[0], y0 + th), min(img.shape[1], x0 + tw)
    img[y0:y1, x0:x1] = np.minimum(img[y0:y1, x0:x1], tile[:y1 - y0, :x1 - x0])


@dataclass
class Axes:
    """Plot area of an image: data (x, y) → pixels, linear or log10 axes."""

    img: np.ndarray
    box: tuple[int, int, int, int]  # left, top, right, bottom (pixels)
    xlim: tuple[float, float]
    ylim: tuple[float, float]
    xlog: bool = False
    ylog: bool = False

    @staticmethod
    def _frac(v: float, lim: tuple[float, float], log: bool) -> float:
        if log:
            v = math.log10(max(v, 1e-300))
            lo, hi = math.log10(lim[0]), math.log10(lim[1])
        else:
            lo, hi = lim
        return (v - lo) / (hi - lo)

    def px(self, x: float, y: float) -> tuple[int, int]:
        left, top, right, bottom = self.box
        fx = self._frac(x, self.xlim, self.xlog)
        fy = self._frac(y, self.ylim, self.ylog)
        return int(round(left + fx * (right - left))), int(round(bottom - fy * (bottom - top)))

    def ypx(self, y: float) -> int:
        return self.px(self.xlim[0], y)[1]

    def xpx(self, x: float) -> int:
        return self.px(x, self.ylim[0])[0]

    def frame(self, title: str, ylabel: str, xlabel: str = '', yticks: Sequence[float] | None = None,
              xticks: Sequence[tuple[float, str]] | None = None, minor_log_grid: bool = True) -> None:
        left, top, right, bottom = self.box
        img = self.img
        if yticks is None:
            yticks = _log_ticks(self.ylim) if self.ylog else list(np.linspace(self.ylim[0], self.ylim[1], 6))
        if self.ylog and minor_log_grid:
            for d in _log_ticks(self.ylim):
                for m in range(2, 10):
                    v = d * m
                    if self.ylim[0] <= v <= self.ylim[1]:
                        cv2.line(img, (left, self.ypx(v)), (right, self.ypx(v)), (238, 238, 238), 1)
        for v in yticks:
            y = self.ypx(v)
            cv2.line(img, (left, y), (right, y), (225, 225, 225), 1)
            cv2.line(img, (left - 4, y), (left, y), BLACK, 1)
            _text(img, _tick_label(v), (left - 7, y + 4), 0.38, anchor='right')
        if xticks:
            for x, label in xticks:
                xp = self.xpx(x)
                cv2.line(img, (xp, bottom), (xp, bottom + 4), BLACK, 1)
                _text(img, label, (xp, bottom + 18), 0.42, anchor='center')
        cv2.rectangle(img, (left, top), (right, bottom), BLACK, 1)
        _text(img, title, ((left + right) / 2, 20), 0.5, anchor='center')
        _vtext(img, ylabel, (14, (top + bottom) // 2))
        if xlabel:
            _text(img, xlabel, ((left + right) / 2, bottom + 38), 0.42, anchor='center')

    def legend(self, entries: Sequence[tuple[str, tuple[int, int, int], str]], y: int) -> None:
        """Entries (label, colour, kind 'box' | 'line' | 'tick') in one row at pixel height ``y``."""
        x = self.box[0]
        for label, color, kind in entries:
            if kind == 'box':
                cv2.rectangle(self.img, (x, y - 9), (x + 12, y + 1), color, -1)
            elif kind == 'tick':
                cv2.line(self.img, (x, y - 4), (x + 12, y - 4), color, 2)
            else:
                cv2.line(self.img, (x, y - 4), (x + 18, y - 4), color, 2, cv2.LINE_AA)
                cv2.circle(self.img, (x + 9, y - 4), 3, color, -1, cv2.LINE_AA)
            (w, _), _ = cv2.getTextSize(label, FONT, 0.4, 1)
            _text(self.img, label, (x + 22, y), 0.4)
            x += 22 + w + 16


def _log_ticks(lim: tuple[float, float]) -> list[float]:
    lo, hi = math.floor(math.log10(lim[0]) + 1e-9), math.ceil(math.log10(lim[1]) - 1e-9)
    return [10.0 ** e for e in range(lo, hi + 1) if lim[0] * (1 - 1e-9) <= 10.0 ** e <= lim[1] * (1 + 1e-9)]


def _tick_label(v: float) -> str:
    if v == 0:
        return '0'
    if abs(v) >= 1000 or abs(v) < 0.01:
        return f'{v:.0e}'.replace('e+0', 'e').replace('e-0', 'e-')
    return f'{v:g}'


def grouped_bar_chart(groups: Sequence[str], series: Sequence[tuple[str, tuple[int, int, int]]], values: np.ndarray,
                      title: str, ylabel: str, ylim: tuple[float, float], ylog: bool = False,
                      whiskers: tuple[np.ndarray, np.ndarray] | None = None, markers: np.ndarray | None = None,
                      marker_label: str = '', annotations: Sequence[str] | None = None,
                      size: tuple[int, int] = (980, 430)) -> np.ndarray:
    """Grouped bars ``values (G, S)`` (BGR image). ``whiskers`` (lo, hi) and ``markers`` (black ticks,
    NaN = none) have the same shape; ``annotations`` one string above each group."""
    width, height = size
    img = np.full((height, width, 3), 255, np.uint8)
    ax = Axes(img, (70, 62, width - 15, height - 50), (0.0, float(len(groups))), ylim, ylog=ylog)
    ax.frame(title, ylabel, xticks=[(i + 0.5, g) for i, g in enumerate(groups)])
    n_s = len(series)
    bar_w = 0.8 / n_s
    base = ylim[0]
    for gi in range(len(groups)):
        for si, (_label, color) in enumerate(series):
            v = float(values[gi, si])
            x0 = gi + 0.1 + si * bar_w
            if math.isfinite(v):
                p0 = ax.px(x0, max(v, ylim[0]) if ylog else v)
                p1 = ax.px(x0 + bar_w * 0.92, base)
                cv2.rectangle(img, (p0[0], min(p0[1], p1[1])), (max(p1[0], p0[0] + 1), p1[1]), color, -1)
            xc = x0 + 0.46 * bar_w
            if whiskers is not None:
                lo, hi = float(whiskers[0][gi, si]), float(whiskers[1][gi, si])
                if math.isfinite(lo) and math.isfinite(hi) and hi > lo:
                    a, b = ax.px(xc, hi), ax.px(xc, lo)
                    cv2.line(img, a, b, (60, 60, 60), 1)
                    cv2.line(img, (a[0] - 2, a[1]), (a[0] + 2, a[1]), (60, 60, 60), 1)
                    cv2.line(img, (b[0] - 2, b[1]), (b[0] + 2, b[1]), (60, 60, 60), 1)
            if markers is not None and math.isfinite(float(markers[gi, si])):
                p = ax.px(xc, float(markers[gi, si]))
                half = max(2, int(0.5 * bar_w * (ax.box[2] - ax.box[0]) / len(groups)))
                cv2.line(img, (p[0] - half, p[1]), (p[0] + half, p[1]), BLACK, 2)
        if annotations:
            _text(img, annotations[gi], (ax.xpx(gi + 0.5), ax.box[1] + 14), 0.38, (60, 60, 60), anchor='center')
    entries = [(label, color, 'box') for label, color in series]
    if markers is not None and marker_label:
        entries.append((marker_label, BLACK, 'tick'))
    ax.legend(entries, 44)
    return img


def line_chart(series: Sequence[tuple[str, tuple[int, int, int], np.ndarray, np.ndarray]], title: str, xlabel: str,
               ylabel: str, xlim: tuple[float, float], ylim: tuple[float, float], xlog: bool = True,
               ylog: bool = True, xticks: Sequence[float] | None = None,
               fits: Sequence[tuple[tuple[int, int, int], float, float]] | None = None,
               size: tuple[int, int] = (820, 470)) -> np.ndarray:
    """Lines with markers (BGR image); ``fits`` (colour, c, k) draw dashed t = c x^k."""
    width, height = size
    img = np.full((height, width, 3), 255, np.uint8)
    rows = math.ceil(len(series) / 3)
    top = 40 + 18 * rows
    ax = Axes(img, (70, top, width - 20, height - 55), xlim, ylim, xlog=xlog, ylog=ylog)
    ticks = [(v, f'{v:g}') for v in (xticks if xticks is not None else np.linspace(*xlim, 5))]
    ax.frame(title, ylabel, xlabel, xticks=ticks)
    for color, c, k in fits or []:
        xs = np.geomspace(xlim[0], xlim[1], 40) if xlog else np.linspace(xlim[0], xlim[1], 40)
        pts = [ax.px(x, c * x ** k) for x in xs]
        for i in range(0, len(pts) - 1, 2):
            cv2.line(img, pts[i], pts[i + 1], color, 1, cv2.LINE_AA)
    for _label, color, xs, ys in series:
        ok = np.isfinite(ys) & (ys > 0 if ylog else True)
        pts = [ax.px(float(x), float(y)) for x, y in zip(xs[ok], ys[ok], strict=True)]
        for a, b in zip(pts[:-1], pts[1:], strict=True):
            cv2.line(img, a, b, color, 2, cv2.LINE_AA)
        for p in pts:
            cv2.circle(img, p, 4, color, -1, cv2.LINE_AA)
    for r in range(rows):
        ax.legend([(label, color, 'line') for label, color, _, _ in series[3 * r:3 * r + 3]], 44 + 18 * r)
    return img


def pf_bar_chart(result: BenchmarkResult) -> np.ndarray:
    """P_F per object and method (mean over seeds, whiskers min–max), the paper's value as a tick."""
    keys = ('gp-m', 'gp-d', 'gp-u', 'gp-p', 'gp-g', 'gp-g-reranked')
    cells = aggregate(result.rows)
    objs = result.objects
    vals = np.array([[cells[(o.object, k)].p_f for k in keys] for o in objs])
    lo = np.array([[cells[(o.object, k)].p_f_min for k in keys] for o in objs])
    hi = np.array([[cells[(o.object, k)].p_f_max for k in keys] for o in objs])
    paper = np.array([[PAPER_TABLE1.get(o.letter, {}).get(k, np.nan) for k in keys] for o in objs])
    s = result.settings
    return grouped_bar_chart([o.letter for o in objs], [(METHOD_BY_KEY[k].label, METHOD_BY_KEY[k].color) for k in keys],
                             vals, f'P_F per object and method (mean of {s.seeds} seed(s), S = {s.shape_samples}; '
                             'whiskers: min-max over seeds)', 'probability of force closure P_F', (0.0, 1.0),
                             whiskers=(lo, hi), markers=paper, marker_label='paper')


def runtime_chart(result: BenchmarkResult) -> np.ndarray:
    """Worst-case planning time (log scale) of GP-P (brute force and adaptive) and GP-G per object."""
    keys = ('gp-p', 'gp-p-adaptive', 'gp-g', 'gp-g-reranked')
    cells = aggregate(result.rows)
    objs = result.objects
    vals = np.array([[cells[(o.object, k)].time_worst for k in keys] for o in objs])
    finite = vals[np.isfinite(vals) & (vals > 0)]
    lo = 10.0 ** math.floor(math.log10(finite.min())) if finite.size else 1e-3
    hi = 10.0 ** math.ceil(math.log10(finite.max())) if finite.size else 1.0
    if hi <= lo:
        hi = lo * 10
    ratios = [_ratio(cells[(o.object, 'gp-p')].time_worst / max(cells[(o.object, 'gp-g')].time_worst, 1e-9))
              for o in objs]
    return grouped_bar_chart([o.letter for o in objs], [(METHOD_BY_KEY[k].label, METHOD_BY_KEY[k].color) for k in keys],
                             vals, 'Worst-case planning time per object (log scale; label: GP-P / GP-G)',
                             'planning time (s)', (lo, hi), ylog=True, annotations=ratios)


def grasp_panel(blur: np.ndarray, geometry: GridGeometry, outline: Sequence[np.ndarray],
                grasp: tuple[np.ndarray, np.ndarray] | None, color: tuple[int, int, int], title: str, subtitle: str,
                jaw_width: float, panel_px: int = 240) -> np.ndarray:
    """One Fig. 4 panel (BGR): GPIS-Blur, true outline (green), the grasp, a title and a subtitle."""
    h, w = geometry.shape
    scale = max(1, int(round(panel_px / max(h, w))))
    img = cv2.resize(to_color(blur), (w * scale, h * scale), interpolation=cv2.INTER_LINEAR)
    for poly in outline:
        p = np.rint(metric_to_pixel(geometry, poly, scale) * 8 - 4).astype(np.int32)  # 3 fractional bits
        cv2.polylines(img, [p.reshape(-1, 1, 2)], True, (0, 170, 0), 1, cv2.LINE_AA, shift=3)
    if grasp is not None:
        draw_grasp(img, geometry, grasp[0], grasp[1], scale, color, None, jaw_width_m=jaw_width, thickness=2)
    header = np.full((36, img.shape[1], 3), 255, np.uint8)
    _text(header, title, (5, 14), 0.45)
    _text(header, subtitle, (5, 30), 0.36, (60, 60, 60))
    return np.vstack([header, img])


def _tile(panels: Sequence[Sequence[np.ndarray]], gap: int = 6) -> np.ndarray:
    """Rows of equally tall panels → one image (rows padded to the widest)."""
    rows = []
    for row in panels:
        parts = []
        for i, p in enumerate(row):
            if i:
                parts.append(np.full((p.shape[0], gap, 3), 255, np.uint8))
            parts.append(p)
        rows.append(np.hstack(parts))
    width = max(r.shape[1] for r in rows)
    out = []
    for i, r in enumerate(rows):
        if i:
            out.append(np.full((gap, width, 3), 255, np.uint8))
        out.append(np.hstack([r, np.full((r.shape[0], width - r.shape[1], 3), 255, np.uint8)]) if r.shape[1] < width
                   else r)
    return np.vstack(out)


def _panel_for(o: ObjectResult, cells: dict[tuple[str, str], Cell], key: str, title_prefix: str = '',
               panel_px: int = 240) -> np.ndarray:
    spec = METHOD_BY_KEY[key]
    row0 = next((r for r in o.rows if r['method'] == key and r['seed'] == 0), None)
    if row0 is None or not row0['success']:
        sub = 'no grasp'
    else:
        qn = f'{row0["q_n"]:.2f}' if math.isfinite(row0['q_n']) else row0['q_n_status']
        sub = f'P_F={row0["p_f"]:.2f}  Q_N={qn}  sim {row0["sim_successes"]}/{row0["sim_trials"]}'
    return grasp_panel(o.blur, o.geometry, o.outline, o.grasps.get(key), spec.color, f'{title_prefix}{spec.label}',
                       sub, o.jaw_width, panel_px)


def object_figure(o: ObjectResult, cells: dict[tuple[str, str], Cell]) -> np.ndarray:
    """Every method's seed-0 grasp on the object's GPIS-Blur, 2 rows x 3 panels (BGR)."""
    keys = ('gp-m', 'gp-d', 'gp-u', 'gp-p', 'gp-g', 'gp-g-reranked')
    panels = [_panel_for(o, cells, k, f'{o.letter}: ') for k in keys]
    body = _tile([panels[:3], panels[3:]])
    header = np.full((28, body.shape[1], 3), 255, np.uint8)
    _text(header, f'{o.object}: GPIS-Blur (dark = object), true outline green, seed-0 grasps', (5, 19), 0.5)
    return np.vstack([header, body])


def fig4_figure(result: BenchmarkResult) -> np.ndarray:
    """The paper's Fig. 4: objects A-D (or the first four) x GP-M, GP-P, GP-G (BGR)."""
    cells = aggregate(result.rows)
    objs = [o for o in result.objects if o.letter in 'ABCD'] or result.objects[:4]
    rows = [[_panel_for(o, cells, k, f'{o.letter}: ', 220) for k in ('gp-m', 'gp-p', 'gp-g')] for o in objs[:4]]
    body = _tile(rows)
    header = np.full((28, body.shape[1], 3), 255, np.uint8)
    _text(header, 'Fig. 4: GP-M / GP-P / GP-G on GPIS-Blur (green: true outline)', (5, 19), 0.5)
    return np.vstack([header, body])


# ------------------------------------------------------------------------------------------
# Scaling with the grid size M
# ------------------------------------------------------------------------------------------


def fit_power_law(sizes: Sequence[float], times: Sequence[float]) -> tuple[float, float]:
    """Least-squares fit of log t = log c + k log M; returns (c, k). Needs >= 2 positive points."""
    m = np.asarray(sizes, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64)
    ok = np.isfinite(m) & np.isfinite(t) & (m > 0) & (t > 0)
    if np.count_nonzero(ok) < 2 or np.unique(m[ok]).size < 2:
        raise ValueError('need at least two distinct positive sizes with positive times')
    k, log_c = np.polyfit(np.log(m[ok]), np.log(t[ok]), 1)
    return float(math.exp(log_c)), float(k)


SCALING_QUANTITIES: tuple[tuple[str, str, tuple[int, int, int]], ...] = (
    ('gpis_fit_s', 'GPIS fit', (170, 110, 30)),
    ('sample_s', 'S joint samples', (0, 150, 250)),
    ('gp_g_s', 'GP-G (N_g = 20)', (30, 150, 30)),
    ('gp_p_s', 'GP-P brute force', (180, 40, 160)),
    ('gp_p_adaptive_s', 'GP-P adaptive', (230, 150, 220)),
    ('segmentation_s', 'segmentation', (120, 120, 120)),
)


def _best_time(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    """Shortest wall time (s) of ``repeats`` calls and the last result (other load only adds time)."""
    times, out = [], None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(min(times)), out


def run_scaling(bag: str | os.PathLike[str], sizes: Sequence[int], settings: BenchmarkSettings = BenchmarkSettings(),
                repeats: int = 3, progress: bool = True) -> list[dict[str, Any]]:
    """Times (s) of the pipeline stages and planners vs the grid side M on one bag (one BLAS thread)."""
    scene = load_bag(bag)
    name = Path(bag).stem
    bar = ProgressBar(len(sizes), unit='grid sizes', enabled=progress)
    rows = []
    with _blas_one_thread():
        for m in sizes:
            params = SensingParams(grid_size=int(m))
            t_seg, grids = _best_time(lambda p=params: publishable_grids(
                segment_frames(scene.rgb_frames, scene.depth_frames, scene.intrinsics, p, frame_id=scene.frame_id)),
                repeats)
            t_fit, posterior = _best_time(lambda g=grids: posterior_from_grids(*g), repeats)
            rng_seed = derive_seed('scaling', name, int(m))
            t_samp, _ = _best_time(lambda po=posterior, sd=rng_seed: po.sample(settings.shape_samples,
                                                                                 np.random.default_rng(sd)), repeats)
            planned = {}
            for key in ('gp-g', 'gp-p-adaptive', 'gp-p'):
                spec = METHOD_BY_KEY[key]
                runs = [plan(spec.planner, posterior, settings.planner_params(spec), seed=rng_seed)
                        for _ in range(max(1, repeats))]
                planned[key] = (min(r.planning_time for r in runs), runs[-1])
            (t_g, g_res), (t_pa, pa_res), (t_p, p_res) = (planned[k] for k in ('gp-g', 'gp-p-adaptive', 'gp-p'))
            rows.append({
                'object': name, 'M': int(m), 'cells': int(m) ** 2, 'resolution_m': posterior.geometry.resolution,
                'rank': int(posterior.rank), 'approximation': posterior.approximation,
                'n_train': int(posterior.train_xy.shape[0]),
                'segmentation_s': t_seg, 'gpis_fit_s': t_fit, 'sample_s': t_samp,
                'gp_g_s': t_g, 'gp_g_per_init_s': t_g / settings.n_initial_grasps,
                'gp_g_iterations': int(g_res.iterations), 'gp_g_p_f': float(g_res.p_f),
                'gp_p_s': t_p, 'gp_p_p_f': float(p_res.p_f),
                'gp_p_adaptive_s': t_pa, 'gp_p_adaptive_p_f': float(pa_res.p_f),
                'grasp_samples': settings.grasp_samples, 'shape_samples': settings.shape_samples,
            })
            bar.advance(f'M={m}')
    bar.close()
    return rows


def scaling_markdown(rows: Sequence[dict[str, Any]], settings: BenchmarkSettings, repeats: int,
                     wall_time_s: float) -> str:
    """Contents of ``scaling.md``: times per M, fitted exponents, 70-vs-25 ratios vs the original."""
    name = rows[0]['object']
    sizes = [r['M'] for r in rows]
    lines = [f'# Runtime vs grid side M ({name})', '',
             f'GPIS built as the nodes build it with SensingParams(grid_size=M); GP-G with N_g = '
             f'{settings.n_initial_grasps}; GP-P with K = {settings.grasp_samples} candidates x S = '
             f'{settings.shape_samples} shape samples (brute force and adaptive successive halving); "S joint '
             f'samples" = drawing S = {settings.shape_samples} joint GPIS samples. Best (shortest) of {repeats} '
             'run(s) of each, one BLAS thread, times in seconds (planning time of the planners, as in Table I).', '']
    header = ['M', 'cells', 'rank r', 'segmentation', 'GPIS fit', 'S samples', 'GP-G', 'GP-G per init',
              'GP-P brute', 'GP-P adaptive', 'GP-P / GP-G']
    body = [[str(r['M']), str(r['cells']), str(r['rank']), _time(r['segmentation_s']), _time(r['gpis_fit_s']),
             _time(r['sample_s']), _time(r['gp_g_s']), _time(r['gp_g_per_init_s']), _time(r['gp_p_s']),
             _time(r['gp_p_adaptive_s']), f'{r["gp_p_s"] / max(r["gp_g_s"], 1e-9):.1f}x'] for r in rows]
    lines += _table(header, body)
    lines += ['', '## Fitted exponents k of t = c M^k (least squares on log t vs log M)', '']
    body = []
    for key, label, _ in SCALING_QUANTITIES:
        try:
            _, k = fit_power_law(sizes, [r[key] for r in rows])
            body.append([label, f'{k:.2f}', f'{k / 2:.2f}'])
        except ValueError:
            body.append([label, '—', '—'])
    lines += _table(['quantity', 'k (vs M)', 'k / 2 (vs cells M²)'], body)
    by_m = {r['M']: r for r in rows}
    if 25 in by_m and 70 in by_m:
        a, b = by_m[25], by_m[70]
        lines += ['', '## Growth from M = 25 to M = 70, compared with the original implementation', '',
                  'The paper\'s implementation (Matlab + CVX, exact GP): one SCP initialisation 8.4 s → 187.9 s, '
                  '1000 shape samples 1.5 s → 392.8 s. Ratios t(70) / t(25):', '']
        body = [
            ['GP-G per initialisation', f'{b["gp_g_per_init_s"] / a["gp_g_per_init_s"]:.1f}x',
             f'{PAPER_SCALING["gp_g_per_init_s"][1] / PAPER_SCALING["gp_g_per_init_s"][0]:.1f}x'],
            [f'{settings.shape_samples} shape samples', f'{b["sample_s"] / a["sample_s"]:.1f}x',
             f'{PAPER_SCALING["sample_s"][1] / PAPER_SCALING["sample_s"][0]:.1f}x'],
            ['GPIS fit', f'{b["gpis_fit_s"] / a["gpis_fit_s"]:.1f}x', '—'],
            ['GP-P brute force', f'{b["gp_p_s"] / a["gp_p_s"]:.1f}x', '—'],
            ['cells M²', f'{(70 / 25) ** 2:.1f}x', f'{(70 / 25) ** 2:.1f}x'],
        ]
        lines += _table(['quantity', 'ours', 'original'], body)
    lines += ['', f'Wall time of the scaling run: {wall_time_s:.1f} s on {os.cpu_count()} CPU core(s).', '']
    return '\n'.join(lines)


def scaling_chart(rows: Sequence[dict[str, Any]]) -> np.ndarray:
    """Log-log plot of the scaling times with their fitted power laws (BGR)."""
    sizes = np.array([r['M'] for r in rows], dtype=np.float64)
    series, fits, all_t = [], [], []
    for key, label, color in SCALING_QUANTITIES:
        t = np.array([r[key] for r in rows], dtype=np.float64)
        try:
            c, k = fit_power_law(sizes, t)
            fits.append((color, c, k))
            label = f'{label} (k={k:.2f})'
        except ValueError:
            pass
        series.append((label, color, sizes, t))
        all_t.append(t[np.isfinite(t) & (t > 0)])
    t_all = np.concatenate(all_t)
    ylim = (10.0 ** math.floor(math.log10(t_all.min())), 10.0 ** math.ceil(math.log10(t_all.max())))
    xlim = (sizes.min() * 0.9, sizes.max() * 1.1)
    return line_chart(series, f'Runtime vs grid side M ({rows[0]["object"]}); dashed: fitted c M^k', 'grid side M',
                      'time (s)', xlim, ylim, xticks=[float(m) for m in sizes], fits=fits)


# ------------------------------------------------------------------------------------------
# Command line
# ------------------------------------------------------------------------------------------


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='gpis-grasp benchmark', description=__doc__.splitlines()[0])
    p.add_argument('--bags', nargs='+', type=Path, default=None, help='bags to run (default: bags/*.mcap)')
    p.add_argument('--out', type=Path, default=Path('out/benchmark'), help='output directory (default: out/benchmark)')
    p.add_argument('--workers', type=int, default=os.cpu_count() or 1,
                   help='worker processes, 1 = serial in this process (default: os.cpu_count())')
    p.add_argument('--seeds', type=int, default=3, help='seeds 0 .. N-1 per object and method (default: 3)')
    p.add_argument('--grasp-samples', type=int, default=1000,
                   help='K heuristic grasp candidates of GP-M / GP-P (default: 1000)')
    p.add_argument('--shape-samples', type=int, default=1000,
                   help='S shape samples of every Monte-Carlo P_F (default: 1000)')
    p.add_argument('--trials', type=int, default=20, help='simulated executions per grasp and seed (default: 20)')
    p.add_argument('--grid-size', type=int, default=25, help='M of the M x M GPIS grid, Table I run (default: 25)')
    p.add_argument('--blur-samples', type=int, default=1000,
                   help='joint samples of the GPIS-Blur figures (default: 1000)')
    p.add_argument('--no-figures', action='store_true', help='skip the PNG figures')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    p.add_argument('--scaling', action='store_true', help='run the runtime-vs-M study instead of Table I')
    p.add_argument('--object', default='A', help='scaling: object letter or bag path (default: A)')
    p.add_argument('--sizes', default='25,40,55,70,100',
                   help='scaling: comma-separated grid sides M (default: 25,40,55,70,100)')
    p.add_argument('--repeats', type=int, default=3,
                   help='scaling: runs per timing, the shortest is kept (default: 3)')
    args = p.parse_args(argv)
    for name in ('seeds', 'grasp_samples', 'shape_samples', 'workers', 'grid_size', 'blur_samples', 'repeats'):
        if getattr(args, name) < 1:
            p.error(f'--{name.replace("_", "-")} must be >= 1')
    if args.trials < 0:
        p.error('--trials must be >= 0')
    return args


def _resolve_object(spec: str) -> Path:
    path = Path(spec)
    if path.suffix == '.mcap' and path.exists():
        return path
    for bag in default_bags():
        if object_letter(bag.stem).upper() == spec.upper() or bag.stem == spec:
            return bag
    raise FileNotFoundError(f'no bag for object {spec!r} in bags/')


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    settings = BenchmarkSettings(seeds=args.seeds, grasp_samples=args.grasp_samples,
                                 shape_samples=args.shape_samples, trials=args.trials, grid_size=args.grid_size,
                                 blur_samples=args.blur_samples)
    out: Path = args.out
    if args.scaling:
        try:
            bag = _resolve_object(args.object)
            sizes = [int(v) for v in str(args.sizes).split(',') if v.strip()]
        except (FileNotFoundError, ValueError) as exc:
            print(f'gpis-grasp benchmark: {exc}', file=sys.stderr)
            return 2
        t0 = time.perf_counter()
        rows = run_scaling(bag, sizes, settings, args.repeats, progress=not args.quiet)
        wall = time.perf_counter() - t0
        out.mkdir(parents=True, exist_ok=True)
        write_results_csv(out / 'scaling.csv', rows)
        text = scaling_markdown(rows, settings, args.repeats, wall)
        (out / 'scaling.md').write_text(text)
        if not args.no_figures:
            _write_png(out / 'scaling.png', scaling_chart(rows))
        print(text)
        print(f'wrote {out}/scaling.md, scaling.csv' + ('' if args.no_figures else ', scaling.png'))
        return 0
    bags = args.bags if args.bags is not None else default_bags()
    missing = [b for b in bags if not Path(b).exists()]
    if not bags or missing:
        print(f'gpis-grasp benchmark: bag(s) not found: {missing or "bags/*.mcap"}', file=sys.stderr)
        return 2
    result = run_benchmark(bags, settings, args.workers, progress=not args.quiet)
    write_outputs(result, out, figures=not args.no_figures)
    print(table1_markdown(result))
    print(f'wrote {out}/: table1.md, results.csv, objects.csv, summary.json'
          + ('' if args.no_figures else ', pf_bars.png, runtime.png, fig4.png, objects/*.png'))
    return 0


if __name__ == '__main__':
    sys.exit(main())
