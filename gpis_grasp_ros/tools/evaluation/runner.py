"""Executors of the evaluations: serial, process (spawned pool) and Dask, behind one interface.

:func:`run_evaluation` runs a list of :class:`~gpis_grasp_ros.tools.evaluation.tasks.Task` s on any of
the three (incremental results, retries, resume; see :mod:`gpis_grasp_ros.tools.evaluate`);
:func:`map_reporting` runs one function per item in this process or a spawned pool with progress
messages (the benchmark's objects). Every worker computes with one BLAS thread, so the numbers do not
depend on the executor. ``--scheduler local`` starts a private
``LocalCluster(host='127.0.0.1', dashboard_address=None)``: every socket on the loopback, no dashboard.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import multiprocessing as mp
import os
import queue
import sys
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gpis_grasp_ros.tools.evaluation.reports import ResultWriter, prepare_out, read_results, write_csv
from gpis_grasp_ros.tools.evaluation.tasks import Task, execute

EXECUTORS = ('serial', 'process', 'dask')
BLAS_ENV = ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS', 'VECLIB_MAXIMUM_THREADS',
            'NUMEXPR_NUM_THREADS')


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

    def __init__(self, writer: ResultWriter, fail_writer: ResultWriter, bar: Any, max_attempts: int) -> None:
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


_PROGRESS_QUEUE: Any = None  # set in process-pool workers by worker_init


def worker_init(progress_queue: Any = None) -> None:
    """Worker start-up: remember the progress queue; limit BLAS/OpenMP pools to one thread (threadpoolctl)."""
    from threadpoolctl import threadpool_limits

    global _PROGRESS_QUEUE
    _PROGRESS_QUEUE = progress_queue
    threadpool_limits(limits=1)


@contextlib.contextmanager
def process_pool(workers: int, progress_queue: Any = None) -> Iterator[ProcessPoolExecutor]:
    """``workers`` spawned processes, each with one BLAS thread (and ``progress_queue`` for :func:`call_reporting`)."""
    ctx = mp.get_context('spawn')
    with _single_thread_env(), ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=worker_init,
                                                   initargs=(progress_queue,)) as pool:
        yield pool


def _run_process(units: Sequence[Unit], col: _Collector, fn: Callable[[Task, int], dict[str, Any]],
                 workers: int) -> None:
    with process_pool(workers) as pool:
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
    worker_init()
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
    files = prepare_out(Path(out), fingerprint(tasks, dataset_digest), fresh)
    done_ids = {r['task_id'] for r in read_results(files.results)}
    todo = [t for t in tasks if t.task_id not in done_ids]
    from tqdm import tqdm

    writer, fail_writer = ResultWriter(files.results), ResultWriter(files.failures)
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


# =========================================================================== one function per item, with progress
def call_reporting(fn: Callable[[Any, Callable[[Any], None] | None], Any], item: Any) -> Any:
    """``fn(item, report)`` in a pool worker, ``report`` putting messages on the pool's progress queue."""
    q = _PROGRESS_QUEUE
    return fn(item, None if q is None else q.put)


def map_reporting(fn: Callable[[Any, Callable[[Any], None] | None], Any], items: Sequence[Any], workers: int,
                  advance: Callable[[Any], None], total: Callable[[], bool] | None = None) -> list[Any]:
    """``[fn(item, report) for item in items]`` in this process (``workers`` 1) or ``workers`` spawned processes.

    ``report(message)`` reaches ``advance(message)`` in this process (through a queue from the workers;
    late messages are awaited until ``total()`` says all arrived, at most 2 s). One BLAS thread everywhere."""
    from threadpoolctl import threadpool_limits

    if workers == 1:
        with threadpool_limits(limits=1):
            return [fn(item, advance) for item in items]
    results: dict[int, Any] = {}
    ctx = mp.get_context('spawn')
    progress_queue = ctx.Queue()
    with process_pool(workers, progress_queue) as pool:
        futures: dict[Future, int] = {pool.submit(call_reporting, fn, item): i for i, item in enumerate(items)}
        pending = set(futures)
        while pending:
            done, pending = wait(pending, timeout=0.25, return_when=FIRST_COMPLETED)
            drain(progress_queue, advance)
            for fut in done:
                results[futures[fut]] = fut.result()
        # Messages still in the workers' queue feeders: wait for them (bounded).
        drain(progress_queue, advance, wait_s=2.0, complete=total)
    progress_queue.close()
    progress_queue.join_thread()
    return [results[i] for i in range(len(items))]


def drain(progress_queue: Any, advance: Callable[[Any], None], wait_s: float = 0.0,
          complete: Callable[[], bool] | None = None) -> None:
    """Hand every queued progress message to ``advance``; block up to ``wait_s`` for late ones until ``complete()``."""
    deadline = time.perf_counter() + wait_s
    while True:
        if complete is not None and complete():
            return
        try:
            left = deadline - time.perf_counter()
            item = progress_queue.get(timeout=min(left, 0.2)) if left > 0 else progress_queue.get_nowait()
        except queue.Empty:
            if time.perf_counter() >= deadline:
                return
            continue
        advance(item)
