"""One evaluation task: object → segmentation → GPIS → plan → simulated executions on the true shape.

A :class:`Task` is an object (its manifest entry) × method × (λ, α) × seed; :func:`run_task` is a
pure function of it (the same task gives the same row apart from :data:`TIMING_COLUMNS`). The
pieces are shared by every evaluation of the package: :func:`fit_scene` (the posterior from a
bag or rendered scene, as the nodes build it), :class:`~gpis_grasp_ros.tools.evaluation.truth.TrueShape`
(the truth-frame transform and the executions) and :class:`GraspRecord` (the result columns of a
planned and executed grasp).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import resource
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from gpis_grasp_ros.core.sensing.params import SensingParams
from gpis_grasp_ros.tools.evaluation.truth import TrueShape
from gpis_grasp_ros.tools.seeds import derive_seed

#: Per-object columns on the GPIS near the true surface (see :class:`ObjectModel`); NaN without a GPIS or truth.
SURFACE_COLUMNS = ('gp_z_rms_near_surface', 'gp_bias_near_surface_cells', 'gp_sd_near_surface_cells')
#: Columns that may differ between executors and runs (wall-clock times, worker identity, memory).
TIMING_COLUMNS = ('task_time_s', 'task_cpu_s', 'planning_time_s', 'evaluation_time_s', 'gpis_time_s', 'gpis_cached',
                  'worker', 'max_rss_mb')
DEFAULT_METHODS = ('gp-gpis-opt', 'gp-m', 'gp-p')


# =========================================================================== the posterior of a scene
@dataclass
class SceneFit:
    """Segmentation and GPIS of one scene, with the stage times (s) and a relaxed check's reason."""

    posterior: Any  # GpisPosterior
    sensing: Any  # SensingResult
    geometry: Any  # GridGeometry of the planning grid (the published grids')
    refusal: str  # why the node defaults refused the target ('' = they did not; see fit_scene)
    sensing_time_s: float
    gpis_fit_time_s: float


def segment_scene(scene: Any, params: Any, relax_opening: bool = False) -> tuple[Any, str]:
    """Segmentation as the nodes run it; with ``relax_opening``, a refusal by the opening check gives its
    reason and a second run without that check (``max_opening_m = 0``).

    The benchmark evaluates the planners on every object: when segmentation refuses the target with
    the node defaults (e.g. a target wider than the gripper opening in every direction), the refusal
    is recorded and the object is segmented again with that check off."""
    from gpis_grasp_ros.core.sensing import SensingParams, segment_frames

    try:
        return segment_frames(scene.rgb_frames, scene.depth_frames, scene.intrinsics, params,
                              frame_id=scene.frame_id), ''
    except ValueError as exc:
        names = {f.name for f in dataclasses.fields(SensingParams)}
        if not relax_opening or 'max_opening_m' not in names or getattr(params, 'max_opening_m', 0) <= 0:
            raise
        relaxed = dataclasses.replace(params, max_opening_m=0.0)
        return segment_frames(scene.rgb_frames, scene.depth_frames, scene.intrinsics, relaxed,
                              frame_id=scene.frame_id), str(exc)


def fit_scene(scene: Any, params: Any, relax_opening: bool = False) -> SceneFit:
    """The GPIS posterior of a scene exactly as the nodes build it (segmentation → the published grids →
    GPIS fit; :func:`~gpis_grasp_ros.data.bags.posterior_from_scene` in two timed stages). Raises
    ValueError when segmentation or the GPIS rejects the scene."""
    from gpis_grasp_ros.core.pipeline import posterior_from_grids, publishable_grids, publishable_obstacles

    t0 = time.perf_counter()
    sensing, refusal = segment_scene(scene, params, relax_opening)
    occ, noise, geometry = publishable_grids(sensing)
    t1 = time.perf_counter()
    posterior = posterior_from_grids(occ, noise, geometry, obstacles=publishable_obstacles(sensing))
    return SceneFit(posterior, sensing, geometry, refusal, t1 - t0, time.perf_counter() - t1)


# =========================================================================== the result record
@dataclass
class GraspRecord:
    """The columns of one planned grasp and its simulated executions, as every evaluation writes them.

    Without a plan every value is NaN / 0 (:meth:`empty`); the execution columns stay 0 / 0 / NaN
    until :meth:`executed` sets them. Times are the planner's own clock (s)."""

    success: bool = False
    message: str = ''
    jaw1_x: float = float('nan')
    jaw1_y: float = float('nan')
    jaw2_x: float = float('nan')
    jaw2_y: float = float('nan')
    width_m: float = float('nan')
    p_f: float = float('nan')
    p_f_std_error: float = float('nan')
    q_f_mean: float = float('nan')
    objective: float = float('nan')
    iterations: int = 0
    sim_successes: int = 0
    sim_trials: int = 0
    sim_success_rate: float = float('nan')
    planning_time_s: float = float('nan')
    evaluation_time_s: float = float('nan')

    @classmethod
    def empty(cls, message: str = '') -> GraspRecord:
        return cls(message=message)

    @classmethod
    def from_plan(cls, r: Any) -> GraspRecord:
        """The plan columns of a :class:`~gpis_grasp_ros.core.planners.GraspResult` (or a stand-in)."""
        return cls(success=bool(r.success), message=r.message, jaw1_x=float(r.jaw1[0]), jaw1_y=float(r.jaw1[1]),
                   jaw2_x=float(r.jaw2[0]), jaw2_y=float(r.jaw2[1]), width_m=float(r.width), p_f=float(r.p_f),
                   p_f_std_error=float(r.p_f_std_error), q_f_mean=float(r.q_mean), objective=float(r.objective),
                   iterations=int(r.iterations), planning_time_s=float(r.planning_time),
                   evaluation_time_s=float(r.evaluation_time))

    def executed(self, successes: int, trials: int) -> GraspRecord:
        """Record ``successes`` of ``trials`` executions (rate NaN without trials)."""
        self.sim_successes, self.sim_trials = int(successes), int(trials)
        self.sim_success_rate = successes / trials if trials > 0 else float('nan')
        return self

    def columns(self, names: Sequence[str] | None = None) -> dict[str, Any]:
        """The record as row columns (all of them, or ``names`` in that order)."""
        row = dataclasses.asdict(self)
        return row if names is None else {k: row[k] for k in names}


PLAN_COLUMNS = tuple(f.name for f in dataclasses.fields(GraspRecord))[:12]
EXECUTION_COLUMNS = ('sim_successes', 'sim_trials', 'sim_success_rate')
PLAN_TIME_COLUMNS = ('planning_time_s', 'evaluation_time_s')


# =========================================================================== dataset tasks
@dataclass(frozen=True)
class EvalSettings:
    """Settings shared by all tasks of a run (counts as in the paper unless reduced for speed)."""

    grid_size: int = SensingParams.grid_size  # M of the GPIS grid; 0 = from the object and the cell size
    frames: int = 10  # camera frames per scene
    grasp_samples: int = 1000  # K heuristic candidates of GP-M / GP-P
    shape_samples: int = 1000  # S shape samples of every Monte-Carlo P_F
    n_initial_grasps: int = 20  # N_g of GP-GPIS-OPT (and GP-D / GP-U where the planner has the option)
    trials: int = 50  # simulated executions per grasp on the true shape

    def __post_init__(self) -> None:
        if int(self.grid_size) < 0:
            raise ValueError(f'grid_size must be >= 0 (0 = from the cell size), got {self.grid_size}')
        for name in ('frames', 'grasp_samples', 'shape_samples', 'n_initial_grasps'):
            if int(getattr(self, name)) < 1:
                raise ValueError(f'{name} must be a positive integer, got {getattr(self, name)}')
        if int(self.trials) < 0:
            raise ValueError(f'trials must be >= 0, got {self.trials}')


@dataclass(frozen=True)
class Task:
    """One independent unit: an object (its manifest entry) × method × (λ, α) × seed.

    ``uncertainty_penalty`` (λ, per m²) and ``antipodal_alpha`` (α of eq. 5) of ``None`` keep
    :class:`~gpis_grasp_ros.core.planners.PlannerParams`' defaults. ``fail_first_attempts`` is a
    fault drill: the task raises on its first k attempts (0 in real runs; used to test retries).
    """

    entry: dict[str, Any]
    method: str
    seed: int = 0
    uncertainty_penalty: float | None = None
    antipodal_alpha: float | None = None
    settings: EvalSettings = field(default_factory=EvalSettings)
    fail_first_attempts: int = 0

    @property
    def task_id(self) -> str:
        lam = 'default' if self.uncertainty_penalty is None else repr(float(self.uncertainty_penalty))
        alpha = 'default' if self.antipodal_alpha is None else repr(float(self.antipodal_alpha))
        return f"{self.entry['id']}|{self.method}|lambda={lam}|alpha={alpha}|seed={int(self.seed)}"


def make_tasks(entries: Sequence[dict[str, Any]], methods: Sequence[str], seeds: Sequence[int],
               lambdas: Sequence[float | None] = (None,), alphas: Sequence[float | None] = (None,),
               settings: EvalSettings = EvalSettings()) -> list[Task]:
    """All combinations, object-major (consecutive tasks share an object and its cached GPIS)."""
    from gpis_grasp_ros.core.planners import METHODS

    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown grasp planner(s) {', '.join(unknown)}; valid names: {', '.join(METHODS)}")
    return [Task(e, m, int(s), lam, a, settings) for e in entries for s in seeds for m in methods
            for lam in lambdas for a in alphas]


class InjectedFailure(RuntimeError):
    """Raised by a task with ``fail_first_attempts`` (fault drill)."""


@dataclass
class ObjectModel:
    """What every task of one object needs: GPIS posterior and ground truth, or why there is none."""

    posterior: Any  # GpisPosterior | None
    truth: TrueShape | None  # the ground truth, planning grid → true grid
    true_com: Any  # (2,) true-grid centre of mass of the scene (m), or None
    status: str  # 'ok', 'no_gpis', 'no_ground_truth'
    message: str
    gpis_time_s: float
    mean_shape_iou: float
    #: the GPIS near the true surface (``calibration.gp_z_scores``, planning cells within 2 cells of it): z RMS of
    #: (sdf_true - mu) / sigma, mean mu - sdf_true (cells; < 0: the mean shape bulges out), mean sigma (cells)
    surface: dict[str, float] = field(default_factory=dict)



@functools.lru_cache(maxsize=4)
def _object_model_cached(entry_json: str, grid_size: int, frames: int) -> ObjectModel:
    from gpis_grasp_ros.core.sensing import SensingParams
    from gpis_grasp_ros.sim.dataset import render_entry
    from gpis_grasp_ros.tools.benchmark.calibration import gp_z_scores

    entry = json.loads(entry_json)
    t0 = time.perf_counter()
    scene = render_entry(entry, frames)
    try:
        posterior = fit_scene(scene, SensingParams(grid_size=grid_size)).posterior
    except ValueError as err:  # segmentation / GPIS rejected the scene: a result, not a crash
        return ObjectModel(None, None, scene.true_center_of_mass, 'no_gpis', f'{type(err).__name__}: {err}',
                           time.perf_counter() - t0, float('nan'))
    iou, surface, truth = float('nan'), {}, None
    if scene.true_sdf is not None:  # the mean shape against the truth at the cell centres, and near its surface
        truth = TrueShape(scene.true_sdf, scene.true_geometry, posterior.geometry, obstacles=scene.true_obstacles)
        iou = truth.iou_on(posterior.geometry, posterior.mean)
        z = gp_z_scores(posterior, truth)
        surface = {k: z[k] for k in SURFACE_COLUMNS}
    status = 'ok' if scene.true_sdf is not None else 'no_ground_truth'
    return ObjectModel(posterior, truth, scene.true_center_of_mass, status,
                       '' if status == 'ok' else 'the bag has no /ground_truth/sdf', time.perf_counter() - t0, iou,
                       surface)


def object_model(entry: dict[str, Any], settings: EvalSettings) -> tuple[ObjectModel, bool]:
    """The object's :class:`ObjectModel` (cached per process) and whether it came from the cache."""
    key = (json.dumps(entry, sort_keys=True), int(settings.grid_size), int(settings.frames))
    hits = _object_model_cached.cache_info().hits
    model = _object_model_cached(*key)
    return model, _object_model_cached.cache_info().hits > hits


def planner_params(task: Task) -> Any:
    """:class:`~gpis_grasp_ros.core.planners.PlannerParams` of a task (only the fields it sets change)."""
    from gpis_grasp_ros.core.planners import PlannerParams

    s = task.settings
    kw: dict[str, Any] = {'n_initial_grasps': int(s.n_initial_grasps), 'n_grasp_samples': int(s.grasp_samples),
                          'n_shape_samples': int(s.shape_samples)}
    if task.uncertainty_penalty is not None:
        kw['uncertainty_penalty'] = float(task.uncertainty_penalty)
    if task.antipodal_alpha is not None:
        kw['antipodal_alpha'] = float(task.antipodal_alpha)
    return PlannerParams(**kw)


def run_task(task: Task, attempt: int = 1) -> dict[str, Any]:
    """Run one task (pure: the same task gives the same row apart from :data:`TIMING_COLUMNS`).

    The planned grasp is executed ``trials`` times on the TRUE shape (the planners' gripper, the scene's true
    centre of mass, its other objects as obstacles), the jaws mapped to the true grid by
    :meth:`~gpis_grasp_ros.tools.evaluation.truth.TrueShape.to_true` (the identity when the frames coincide)."""
    import numpy as np

    from gpis_grasp_ros.core.planners import plan

    t_task, cpu_task = time.perf_counter(), time.process_time()
    if attempt <= int(task.fail_first_attempts):
        raise InjectedFailure(f'fault drill: attempt {attempt} of task {task.task_id} fails on purpose')
    e = task.entry
    params = planner_params(task)
    row: dict[str, Any] = {
        'task_id': task.task_id, 'object': e['id'], 'source': e['source'], 'family': e['family'],
        'size_m': e['size_m'], 'size_class': e['size_class'], 'material_class': e['material_class'],
        'camera': e['camera'], 'method': task.method, 'lambda': float(params.uncertainty_penalty),
        'alpha': float(params.antipodal_alpha), 'seed': int(task.seed), 'attempts': int(attempt),
    }
    model, cached = object_model(e, task.settings)
    planner_seed = derive_seed('planner', int(task.seed), e['id'])
    row.update({'planner_seed': planner_seed, 'mean_shape_iou': model.mean_shape_iou})
    row.update({k: model.surface.get(k, float('nan')) for k in SURFACE_COLUMNS})
    record = GraspRecord.empty(model.message)
    status = model.status
    if model.posterior is not None:
        r = plan(task.method, model.posterior, params, seed=planner_seed)
        record = GraspRecord.from_plan(r)
        if not r.success:
            status = 'no_grasp'
        if model.truth is not None:
            trials = int(task.settings.trials)
            succ = 0
            if r.success:
                gripper = params.gripper
                rng = np.random.default_rng(derive_seed('gripper', int(task.seed), e['id']))
                succ = model.truth.execute(r.jaw1, r.jaw2, gripper, trials, rng, center_of_mass=model.true_com,
                                           snap_aligned=True)
            record.executed(succ, trials)
    row.update(record.columns())
    row['status'] = status
    row.update({'gpis_time_s': 0.0 if cached else model.gpis_time_s, 'gpis_cached': bool(cached),
                'worker': f'{os.uname().nodename}:{os.getpid()}',
                'max_rss_mb': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
                'task_time_s': time.perf_counter() - t_task, 'task_cpu_s': time.process_time() - cpu_task})
    return row


def execute(task: Task, attempt: int = 1) -> dict[str, Any]:
    """:func:`run_task` with BLAS limited to one thread (what every executor calls)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        return run_task(task, attempt)
