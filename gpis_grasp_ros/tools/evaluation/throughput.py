"""Throughput of the executors: tasks/s, CPU time and memory of one task list per (executor, workers)."""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from gpis_grasp_ros.tools.evaluation import tasks as _tasks
from gpis_grasp_ros.tools.evaluation.reports import comparable
from gpis_grasp_ros.tools.evaluation.runner import dask_client, run_evaluation
from gpis_grasp_ros.tools.evaluation.tasks import Task


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
        _tasks._object_model_cached.cache_clear()
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


def cpu_makespan_speedup(rows: Sequence[dict[str, Any]], serial_cpu_s: float) -> float:
    """Serial CPU time / the largest per-worker CPU sum: the speed-up with one dedicated core per
    worker (load balance included, waiting for a shared CPU excluded)."""
    per: dict[str, float] = {}
    for r in rows:
        per[r['worker']] = per.get(r['worker'], 0.0) + float(r['task_cpu_s'])
    return serial_cpu_s / max(per.values())
