"""``gpis-grasp evaluate``: dataset-scale evaluation as independent tasks on three executors (issue 13).

    gpis-grasp evaluate --dataset DIR --out DIR [--methods gp-gpis-opt,gp-m,gp-p] [--lambda 2] [--alpha 0.5]
                        [--seeds 1] [--executor serial|process|dask] [--workers N] [--scheduler local|tcp://HOST:PORT]
    gpis-grasp evaluate --dataset DIR --out DIR --throughput 1,2 [--executors serial,process,dask]

**Tasks.** The evaluation is a list of independent :class:`Task` s, one per object × method ×
parameter setting (λ = ``uncertainty_penalty``, α = ``antipodal_alpha`` of
:class:`~gpis_grasp_ros.core.planners.PlannerParams`) × seed. :func:`run_task` is a pure function of
its task: it renders the object's scene in memory (:func:`~gpis_grasp_ros.sim.dataset.render_entry`;
a user's bag is read instead), segments it and fits the GPIS exactly as the nodes do
(:func:`~gpis_grasp_ros.data.bags.posterior_from_scene`), plans with
:func:`~gpis_grasp_ros.core.planners.plan` and executes the grasp ``trials`` times on the TRUE
shape with :func:`~gpis_grasp_ros.sim.execution.execute_grasp_trials` (σ_g = 0.5 planning cell,
true centre of mass). A task carries its manifest entry, so a remote worker needs the package but no
files (except for user-bag entries). The GPIS of an object is cached per worker process
(:func:`object_model`, LRU), so consecutive tasks of one object fit it once per worker.

**Seeds (common random numbers).** The planner seed is a function of (seed, object) only, the
execution noise of (seed, object) only: every method and parameter setting of one seed faces the
same candidates, evaluation samples and positioning errors. Nothing depends on the process, the
executor or the order of execution, and every task runs with one BLAS thread (threadpoolctl), so the
results are identical whatever the executor and worker count, apart from :data:`TIMING_COLUMNS`.

**Executors.** ``serial`` (this process), ``process`` (a spawned ``ProcessPoolExecutor``) and
``dask`` (:mod:`dask.distributed`): ``--scheduler local`` starts a private
``LocalCluster(host='127.0.0.1', dashboard_address=None, processes=True, threads_per_worker=1)``
whose sockets all listen on 127.0.0.1; ``--scheduler tcp://HOST:PORT`` joins an existing cluster
(``dask scheduler`` on one machine, ``dask worker tcp://HOST:PORT --nthreads 1`` on the others; the
workers need this package installed). Progress is a tqdm bar for every executor. The parallel
executors schedule the pending tasks of one object as one unit (``--affinity object``, default): the
GPIS fit (1-4 s at M = 25, more than most plans) then happens once per object instead of once per
object and worker; ``--affinity task`` schedules single tasks (finer load balance, repeated fits).

**Failures, incremental results, resume.** Every finished task appends one JSON line to
``results.jsonl`` as soon as the parent receives it (flushed; with object units, when the object's
unit returns). A task that raises is retried once; if it fails again the error
and traceback go to ``failures.jsonl`` and the run ends with exit code 1 and a list of the failed
tasks — never silently dropped. Domain outcomes are not failures but statuses of a result row:
``ok``, ``no_gpis`` (segmentation/GPIS rejected the scene, e.g. nothing segmented), ``no_grasp``
(the planner found no grasp; message kept), ``no_ground_truth`` (a bag without ground truth).
Running the same command again resumes: tasks already in ``results.jsonl`` are skipped (a line cut
by an interruption is discarded), failed tasks are tried again; ``run.json`` records the settings
and the dataset digest, and a resume with other settings is refused (use ``--fresh``).

Outputs: ``results.jsonl``, ``results.csv`` (task order), ``failures.jsonl``, ``run.json`` and
``summary.md`` (per material class × size class × method: P_F, simulated success, planning time; then per
class the GPIS near the true surface, one value per object: mean-shape IoU, the mean's bias, σ and the z RMS -
how far the posterior is from calibrated where the grasps touch).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import functools
import json
import math
import multiprocessing as mp
import os
import resource
import sys
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gpis_grasp_ros.tools.seeds import derive_seed

EXECUTORS = ('serial', 'process', 'dask')
#: Per-object columns on the GPIS near the true surface (see :class:`ObjectModel`); NaN without a GPIS or truth.
SURFACE_COLUMNS = ('gp_z_rms_near_surface', 'gp_bias_near_surface_cells', 'gp_sd_near_surface_cells')
#: Columns that may differ between executors and runs (wall-clock times, worker identity, memory).
TIMING_COLUMNS = ('task_time_s', 'task_cpu_s', 'planning_time_s', 'evaluation_time_s', 'gpis_time_s', 'gpis_cached',
                  'worker', 'max_rss_mb')
DEFAULT_METHODS = ('gp-gpis-opt', 'gp-m', 'gp-p')
BLAS_ENV = ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS', 'VECLIB_MAXIMUM_THREADS',
            'NUMEXPR_NUM_THREADS')


# =========================================================================== tasks
@dataclass(frozen=True)
class EvalSettings:
    """Settings shared by all tasks of a run (counts as in the paper unless reduced for speed)."""

    grid_size: int = 25  # M of the GPIS grid
    frames: int = 10  # camera frames per scene
    grasp_samples: int = 1000  # K heuristic candidates of GP-M / GP-P
    shape_samples: int = 1000  # S shape samples of every Monte-Carlo P_F
    n_initial_grasps: int = 20  # N_g of GP-GPIS-OPT (and GP-D / GP-U where the planner has the option)
    trials: int = 50  # simulated executions per grasp on the true shape

    def __post_init__(self) -> None:
        for name in ('grid_size', 'frames', 'grasp_samples', 'shape_samples', 'n_initial_grasps'):
            if int(getattr(self, name)) < 1:
                raise ValueError(f'{name} must be a positive integer, got {getattr(self, name)}')
        if int(self.trials) < 0:
            raise ValueError(f'trials must be >= 0, got {self.trials}')


@dataclass(frozen=True)
class Task:
    """One independent unit: an object (its manifest entry) × method × (λ, α) × seed.

    ``uncertainty_penalty`` (λ, per cell²) and ``antipodal_alpha`` (α of eq. 5) of ``None`` keep
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
    true_sdf: np.ndarray | None
    true_geometry: Any
    true_com: np.ndarray | None
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
    from gpis_grasp_ros.data.bags import posterior_from_scene
    from gpis_grasp_ros.sim.dataset import render_entry
    from gpis_grasp_ros.tools.benchmark.calibration import gp_z_scores
    from gpis_grasp_ros.tools.benchmark.evaluation import TrueShape

    entry = json.loads(entry_json)
    t0 = time.perf_counter()
    scene = render_entry(entry, frames)
    try:
        posterior, _ = posterior_from_scene(scene, SensingParams(grid_size=grid_size))
    except ValueError as err:  # segmentation / GPIS rejected the scene: a result, not a crash
        return ObjectModel(None, scene.true_sdf, scene.true_geometry, scene.true_center_of_mass, 'no_gpis',
                           f'{type(err).__name__}: {err}', time.perf_counter() - t0, float('nan'))
    iou, surface = float('nan'), {}
    if scene.true_sdf is not None:  # the mean shape against the truth at the cell centres, and near its surface
        truth = TrueShape(scene.true_sdf, scene.true_geometry, posterior.geometry)
        iou = truth.iou_on(posterior.geometry, posterior.mean)
        z = gp_z_scores(posterior, truth)
        surface = {k: z[k] for k in SURFACE_COLUMNS}
    status = 'ok' if scene.true_sdf is not None else 'no_ground_truth'
    return ObjectModel(posterior, scene.true_sdf, scene.true_geometry, scene.true_center_of_mass, status,
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


def to_truth_grid(xy: np.ndarray, planning: Any, truth: Any) -> np.ndarray:
    """Planning-grid (x, y) on the table (m) → ground-truth grid (x, y), through the sensor frame.

    Both grids lie in the table plane; with a top-down camera both rotations are the identity and
    this is the identity map. With a tilted camera the estimated table frame and the simulator's
    may differ by a rotation about the table normal and an offset."""
    if np.allclose(planning.rotation_matrix, truth.rotation_matrix) and math.isclose(planning.z, truth.z):
        return np.asarray(xy, dtype=np.float64)
    return truth.from_sensor(planning.to_sensor(np.asarray(xy, dtype=np.float64)))[0]


def run_task(task: Task, attempt: int = 1) -> dict[str, Any]:
    """Run one task (pure: the same task gives the same row apart from :data:`TIMING_COLUMNS`)."""
    from gpis_grasp_ros.core.planners import plan
    from gpis_grasp_ros.sim.execution import execute_grasp_trials

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
    nan = float('nan')
    result_cols = {'success': False, 'message': model.message, 'jaw1_x': nan, 'jaw1_y': nan, 'jaw2_x': nan,
                   'jaw2_y': nan, 'width_m': nan, 'p_f': nan, 'p_f_std_error': nan, 'q_f_mean': nan,
                   'objective': nan, 'iterations': 0, 'sim_successes': 0, 'sim_trials': 0, 'sim_success_rate': nan,
                   'planning_time_s': nan, 'evaluation_time_s': nan}
    status = model.status
    if model.posterior is not None:
        r = plan(task.method, model.posterior, params, seed=planner_seed)
        result_cols.update({
            'success': bool(r.success), 'message': r.message, 'jaw1_x': float(r.jaw1[0]), 'jaw1_y': float(r.jaw1[1]),
            'jaw2_x': float(r.jaw2[0]), 'jaw2_y': float(r.jaw2[1]), 'width_m': float(r.width), 'p_f': float(r.p_f),
            'p_f_std_error': float(r.p_f_std_error), 'q_f_mean': float(r.q_mean), 'objective': float(r.objective),
            'iterations': int(r.iterations), 'planning_time_s': float(r.planning_time),
            'evaluation_time_s': float(r.evaluation_time)})
        if not r.success:
            status = 'no_grasp'
        if model.true_sdf is not None:
            trials = int(task.settings.trials)
            succ = 0
            if r.success:
                gripper = params.gripper.resolved(model.posterior.geometry)
                rng = np.random.default_rng(derive_seed('gripper', int(task.seed), e['id']))
                jaw1, jaw2 = (to_truth_grid(j, model.posterior.geometry, model.true_geometry) for j in (r.jaw1, r.jaw2))
                succ = execute_grasp_trials(model.true_sdf, model.true_geometry, jaw1, jaw2, gripper, trials,
                                            rng, center_of_mass=model.true_com)
            result_cols.update({'sim_successes': int(succ), 'sim_trials': trials,
                                'sim_success_rate': succ / trials if trials else nan})
    row.update(result_cols)
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


# =========================================================================== result files
@dataclass
class RunFiles:
    """The files of one evaluation folder."""

    root: Path

    @property
    def results(self) -> Path:
        return self.root / 'results.jsonl'

    @property
    def failures(self) -> Path:
        return self.root / 'failures.jsonl'

    @property
    def run(self) -> Path:
        return self.root / 'run.json'


def read_results(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """Rows of a ``results.jsonl`` (or its folder); a trailing line cut by an interruption is ignored."""
    p = Path(path)
    p = p / 'results.jsonl' if p.is_dir() else p
    rows = []
    if not p.exists():
        return rows
    for line in p.read_text(encoding='utf8').splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return rows


def _repair_tail(path: Path) -> None:
    """Cut a partial last line (no newline: the run was interrupted while writing it)."""
    if not path.exists() or path.stat().st_size == 0:
        return
    data = path.read_bytes()
    if not data.endswith(b'\n'):
        path.write_bytes(data[:data.rfind(b'\n') + 1])


class _Writer:
    """Appends one JSON line per finished task and flushes it at once."""

    def __init__(self, path: Path) -> None:
        self.fh = open(path, 'a', encoding='utf8')

    def write(self, row: dict[str, Any]) -> None:
        self.fh.write(json.dumps(row, sort_keys=True) + '\n')
        self.fh.flush()

    def close(self) -> None:
        self.fh.close()


def _prepare_out(out: Path, fingerprint: dict[str, Any], fresh: bool) -> RunFiles:
    files = RunFiles(out)
    if fresh and out.exists():
        for p in (files.results, files.failures, files.run, out / 'results.csv', out / 'summary.md'):
            p.unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    if files.run.exists():
        old = json.loads(files.run.read_text(encoding='utf8'))
        if old != fingerprint:
            raise ValueError(f'{out} holds results of another run (different settings or dataset: see {files.run}); '
                             'resume with the same settings, or start over with --fresh or another --out')
    else:
        files.run.write_text(json.dumps(fingerprint, sort_keys=True, indent=1) + '\n', encoding='utf8')
    _repair_tail(files.results)
    files.failures.unlink(missing_ok=True)  # failed tasks of an earlier run are tried again
    return files


# =========================================================================== executors
@dataclass
class EvalRun:
    """Outcome of :func:`run_evaluation`: all rows (task order), failures, counts and wall time."""

    rows: list[dict[str, Any]]
    failures: list[dict[str, Any]]
    ran: int  # tasks executed in this call (not resumed)
    resumed: int  # tasks skipped because their row was already written
    wall_time_s: float
    executor: str
    workers: int
    out: Path


@contextlib.contextmanager
def _single_thread_env() -> Iterator[None]:
    """BLAS thread variables = 1 while worker processes start (threadpoolctl then enforces it per task)."""
    saved = {k: os.environ.get(k) for k in BLAS_ENV}
    os.environ.update({k: '1' for k in BLAS_ENV})
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _failure(task: Task, attempt: int, err: BaseException) -> dict[str, Any]:
    tb = err.tb if isinstance(err, TaskError) else ''.join(traceback.format_exception(type(err), err,
                                                                                     err.__traceback__))
    return {'task_id': task.task_id, 'object': task.entry['id'], 'method': task.method, 'attempts': attempt,
            'error': f'{_err_name(err)}: {err}', 'traceback': tb}


class TaskError(Exception):
    """A task's exception as it happened in a worker: type name, message and formatted traceback."""

    def __init__(self, kind: str, message: str, tb: str) -> None:
        super().__init__(message)
        self.kind, self.message, self.tb = kind, message, tb


Unit = list[tuple[Task, int]]  # (task, attempt) pairs run one after the other by one worker


def run_unit(unit: Unit, fn: Callable[[Task, int], dict[str, Any]] = execute
             ) -> list[tuple[dict[str, Any] | None, tuple[str, str, str] | None]]:
    """Run the tasks of a unit in order; per task (row, None) or (None, (type, message, traceback))."""
    out: list[tuple[dict[str, Any] | None, tuple[str, str, str] | None]] = []
    for task, attempt in unit:
        try:
            out.append((fn(task, attempt), None))
        except Exception as exc:  # noqa: BLE001 - reported per task by the parent
            out.append((None, (type(exc).__name__, str(exc), traceback.format_exc())))
    return out


def make_units(tasks: Sequence[Task], affinity: str = 'object') -> list[Unit]:
    """Scheduling units: all (pending) tasks of one object together (``'object'``: the object's GPIS is
    fitted once, by one worker) or one task per unit (``'task'``)."""
    if affinity == 'task':
        return [[(t, 1)] for t in tasks]
    if affinity != 'object':
        raise ValueError(f"affinity must be 'object' or 'task', got '{affinity}'")
    groups: dict[str, Unit] = {}
    for t in tasks:
        groups.setdefault(t.entry['id'], []).append((t, 1))
    return list(groups.values())


class _Collector:
    """Retry bookkeeping shared by the executors: records outcomes, returns the tasks to run again."""

    def __init__(self, writer: _Writer, fail_writer: _Writer, bar: Any, max_attempts: int) -> None:
        self.writer, self.fail_writer, self.bar, self.max_attempts = writer, fail_writer, bar, max_attempts
        self.rows: list[dict[str, Any]] = []
        self.failures: list[dict[str, Any]] = []

    def done(self, task: Task, attempt: int, row: dict[str, Any] | None, err: BaseException | None) -> int | None:
        """Record one outcome; the next attempt number if the task is to be retried, else None."""
        if err is None:
            assert row is not None
            self.writer.write(row)
            self.rows.append(row)
        elif attempt < self.max_attempts:
            self.bar.write(f'evaluate: task {task.task_id} failed ({_err_name(err)}: {err}); retrying')
            return attempt + 1
        else:
            f = _failure(task, attempt, err)
            self.fail_writer.write(f)
            self.failures.append(f)
            self.bar.write(f"evaluate: task {task.task_id} FAILED after {attempt} attempts: {f['error']}")
        self.bar.update(1)
        return None

    def done_unit(self, unit: Unit, results: Any, unit_error: BaseException | None) -> list[Unit]:
        """Record a finished unit (or the error that lost it); failed tasks come back as units of one."""
        retry: list[Unit] = []
        for k, (task, attempt) in enumerate(unit):
            if unit_error is not None:
                row, err = None, unit_error
            else:
                row, info = results[k]
                err = None if info is None else TaskError(*info)
            again = self.done(task, attempt, row, err)
            if again is not None:
                retry.append([(task, again)])
        return retry


def _err_name(err: BaseException) -> str:
    return err.kind if isinstance(err, TaskError) else type(err).__name__


def _run_serial(tasks: Sequence[Task], col: _Collector, fn: Callable[[Task, int], dict[str, Any]]) -> None:
    for task in tasks:
        attempt: int | None = 1
        while attempt is not None:
            try:
                row, err = fn(task, attempt), None
            except Exception as exc:  # noqa: BLE001 - every task failure is reported, never raised past the run
                row, err = None, exc
            attempt = col.done(task, attempt, row, err)


def _worker_init() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)


def _run_process(units: Sequence[Unit], col: _Collector, fn: Callable[[Task, int], dict[str, Any]],
                 workers: int) -> None:
    ctx = mp.get_context('spawn')
    with _single_thread_env(), ProcessPoolExecutor(max_workers=workers, mp_context=ctx,
                                                   initializer=_worker_init) as pool:
        pending: dict[Future, Unit] = {pool.submit(run_unit, u, fn): u for u in units}
        while pending:
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                unit = pending.pop(fut)
                err = fut.exception()
                for again in col.done_unit(unit, None if err else fut.result(), err):
                    pending[pool.submit(run_unit, again, fn)] = again


def _check_scheduler(scheduler: str) -> None:
    if scheduler != 'local' and not scheduler.startswith(('tcp://', 'tls://', 'ucx://', 'inproc://')):
        raise ValueError(f"--scheduler must be 'local' or a scheduler address such as tcp://10.0.0.5:8786, "
                         f"got '{scheduler}'")


@contextlib.contextmanager
def dask_client(scheduler: str = 'local', workers: int = 2) -> Iterator[Any]:
    """A ``distributed.Client``: a private loopback LocalCluster (``'local'``) or an existing scheduler."""
    from distributed import Client, LocalCluster

    if scheduler == 'local':
        # no dashboard; the scheduler's small HTTP endpoint (health, metrics) on a free loopback port
        # instead of 8787, so several private clusters can run side by side
        http = {'dashboard': False, 'dashboard_address': '127.0.0.1:0'}
        with _single_thread_env(), LocalCluster(host='127.0.0.1', dashboard_address=None, processes=True,
                                                n_workers=int(workers), threads_per_worker=1, silence_logs=40,
                                                scheduler_kwargs=http) as cluster, Client(cluster) as client:
            yield client
    else:
        _check_scheduler(scheduler)
        with Client(scheduler) as client:
            yield client


def glibc_malloc_thresholds(trim_bytes: int = 256 << 20, mmap_bytes: int = 64 << 20) -> bool:
    """Set glibc's malloc trim and mmap thresholds of this process (False where glibc is absent).

    Dask's nanny starts workers with ``MALLOC_TRIM_THRESHOLD_=65536``, which also freezes glibc's
    dynamic mmap threshold at 128 KiB: every large numpy temporary is then mmap-ed and page-faulted
    afresh, and the planners ran at about twice the CPU time per task (measured: 17.5 s vs 7.5 s of
    thread CPU for three GP-P plans). Large static thresholds restore heap reuse.
    """
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library('c')
    if not name or not sys.platform.startswith('linux'):
        return False
    try:
        libc = ctypes.CDLL(name)
        m_trim_threshold, m_mmap_threshold = -1, -3  # <malloc.h>
        return bool(libc.mallopt(m_trim_threshold, int(trim_bytes)) and libc.mallopt(m_mmap_threshold,
                                                                                      int(mmap_bytes)))
    except (OSError, AttributeError):
        return False


def _dask_worker_setup(dask_worker: Any = None) -> bool:
    """Run on every Dask worker before the tasks: malloc thresholds and one BLAS thread."""
    _worker_init()
    return glibc_malloc_thresholds()


def _run_dask(units: Sequence[Unit], col: _Collector, fn: Callable[[Task, int], dict[str, Any]],
              client: Any) -> None:
    from distributed import as_completed

    client.register_worker_callbacks(_dask_worker_setup)  # also on workers that join later

    def submit(unit: Unit) -> Any:
        first, attempt = unit[0]
        return client.submit(run_unit, unit, fn, pure=False, key=f'unit-{attempt}-{first.task_id}')

    pending: dict[Any, Unit] = {submit(u): u for u in units}
    ac = as_completed(list(pending))
    for fut in ac:
        unit = pending.pop(fut)
        err = None
        if fut.status == 'error':
            err = fut.exception()
        elif fut.status == 'cancelled':
            err = RuntimeError('the Dask future was cancelled (worker or scheduler lost)')
        results = None if err else fut.result()
        fut.release()
        for again in col.done_unit(unit, results, err):
            new = submit(again)
            pending[new] = again
            ac.add(new)


def fingerprint(tasks: Sequence[Task], dataset_digest: str = '') -> dict[str, Any]:
    """What must match for a resume: the settings of the tasks and the dataset digest."""
    settings = sorted({json.dumps(dataclasses.asdict(t.settings), sort_keys=True) for t in tasks})
    return {'settings': [json.loads(s) for s in settings], 'dataset': dataset_digest}


def run_evaluation(tasks: Sequence[Task], out: str | os.PathLike[str], executor: str = 'serial', workers: int = 1,
                   scheduler: str = 'local', fresh: bool = False, progress: bool = True, max_attempts: int = 2,
                   dataset_digest: str = '', client: Any = None,
                   task_fn: Callable[[Task, int], dict[str, Any]] = execute, affinity: str = 'object') -> EvalRun:
    """Run ``tasks`` (skipping those already in ``out/results.jsonl``) and write the results.

    ``executor`` is 'serial', 'process' (``workers`` spawned processes) or 'dask' (``client`` if
    given, else :func:`dask_client` with ``scheduler`` and ``workers``). Each failing task is tried
    ``max_attempts`` times in all, then recorded in ``failures.jsonl``. The parallel executors
    schedule :func:`make_units` (``affinity``): by default the pending tasks of one object go to one
    worker together, so that its GPIS is fitted once; rows are written as each unit returns.
    """
    if executor not in EXECUTORS:
        raise ValueError(f"executor must be one of {', '.join(EXECUTORS)}, got '{executor}'")
    ids = [t.task_id for t in tasks]
    if len(set(ids)) != len(ids):
        raise ValueError('duplicate tasks in the task list')
    if executor == 'dask' and client is None:
        _check_scheduler(scheduler)
    workers = 1 if executor == 'serial' else max(1, int(workers))
    files = _prepare_out(Path(out), fingerprint(tasks, dataset_digest), fresh)
    done_ids = {r['task_id'] for r in read_results(files.results)}
    todo = [t for t in tasks if t.task_id not in done_ids]
    from tqdm import tqdm

    writer, fail_writer = _Writer(files.results), _Writer(files.failures)
    t0 = time.perf_counter()
    with tqdm(total=len(tasks), initial=len(tasks) - len(todo), desc=f'evaluate [{executor}]', unit='task',
              disable=not progress, file=sys.stderr, dynamic_ncols=True) as bar:
        col = _Collector(writer, fail_writer, bar, max(1, int(max_attempts)))
        try:
            if not todo:
                pass
            elif executor == 'serial':
                _run_serial(todo, col, task_fn)
            elif executor == 'process':
                _run_process(make_units(todo, affinity), col, task_fn, workers)
            elif client is not None:
                _run_dask(make_units(todo, affinity), col, task_fn, client)
            else:
                with dask_client(scheduler, workers) as c:
                    _run_dask(make_units(todo, affinity), col, task_fn, c)
        finally:
            writer.close()
            fail_writer.close()
    wall = time.perf_counter() - t0
    order = {tid: i for i, tid in enumerate(ids)}
    rows = sorted((r for r in read_results(files.results) if r['task_id'] in order), key=lambda r: order[r['task_id']])
    write_csv(Path(out) / 'results.csv', rows)
    return EvalRun(rows, col.failures, len(todo), len(tasks) - len(todo), wall, executor, workers, Path(out))


def write_csv(path: Path, rows: Sequence[dict[str, Any]]) -> None:
    """Rows as CSV (union of the keys, first row's order first)."""
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    with open(path, 'w', newline='', encoding='utf8') as fh:
        w = csv.DictWriter(fh, fieldnames=keys, lineterminator='\n')
        w.writeheader()
        w.writerows(rows)


def comparable(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Rows without :data:`TIMING_COLUMNS`, sorted by task id (for executor-identity checks)."""
    return sorted(({k: v for k, v in r.items() if k not in TIMING_COLUMNS} for r in rows), key=lambda r: r['task_id'])


# =========================================================================== summaries
def _mean(values: Sequence[float]) -> float:
    v = [x for x in values if x is not None and math.isfinite(x)]
    return float(np.mean(v)) if v else float('nan')


def summary_table(rows: Sequence[dict[str, Any]], by: Sequence[str] = ('material_class', 'size_class')) -> str:
    """Markdown: per group and method, tasks, mean P_F, simulated success, median planning time.

    Tasks without a grasp count as P_F 0 and success 0 (the robot would not grasp); ``no_gpis``
    tasks are counted separately."""
    methods = sorted({r['method'] for r in rows})
    lines = [f"| {' | '.join(by)} | method | tasks | no GPIS | mean P_F | sim success | median planning (s) |",
             '|' + '---|' * (len(by) + 6)]
    for dim in by:
        groups = sorted({r[dim] for r in rows})
        for g in groups:
            for m in methods:
                sel = [r for r in rows if r[dim] == g and r['method'] == m]
                if not sel:
                    continue
                usable = [r for r in sel if r['status'] != 'no_gpis']
                pf = _mean([r['p_f'] if r['success'] else 0.0 for r in usable])
                succ = _mean([r['sim_success_rate'] if r['success'] else 0.0 for r in usable
                              if r['status'] != 'no_ground_truth'])
                times = [r['planning_time_s'] for r in usable if math.isfinite(r['planning_time_s'])]
                cells = [g if d == dim else '' for d in by]
                lines.append(f"| {' | '.join(cells)} | {m} | {len(sel)} | {len(sel) - len(usable)} | {pf:.3f} | "
                             f"{succ:.3f} | {np.median(times) if times else float('nan'):.3f} |")
    return '\n'.join(lines)


def surface_table(rows: Sequence[dict[str, Any]],
                  by: Sequence[str] = ('material_class', 'size_class', 'camera')) -> str:
    """Markdown: per group, the GPIS near the true surface, one value per object (median over the objects with a
    GPIS and a ground truth): mean-shape IoU, bias mu - sdf_true (cells; < 0: the mean shape bulges out), sigma
    (cells) and the z RMS of (sdf_true - mu) / sigma (1 for a calibrated posterior). '' when no row has them."""
    per_object: dict[str, dict[str, Any]] = {}
    for r in rows:
        if all(math.isfinite(float(r.get(k, float('nan')))) for k in SURFACE_COLUMNS):
            per_object.setdefault(r['object'], r)
    if not per_object:
        return ''
    objs = list(per_object.values())
    lines = [f"| {' | '.join(by)} | objects | mean-shape IoU | bias near surface (cells) | σ near surface (cells) "
             '| z RMS near surface |', '|' + '---|' * (len(by) + 5)]
    for dim in ('all', *by):
        for g in (['all'] if dim == 'all' else sorted({o[dim] for o in objs})):
            sel = objs if dim == 'all' else [o for o in objs if o[dim] == g]
            med = [float(np.median([float(o[k]) for o in sel])) for k in ('mean_shape_iou', *SURFACE_COLUMNS)]
            cells = [('all' if dim == 'all' and i == 0 else (g if d == dim else '')) for i, d in enumerate(by)]
            lines.append(f"| {' | '.join(cells)} | {len(sel)} | {med[0]:.2f} | {med[2]:+.2f} | {med[3]:.2f} | "
                         f'{med[1]:.1f} |')
    return '\n'.join(lines)


# =========================================================================== throughput
def _noop(i: int) -> int:
    return i


def dask_round_trip_s(client: Any, n: int = 200) -> float:
    """Dask's own cost per task (s): wall time of ``n`` no-op tasks submitted at once, divided by ``n``."""
    t0 = time.perf_counter()
    futures = client.map(_noop, range(n), pure=False)
    client.gather(futures)
    return (time.perf_counter() - t0) / n


def throughput(tasks: Sequence[Task], out: Path, configs: Sequence[tuple[str, int]], progress: bool = False,
               affinity: str = 'object') -> list[dict[str, Any]]:
    """Wall time, tasks/s, CPU time and memory of the same task list per (executor, workers), from scratch.

    Every configuration starts with fresh worker processes (cold GPIS caches) and runs all tasks; in
    the serial configuration this process's cache is cleared first. ``wall_s`` is the evaluation's wall
    time (process pools start inside it; a Dask LocalCluster's start-up is ``startup_s``, apart).
    ``idle_per_task_s`` = (wall × workers − Σ task wall time) / tasks: time a worker slot spends not
    computing (scheduling, transfers, start-up, load imbalance at the end). ``cpu_s`` sums the tasks'
    CPU time (``time.process_time``), which other processes on a shared machine do not inflate.
    """
    out.mkdir(parents=True, exist_ok=True)
    reference: list[dict[str, Any]] | None = None
    stats, all_rows = [], []
    for executor, workers in configs:
        _object_model_cached.cache_clear()
        load_before = os.getloadavg()[0]
        startup, round_trip = 0.0, float('nan')
        target = out / f'{executor}-{workers}'
        if executor == 'dask':
            t0 = time.perf_counter()
            with dask_client('local', workers) as client:
                client.wait_for_workers(workers)
                startup = time.perf_counter() - t0
                round_trip = dask_round_trip_s(client)
                run = run_evaluation(tasks, target, executor, workers, fresh=True, progress=progress,
                                     affinity=affinity, client=client)
        else:
            run = run_evaluation(tasks, target, executor, workers, fresh=True, progress=progress, affinity=affinity)
        if run.failures:
            raise RuntimeError(f'{executor} x {workers}: {len(run.failures)} tasks failed; see {run.out}')
        all_rows.append(run.rows)
        same = reference is None or comparable(run.rows) == reference
        reference = reference or comparable(run.rows)
        busy = sum(r['task_time_s'] for r in run.rows)
        rss: dict[str, float] = {}
        for r in run.rows:
            rss[r['worker']] = max(rss.get(r['worker'], 0.0), r['max_rss_mb'])
        stats.append({'executor': executor, 'workers': workers, 'tasks': len(run.rows), 'wall_s': run.wall_time_s,
                      'tasks_per_s': len(run.rows) / run.wall_time_s, 'busy_s': busy,
                      'cpu_s': sum(r.get('task_cpu_s', float('nan')) for r in run.rows),
                      'idle_per_task_s': (run.wall_time_s * workers - busy) / len(run.rows),
                      'startup_s': startup, 'dask_round_trip_s': round_trip,
                      'max_rss_mb_per_worker': max(rss.values()), 'identical_to_first': same,
                      'load_avg_1min': 0.5 * (load_before + os.getloadavg()[0])})
    base = next((s['tasks_per_s'] for s in stats if s['executor'] == 'serial'), stats[0]['tasks_per_s'])
    serial_cpu = next((s['cpu_s'] for s in stats if s['executor'] == 'serial'), None)
    for s, rows in zip(stats, all_rows, strict=True):
        s['speedup_vs_serial'] = s['tasks_per_s'] / base
        if serial_cpu is not None:
            s['cpu_speedup'] = cpu_makespan_speedup(rows, serial_cpu)
    return stats


def throughput_markdown(stats: Sequence[dict[str, Any]]) -> str:
    lines = ['| executor | workers | tasks | wall (s) | tasks/s | speed-up vs serial | task CPU (s) | '
             'idle per task (s) | start-up (s) | Dask no-op round trip (ms) | max RSS per worker (MB) | '
             'rows identical | machine load (1 min) |', '|---' * 13 + '|']
    for s in stats:
        rt = s['dask_round_trip_s']
        lines.append(f"| {s['executor']} | {s['workers']} | {s['tasks']} | {s['wall_s']:.1f} | "
                     f"{s['tasks_per_s']:.3f} | {s['speedup_vs_serial']:.2f} | {s['cpu_s']:.1f} | "
                     f"{s['idle_per_task_s']:.3f} | {s['startup_s']:.1f} | "
                     f"{'' if math.isnan(rt) else f'{rt * 1e3:.1f}'} | {s['max_rss_mb_per_worker']:.0f} | "
                     f"{'yes' if s['identical_to_first'] else 'NO'} | {s['load_avg_1min']:.1f} |")
    return '\n'.join(lines)


def projection_markdown(task_s: float, overhead_s: float, tasks: int, cores_per_machine: int = 2,
                        machines: Sequence[int] = (1, 2, 4, 8, 16, 32)) -> str:
    """Projected wall time of ``tasks`` tasks on N machines from a per-task time and overhead.

    Assumptions: identical machines with ``cores_per_machine`` worker slots each, each slot a
    dedicated core; tasks independent, so wall = ceil(tasks / slots) × (task + overhead) (no
    straggler tail beyond one task, GPIS fits amortised as in the measurement)."""
    lines = ['| machines | worker slots | projected wall (min) | tasks/s |', '|---|---|---|---|']
    for n in machines:
        slots = n * cores_per_machine
        wall = math.ceil(tasks / slots) * (task_s + overhead_s)
        lines.append(f'| {n} | {slots} | {wall / 60:.1f} | {tasks / wall:.2f} |')
    return '\n'.join(lines)


def cpu_makespan_speedup(rows: Sequence[dict[str, Any]], serial_cpu_s: float) -> float:
    """Serial CPU time / the largest per-worker CPU sum: the speed-up with one dedicated core per
    worker (load balance included, waiting for a shared CPU excluded)."""
    per: dict[str, float] = {}
    for r in rows:
        per[r['worker']] = per.get(r['worker'], 0.0) + float(r['task_cpu_s'])
    return serial_cpu_s / max(per.values())


def throughput_report(stats: Sequence[dict[str, Any]], n_tasks: int, n_objects: int, target_objects: int = 200) -> str:
    """Throughput table, per-task CPU time, Dask overhead and the projection for ``target_objects`` objects.

    The projection takes the serial run's mean task CPU time (what a dedicated core needs) plus the
    Dask no-op round trip as the per-task overhead."""
    serial = [s for s in stats if s['executor'] == 'serial']
    dask_rows = [s for s in stats if s['executor'] == 'dask']
    ref = max(dask_rows or stats, key=lambda s: s['workers'])
    task_s = (serial[0] if serial else ref)['cpu_s'] / n_tasks
    overhead = ref['dask_round_trip_s'] if dask_rows else max(0.0, ref['idle_per_task_s'])
    per_object = n_tasks / max(1, n_objects)
    total = int(round(target_objects * per_object))
    lines = [throughput_markdown(stats), '']
    lines += [f"CPU-time speed-up ({s['executor']}, {s['workers']} workers): {s['cpu_speedup']:.2f}"
              for s in stats if 'cpu_speedup' in s]
    lines += ['', f'Mean task CPU time {task_s:.3f} s (serial); per-task overhead {overhead * 1e3:.1f} ms '
              f"({ref['executor']}, {ref['workers']} workers). Projection for {target_objects} objects x "
              f'{per_object:g} tasks per object = {total} tasks:', '',
              projection_markdown(task_s, overhead, total)]
    return '\n'.join(lines)


# =========================================================================== CLI
def _floats(text: str) -> list[float]:
    try:
        return [float(x) for x in text.split(',') if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got '{text}'") from None


def _ints(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(',') if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got '{text}'") from None


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by ``evaluate`` and ``tune``: dataset, output, executor, sample counts."""
    parser.add_argument('--dataset', required=True, help='dataset folder (gpis-grasp make-dataset) or manifest.json')
    parser.add_argument('--out', required=True, help='output folder (results.jsonl, results.csv, ...)')
    parser.add_argument('--objects', type=int, default=0, help='use only the first N objects (default: all)')
    parser.add_argument('--seeds', type=int, default=1, help='seeds 0 .. N-1 (default: %(default)s)')
    parser.add_argument('--executor', choices=EXECUTORS, default='serial')
    parser.add_argument('--workers', type=int, default=os.cpu_count() or 1,
                        help='worker processes for process / local Dask (default: %(default)s)')
    parser.add_argument('--scheduler', default='local',
                        help="Dask: 'local' (private LocalCluster on 127.0.0.1) or a scheduler address tcp://HOST:PORT")
    parser.add_argument('--affinity', choices=('object', 'task'), default='object',
                        help="parallel executors: schedule an object's tasks together or single tasks")
    parser.add_argument('--fresh', action='store_true', help='discard earlier results in --out instead of resuming')
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')
    d = EvalSettings()
    parser.add_argument('--grid-size', type=int, default=d.grid_size)
    parser.add_argument('--frames', type=int, default=d.frames)
    parser.add_argument('--grasp-samples', type=int, default=d.grasp_samples)
    parser.add_argument('--shape-samples', type=int, default=d.shape_samples)
    parser.add_argument('--initial-grasps', type=int, default=d.n_initial_grasps)
    parser.add_argument('--trials', type=int, default=d.trials, help='simulated executions per grasp')


def settings_from_args(args: argparse.Namespace) -> EvalSettings:
    return EvalSettings(grid_size=args.grid_size, frames=args.frames, grasp_samples=args.grasp_samples,
                        shape_samples=args.shape_samples, n_initial_grasps=args.initial_grasps, trials=args.trials)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='gpis-grasp evaluate', description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_run_arguments(p)
    p.add_argument('--methods', default=','.join(DEFAULT_METHODS), help='planners (default: %(default)s)')
    p.add_argument('--lambda', dest='lambdas', type=_floats, default=None, help='λ values (default: planner default)')
    p.add_argument('--alpha', dest='alphas', type=_floats, default=None, help='α values (default: planner default)')
    p.add_argument('--throughput', type=_ints, default=None, metavar='W1,W2',
                   help='measure tasks/s for these worker counts instead of a normal run')
    p.add_argument('--executors', default='serial,process,dask', help='executors of --throughput')
    return p.parse_args(argv)


def load_entries(dataset: str, limit: int = 0) -> tuple[list[dict[str, Any]], str]:
    from gpis_grasp_ros.sim.dataset import load_dataset, manifest_digest

    ds = load_dataset(dataset)
    entries = ds.entries[:limit] if limit and limit > 0 else ds.entries
    return entries, manifest_digest(ds)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        entries, digest = load_entries(args.dataset, args.objects)
        settings = settings_from_args(args)
        methods = [m.strip() for m in args.methods.split(',') if m.strip()]
        tasks = make_tasks(entries, methods, range(max(1, args.seeds)), args.lambdas or [None], args.alphas or [None],
                           settings)
    except ValueError as err:
        print(f'gpis-grasp evaluate: {err}', file=sys.stderr)
        return 2
    out = Path(args.out)
    if args.throughput:
        execs = [e.strip() for e in args.executors.split(',') if e.strip()]
        configs = [('serial', 1)] if 'serial' in execs else []
        configs += [(e, w) for e in execs if e != 'serial' for w in args.throughput]
        stats = throughput(tasks, out, configs, progress=not args.no_progress, affinity=args.affinity)
        text = throughput_report(stats, len(tasks), len(entries))
        (out / 'throughput.md').write_text(text + '\n', encoding='utf8')
        (out / 'throughput.json').write_text(json.dumps(stats, indent=1) + '\n', encoding='utf8')
        print(text)
        return 0
    try:
        run = run_evaluation(tasks, out, args.executor, args.workers, args.scheduler, fresh=args.fresh,
                             progress=not args.no_progress, dataset_digest=digest, affinity=args.affinity)
    except ValueError as err:
        print(f'gpis-grasp evaluate: {err}', file=sys.stderr)
        return 2
    table = summary_table(run.rows)
    surface = surface_table(run.rows)
    if surface:
        table += '\n\nThe GPIS near the true surface (one value per object; median over the objects):\n\n' + surface
    (out / 'summary.md').write_text(table + '\n', encoding='utf8')
    print(table)
    where = f'Dask at {args.scheduler}' if args.executor == 'dask' and args.scheduler != 'local' else \
        f'{run.executor} x {run.workers}'
    print(f'\n{len(run.rows)} of {len(tasks)} tasks done ({run.resumed} resumed) in {run.wall_time_s:.1f} s '
          f'with {where}; results in {out}')
    if run.failures:
        print(f'gpis-grasp evaluate: {len(run.failures)} task(s) failed after retry (details in '
              f'{out / "failures.jsonl"}):', file=sys.stderr)
        for f in run.failures:
            print(f"  {f['task_id']}: {f['error']}", file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
