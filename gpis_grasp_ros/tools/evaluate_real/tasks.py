"""The tasks of ``gpis-grasp evaluate-real``: one unit (capture × variant) × method × planner seed.

A unit's capture is imported in memory (:func:`~gpis_grasp_ros.data.rgbd_import.import_capture`, exactly the
scene its bag would give) or read from its bag, segmented and fitted once per process
(:func:`~gpis_grasp_ros.tools.evaluation.real.prepare_real`); each task plans and executes one grasp on it
(:func:`~gpis_grasp_ros.tools.evaluation.real.evaluate_grasp`). A refused import or segmentation is a row
with its reason. Seeds are used as given (planner and execution seed), as ``import-rgbd --evaluate`` does.
"""

from __future__ import annotations

import functools
import json
import math
import sys
import time
from collections.abc import Sequence
from typing import Any

from gpis_grasp_ros.tools.evaluation.real import RealFit, evaluate_grasp, prepare_real, sensing_params
from gpis_grasp_ros.tools.evaluation.tasks import EvalSettings, Task

#: How a row's executions failed (:class:`~gpis_grasp_ros.sim.execution.ExecutionOutcome`'s counts; 0 without a grasp)
FAILURES = ('collision', 'missed', 'slipped', 'too_wide')
#: The method name of planning GP-GPIS-OPT on the truth sampled at the planning grid (``--oracle``)
ORACLE = 'oracle'
ORACLE_PLANNER = 'gp-gpis-opt'


def unit_scene(entry: dict[str, Any]) -> tuple[Any, tuple[float, float]]:
    """The scene of a unit entry and its target pixel in the scene's image."""
    from gpis_grasp_ros.data import rgbd_import as ri
    from gpis_grasp_ros.data.bags import load_bag

    if entry['bag']:
        return load_bag(entry['bag'], frames=1), tuple(entry['target_pixel'])
    imported = import_unit(entry)
    return ri.capture_scene(imported), imported.target_px


def import_unit(entry: dict[str, Any]) -> Any:
    """:func:`~gpis_grasp_ros.data.rgbd_import.import_capture` of a raw unit entry."""
    from gpis_grasp_ros.data import rgbd_import as ri

    return ri.import_capture(entry['rgb'], entry['depth'], entry['intrinsics'], entry['depth_scale'], entry['crop'],
                             entry['scale'], entry['gt_mask'], entry['gt_depth'], tuple(entry['target_pixel']),
                             entry['sensor'])


@functools.lru_cache(maxsize=2)
def _prepared(entry_json: str, grid_size: int) -> tuple[RealFit | None, str, float]:
    entry = json.loads(entry_json)
    t0 = time.perf_counter()
    try:
        scene, target = unit_scene(entry)
    except ValueError as exc:
        return None, f'import: {exc}', time.perf_counter() - t0
    try:
        params = sensing_params(target, entry['sensor'], grid_size, entry['clear_body_height_m'])
        rf = prepare_real(scene, params, entry['id'])
    except ValueError as exc:
        return None, f'segmentation: {exc}', time.perf_counter() - t0
    return rf, '', time.perf_counter() - t0


def make_tasks(entries: Sequence[dict[str, Any]], methods: Sequence[str], seeds: Sequence[int], oracle: bool,
               trials: int, grid_size: int) -> list[Task]:
    """Unit-major tasks: every method (then the oracle) for every seed."""
    settings = EvalSettings(grid_size=int(grid_size), trials=int(trials))
    names = [*methods, *([ORACLE] if oracle else [])]
    return [Task(e, m, int(s), settings=settings) for e in entries for m in names for s in seeds]


def run_real_task(task: Task, attempt: int = 1) -> dict[str, Any]:
    """One grasp of one unit as a result row (BLAS limited to one thread, as every executor computes);
    prints a progress line on stderr."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        t0 = time.perf_counter()
        e = task.entry
        hits = _prepared.cache_info().hits
        rf, refusal, prepare_s = _prepared(json.dumps(e, sort_keys=True), int(task.settings.grid_size))
        cached = _prepared.cache_info().hits > hits
        oracle = task.method == ORACLE
        trials = int(task.settings.trials)
        row: dict[str, Any] = {'task_id': task.task_id, 'object': e['id'], 'capture': e['capture'],
                               'variant': e['variant'], 'method': task.method, 'oracle': oracle,
                               'seed': int(task.seed), 'trials': trials, 'attempts': int(attempt)}
        if rf is None:
            row.update({'status': 'refused', 'refusal': refusal, 'successes': 0, **dict.fromkeys(FAILURES, 0),
                        'p_f': math.nan,
                        'occupancy_iou': math.nan, 'mean_shape_iou': math.nan, 'jaw_clearance_m': math.nan,
                        'true_clearance_m': math.nan,
                        'objects_seen': None, 'tilt_deg': math.nan, 'message': ''})
        else:
            ev = evaluate_grasp(rf, ORACLE_PLANNER if oracle else task.method, int(task.seed), trials, oracle)
            failures = {k: 0 if ev.outcome is None else int(getattr(ev.outcome, k)) for k in FAILURES}
            row.update({'status': 'ok' if math.isfinite(ev.p_f) else 'no_grasp', 'refusal': '',
                        'successes': ev.successes, **failures, 'p_f': ev.p_f, 'occupancy_iou': ev.occupancy_iou,
                        'mean_shape_iou': ev.mean_shape_iou, 'jaw_clearance_m': ev.jaw_clearance_m,
                        'true_clearance_m': ev.true_clearance_m,
                        'objects_seen': int(ev.objects_seen), 'tilt_deg': float(ev.tilt_deg), 'message': ev.message})
        row.update({'prepare_time_s': 0.0 if cached else prepare_s, 'task_time_s': time.perf_counter() - t0})
    outcome = (f"refused ({row['refusal']})" if rf is None else
               f"{row['successes']}/{trials} closed, P_F {row['p_f']:.2f}")
    print(f"evaluate-real: {e['capture']} [{e['variant']}] {task.method} seed {task.seed}: {outcome} "
          f"({row['task_time_s']:.1f} s)", file=sys.stderr, flush=True)
    return row
