"""Table I evaluation: methods, settings, one object per task, serial or worker processes."""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from gpis_grasp_ros.core.blur import gpis_blur
from gpis_grasp_ros.core.gpis import GpisPosterior, center_of_mass
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.planners import PlannerParams, plan
from gpis_grasp_ros.core.planners.params import UNCERTAINTY_PENALTY
from gpis_grasp_ros.core.sensing import SensingParams
from gpis_grasp_ros.core.sensing.params import PAPER_GRID_SIZE
from gpis_grasp_ros.data.bags import load_bag
from gpis_grasp_ros.tools.benchmark.calibration import calibrate_object
from gpis_grasp_ros.tools.evaluation.runner import map_reporting
from gpis_grasp_ros.tools.evaluation.tasks import (
    EXECUTION_COLUMNS,
    PLAN_COLUMNS,
    PLAN_TIME_COLUMNS,
    GraspRecord,
    fit_scene,
)
from gpis_grasp_ros.tools.evaluation.truth import TrueShape
from gpis_grasp_ros.tools.seeds import derive_seed

# ------------------------------------------------------------------------------------------
# Methods, reference numbers, settings
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MethodSpec:
    """A benchmarked planner: ``key`` (CSV), ``label`` (tables), ``planner`` (planners.plan name).

    ``color`` is a matplotlib colour for the figures; ``extra`` marks methods that are not in the
    paper's Table I (shown in the "beyond the paper" tables only).
    """

    key: str
    label: str
    planner: str
    gp_p_adaptive: bool = False  # only used by 'gp-p'
    color: str = 'black'
    extra: bool = False


METHODS: tuple[MethodSpec, ...] = (
    MethodSpec('gp-m', 'GP-M', 'gp-m', color='#dc2828'),
    MethodSpec('gp-d', 'GP-D', 'gp-d', color='#fa9600'),
    MethodSpec('gp-u', 'GP-U', 'gp-u', color='#1e6eaa'),
    MethodSpec('gp-p', 'GP-P', 'gp-p', gp_p_adaptive=False, color='#a028b4'),
    MethodSpec('gp-g', 'GP-G', 'gp-gpis-opt', color='#1e961e'),
    MethodSpec('gp-p-adaptive', 'GP-P adaptive', 'gp-p', gp_p_adaptive=True, color='#dc96e6', extra=True),
    MethodSpec('gp-g-reranked', 'GP-G re-ranked', 'gp-gpis-opt-reranked', color='#78c878', extra=True),
    MethodSpec('gp-d-single', 'GP-D 1 start', 'gp-d-single', color='#fcd08c', extra=True),
    MethodSpec('gp-u-single', 'GP-U 1 start', 'gp-u-single', color='#8cb4dc', extra=True),
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

#: Growth of the original implementation between M = 25 and M = 70 (seconds at 25, at 70): one
#: SCP initialisation, and drawing 1000 shape samples. These figures are NOT in the paper (its
#: text only refers to "the supplementary file" for convergence and time complexity); they come
#: from the authors' code repository (Matlab + CVX, exact GP), as quoted in an earlier report of
#: this project. Used only for the side-by-side growth ratios of the scaling report.
PAPER_SCALING: dict[str, tuple[float, float]] = {
    'gp_g_per_init_s': (8.4, 187.9),
    'sample_s': (1.5, 392.8),
}

#: Columns of results.csv that hold wall-clock times (excluded from serial/parallel identity).
TIME_COLUMNS = ('planning_time_s', 'evaluation_time_s')
OBJECT_TIME_COLUMNS = ('sensing_time_s', 'gpis_fit_time_s', 'object_wall_time_s', 'calibration_time_s')

REPO_ROOT = Path(__file__).resolve().parents[3]


@dataclass(frozen=True)
class BenchmarkSettings:
    """Settings of the Table I run (paper defaults; lengths in metres, counts dimensionless)."""

    seeds: int = 3  # seeds 0 .. seeds-1
    grasp_samples: int = 1000  # K heuristic candidates of GP-M / GP-P
    shape_samples: int = 1000  # S shape samples for every Monte-Carlo P_F
    trials: int = 20  # simulated executions per grasp and seed
    n_initial_grasps: int = 20  # N_g
    uncertainty_penalty: float = UNCERTAINTY_PENALTY  # λ per m² of SDF variance
    grid_size: int = PAPER_GRID_SIZE  # M of the GPIS grid (the paper's 25); 0 = from the object and the cell size
    blur_samples: int = 1000  # joint samples for the GPIS-Blur figures
    com_samples: int = 1000  # joint samples for the centre-of-mass spread
    methods: tuple[str, ...] = tuple(m.key for m in METHODS)  # keys of METHODS to run, in this order
    calibration_candidates: int = 0  # calibration study: GP-P candidates per object (0 = no study)
    calibration_trials: int = 50  # simulated executions per grasp of the calibration study
    calibration_perturbations: int = 1000  # jaw perturbations of the mean-shape P̃_F estimates

    @property
    def method_specs(self) -> tuple[MethodSpec, ...]:
        """The :class:`MethodSpec` of every key in ``methods`` (KeyError for an unknown key)."""
        return tuple(METHOD_BY_KEY[k] for k in self.methods)

    def planner_params(self, spec: MethodSpec) -> PlannerParams:
        """:class:`~gpis_grasp_ros.core.planners.PlannerParams` of ``spec`` with these settings."""
        return PlannerParams(n_initial_grasps=self.n_initial_grasps, n_grasp_samples=self.grasp_samples,
                             n_shape_samples=self.shape_samples, uncertainty_penalty=self.uncertainty_penalty,
                             gp_p_adaptive=spec.gp_p_adaptive)


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
    #: GP-G seed 0, one entry per restart: objective history per SCP iteration and flags.
    convergence: list[dict[str, Any]] = field(default_factory=list)
    calibration: list[dict[str, Any]] = field(default_factory=list)  # rows of the calibration study


def _restart_history(info: Any) -> np.ndarray | None:
    """Objective (eq. 6, maximised) per SCP iteration of one restart, if the planner recorded it."""
    for name in ('objective_history', 'history'):
        h = getattr(info, name, None)
        if h is not None and len(h):
            arr = np.asarray(h, dtype=np.float64)
            if arr.ndim == 1:
                return arr
    return None


def _convergence_entries(result: Any) -> list[dict[str, Any]]:
    out = []
    for info in getattr(result, 'restarts', []) or []:
        out.append({'history': _restart_history(info), 'converged': bool(info.converged),
                    'feasible': bool(info.feasible), 'reason': str(info.reason), 'iterations': int(info.iterations),
                    'objective': float(info.objective)})
    return out


def _plan_or_failure(spec: MethodSpec, posterior: GpisPosterior, params: PlannerParams, seed: int) -> Any:
    """``plan(...)``; an exception inside a planner becomes a failed result whose message names it.

    The run goes on with the other methods and objects; the failure is counted in Table I
    ("[n failed]"), its message is in results.csv and it is printed on stderr.
    """
    t0 = time.perf_counter()
    try:
        return plan(spec.planner, posterior, params, seed=seed)
    except Exception as exc:  # noqa: BLE001 - reported, never swallowed
        message = f'planner raised {type(exc).__name__}: {exc}'
        print(f'gpis-grasp benchmark: {spec.key} (seed {seed}): {message}', file=sys.stderr)
        nan2 = np.full(2, np.nan)
        return PlanFailure(message=message, jaw1=nan2, jaw2=nan2, planning_time=time.perf_counter() - t0)


@dataclass
class PlanFailure:
    """Stand-in for a :class:`~gpis_grasp_ros.core.planners.GraspResult` of a planner that raised."""

    message: str
    jaw1: np.ndarray
    jaw2: np.ndarray
    planning_time: float
    success: bool = False
    width: float = float('nan')
    p_f: float = 0.0
    p_f_std_error: float = 0.0
    q_mean: float = float('nan')
    objective: float = float('nan')
    iterations: int = 0
    n_candidates: int = 0
    converged: bool = False
    evaluation_time: float = 0.0
    restarts: list = field(default_factory=list)


def run_object(task: ObjectTask, report: Callable[[tuple[str, str]], None] | None = None) -> ObjectResult:
    """Build the GPIS of one bag and run every method for every seed (see the module docstring).

    ``report((object, step))`` is called after all seeds of a method are done (and after the
    calibration study).
    """
    t_object = time.perf_counter()
    s = task.settings
    bag = Path(task.bag)
    name = bag.stem
    letter = object_letter(name)
    scene = load_bag(bag)
    fit = fit_scene(scene, SensingParams(grid_size=s.grid_size), relax_opening=True)
    posterior, refusal, geometry = fit.posterior, fit.refusal, fit.geometry
    res = geometry.resolution
    truth = (TrueShape(scene.true_sdf, scene.true_geometry, geometry, obstacles=scene.true_obstacles)
             if scene.true_sdf is not None and scene.true_geometry is not None else None)
    com_rms, com_p95 = com_statistics(posterior, s.com_samples, np.random.default_rng(derive_seed('com', name)))
    info: dict[str, Any] = {
        'object': name, 'letter': letter, 'bag': str(bag), 'grid_size': geometry.width, 'resolution_m': res,
        'rank': int(posterior.rank), 'signal_std_m': math.sqrt(posterior.params.signal_variance),
        'length_scale_m': posterior.params.length_scale,
        'max_std_cells': float(np.sqrt(np.max(posterior.variance)) / res),
        'com_spread_rms_cells': com_rms / res, 'com_spread_p95_cells': com_p95 / res,
        'mean_shape_iou': truth.iou_on(geometry, posterior.mean) if truth is not None else float('nan'),
        'sensing_time_s': fit.sensing_time_s, 'gpis_fit_time_s': fit.gpis_fit_time_s, 'segmentation_refusal': refusal,
    }
    rows: list[dict[str, Any]] = []
    grasps: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    convergence: list[dict[str, Any]] = []
    exec_gripper = s.planner_params(METHODS[0]).gripper  # the planners' gripper (metric) executes every grasp
    for spec in s.method_specs:
        params = s.planner_params(spec)
        for seed in range(s.seeds):
            planner_seed = derive_seed('planner', seed, name)
            r = _plan_or_failure(spec, posterior, params, planner_seed)
            restarts = list(getattr(r, 'restarts', []) or [])
            record = GraspRecord.from_plan(r)
            row: dict[str, Any] = {
                'object': name, 'letter': letter, 'method': spec.key, 'label': spec.label, 'seed': seed,
                # n_shape_samples next to the P_F estimate it qualifies (the CSV's column order)
                'planner_seed': planner_seed, **record.columns(PLAN_COLUMNS[:9]), 'n_shape_samples': s.shape_samples,
                **record.columns(PLAN_COLUMNS[9:]),
                'n_candidates': int(r.n_candidates), 'converged': bool(r.converged),
                'restarts': len(restarts), 'restarts_converged': sum(1 for i in restarts if i.converged),
            }
            if truth is not None and r.success:
                q_n, status = truth.nominal_quality(r.jaw1, r.jaw2, exec_gripper)
                gripper_seed = derive_seed('gripper', seed, name)
                succ = truth.execute(r.jaw1, r.jaw2, exec_gripper, s.trials, np.random.default_rng(gripper_seed))
            else:
                q_n, status, succ = float('nan'), 'no_grasp' if truth is not None else 'no_ground_truth', 0
            record.executed(succ, s.trials)
            row.update({'q_n': q_n, 'q_n_status': status, **record.columns(EXECUTION_COLUMNS + PLAN_TIME_COLUMNS)})
            rows.append(row)
            if seed == 0 and r.success:
                grasps[spec.key] = (np.asarray(r.jaw1, dtype=np.float64), np.asarray(r.jaw2, dtype=np.float64))
            if seed == 0 and spec.key == 'gp-g':
                convergence = _convergence_entries(r)
        if report is not None:
            report((name, spec.key))
    calibration_rows: list[dict[str, Any]] = []
    if s.calibration_candidates > 0 and truth is not None:
        t_cal = time.perf_counter()
        planned = [{'method': r['method'], 'seed': r['seed'], 'jaw1': (r['jaw1_x'], r['jaw1_y']),
                    'jaw2': (r['jaw2_x'], r['jaw2_y']), 'p_f': r['p_f']} for r in rows if r['success']]
        calibration_rows, z_info = calibrate_object(
            posterior, truth, planned, s.planner_params(METHOD_BY_KEY['gp-p']),
            s.calibration_candidates, s.calibration_trials, s.calibration_perturbations,
            derive_seed('calibration', name), object_name=name)
        for row in calibration_rows:
            row['letter'] = letter
        info.update(z_info)
        info['calibration_time_s'] = time.perf_counter() - t_cal
        if report is not None:
            report((name, 'calibration'))
    blur = gpis_blur(posterior, n_samples=s.blur_samples, rng=np.random.default_rng(derive_seed('blur', name)))
    info['object_wall_time_s'] = time.perf_counter() - t_object
    return ObjectResult(object=name, letter=letter, bag=str(bag), rows=rows, info=info, geometry=geometry,
                        blur=blur, outline=truth.outline() if truth is not None else [],
                        jaw_width=exec_gripper.jaw_width, grasps=grasps, convergence=convergence,
                        calibration=calibration_rows)


# ------------------------------------------------------------------------------------------
# Running all objects (serial or in worker processes) with a progress bar
# ------------------------------------------------------------------------------------------


def progress_bar(total: int, enabled: bool = True, unit: str = 'step', desc: str = 'benchmark') -> tqdm:
    """A tqdm bar on stderr (``disable`` when not ``enabled``), with elapsed and remaining time."""
    return tqdm(total=total, unit=unit, desc=desc, disable=not enabled, file=sys.stderr, dynamic_ncols=True,
                smoothing=0.0)


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

    @property
    def calibration_rows(self) -> list[dict[str, Any]]:
        return [row for obj in self.objects for row in obj.calibration]


def steps_per_object(settings: BenchmarkSettings) -> int:
    """Progress steps reported by :func:`run_object` for one object."""
    return len(settings.methods) + (1 if settings.calibration_candidates > 0 else 0)


def run_benchmark(bags: Sequence[str | os.PathLike[str]], settings: BenchmarkSettings = BenchmarkSettings(),
                  workers: int | None = None, progress: bool = True, desc: str = 'benchmark') -> BenchmarkResult:
    """Run :func:`run_object` for every bag, in ``workers`` spawned processes (1 = in this process).

    BLAS/OpenMP thread pools are limited to one thread (threadpoolctl) in this process for a serial
    run and in every worker, so serial and parallel runs give bit-identical numbers.
    """
    bags = [str(b) for b in bags]
    if not bags:
        raise ValueError('no bags to benchmark')
    tasks = [ObjectTask(b, settings, i) for i, b in enumerate(bags)]
    workers = max(1, min(int(workers or os.cpu_count() or 1), len(tasks)))
    t0 = time.perf_counter()
    with progress_bar(len(tasks) * steps_per_object(settings), progress, desc=desc) as bar:
        def advance(item: tuple[str, str]) -> None:
            bar.set_postfix_str(f'{item[0]} {item[1]}', refresh=False)
            bar.update(1)

        results = map_reporting(run_object, tasks, workers, advance, total=lambda: bar.n >= bar.total)
    return BenchmarkResult(results, settings, workers, time.perf_counter() - t0)
