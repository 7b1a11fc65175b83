"""Table I evaluation: methods, settings, one object per task, serial or worker processes."""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import queue
import sys
import time
import zlib
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from gpis_grasp_ros.core.blur import gpis_blur
from gpis_grasp_ros.core.contacts import GripperParams, SdfBank, bilinear, find_contacts
from gpis_grasp_ros.core.gpis import GpisPosterior, center_of_mass
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.pipeline import posterior_from_grids, publishable_grids
from gpis_grasp_ros.core.planners import PlannerParams, execute_grasp_trials, plan
from gpis_grasp_ros.core.quality import ferrari_canny_l1, torque_scale
from gpis_grasp_ros.core.sensing import SensingParams, segment_frames
from gpis_grasp_ros.data.bags import load_bag

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

REPO_ROOT = Path(__file__).resolve().parents[3]


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
        """:class:`~gpis_grasp_ros.core.planners.PlannerParams` of ``spec`` with these settings."""
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

    The RMS is :func:`~gpis_grasp_ros.core.gpis.com_spread`'s definition (condition 1 of section
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


