"""GP-GPIS-OPT cold against warm-started from the previous burst's plan, on every shipped simulated bag.

    python scripts/warm_start_bursts.py [--seeds 3] [--grid-size 25] [--json FILE]

Per bag (bags/*.mcap, bags/head/*.mcap; the paper's 25-cell grid, ``--grid-size 0``: the nodes' cell rule) the
frames 0-4 are the previous burst and 5-9 the new one. Per planner seed: a plan on the previous burst, then on the
new burst a cold plan (fresh initial grasps) and a plan warm-started from the previous plan's optima
(``WarmStart``), each run twice and the second timed. Printed per bag: the mean final P_F (S = 1000) of the two,
the median planning CPU time (``GraspResult.planning_cpu_time``, one BLAS thread), the summed eq. 6 evaluations,
the mean number of warm starts used, and how far each plan's grasp lies from the previous burst's (mean distance of
the two jaws in the sensor frame, either jaw order; mm, median over the seeds).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.pipeline import posterior_from_grids, publishable_grids
from gpis_grasp_ros.core.planners import GraspResult, PlannerParams, WarmStart, plan
from gpis_grasp_ros.core.sensing import SensingParams, segment_frames
from gpis_grasp_ros.core.sensing.params import PAPER_GRID_SIZE
from gpis_grasp_ros.data.bags import load_bag

BAGS = Path(__file__).resolve().parents[1] / 'bags'


def grasp_move_mm(a: GraspResult, ga: GridGeometry, b: GraspResult, gb: GridGeometry) -> float:
    """Mean distance (mm) of the two jaws of grasps ``a`` and ``b`` (planned on grids ``ga``, ``gb``) in the sensor
    frame, in whichever jaw order is nearer."""
    a1, a2, b1, b2 = ga.to_sensor(a.jaw1), ga.to_sensor(a.jaw2), gb.to_sensor(b.jaw1), gb.to_sensor(b.jaw2)
    same = np.linalg.norm(a1 - b1) + np.linalg.norm(a2 - b2)
    swap = np.linalg.norm(a1 - b2) + np.linalg.norm(a2 - b1)
    return float(500.0 * min(same, swap))


def bag_rows(path: Path, seeds: int, grid_size: int = PAPER_GRID_SIZE) -> list[dict]:
    scene = load_bag(path, frames=10)
    params = SensingParams(grid_size=grid_size)
    posts = [posterior_from_grids(*publishable_grids(segment_frames(
        scene.rgb_frames[k:k + 5], scene.depth_frames[k:k + 5], scene.intrinsics, params, frame_id=scene.frame_id)))
        for k in (0, 5)]
    rows = []
    for seed in range(seeds):
        before = plan('gp-gpis-opt', posts[0], PlannerParams(), seed=seed)
        warm_start = WarmStart.from_result(before, posts[0].geometry)
        cold = [plan('gp-gpis-opt', posts[1], PlannerParams(), seed=seed) for _ in range(2)][-1]
        warm = [plan('gp-gpis-opt', posts[1], PlannerParams(), seed=seed, warm_start=warm_start)
                for _ in range(2)][-1]
        rows.append({'bag': str(path.relative_to(BAGS).with_suffix('')), 'seed': seed, 'p_f_cold': cold.p_f,
                     'p_f_warm': warm.p_f, 'cpu_cold': cold.planning_cpu_time, 'cpu_warm': warm.planning_cpu_time,
                     'evaluations_cold': sum(r.evaluations for r in cold.restarts),
                     'evaluations_warm': sum(r.evaluations for r in warm.restarts),
                     'warm_starts': sum(r.warm for r in warm.restarts),
                     'moved_cold_mm': grasp_move_mm(before, posts[0].geometry, cold, posts[1].geometry),
                     'moved_warm_mm': grasp_move_mm(before, posts[0].geometry, warm, posts[1].geometry)})
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--seeds', type=int, default=3, help='planner seeds 0 .. N-1')
    ap.add_argument('--grid-size', type=int, default=PAPER_GRID_SIZE, help='M of the planning grid (0: the cell rule)')
    ap.add_argument('--json', type=Path, help='also write every row here')
    args = ap.parse_args()
    rows = []
    print('| bag | P_F cold | P_F warm | CPU cold (s) | CPU warm (s) | evaluations cold | warm | warm starts '
          '| moved cold (mm) | moved warm (mm) |')
    print('|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|')
    with threadpool_limits(1):
        for path in sorted(BAGS.glob('*.mcap')) + sorted((BAGS / 'head').glob('*.mcap')):
            r = bag_rows(path, args.seeds, args.grid_size)
            rows += r
            col = {k: np.array([x[k] for x in r]) for k in r[0] if k != 'bag'}
            print(f"| {r[0]['bag']} | {col['p_f_cold'].mean():.3f} | {col['p_f_warm'].mean():.3f} | "
                  f"{np.median(col['cpu_cold']):.3f} | {np.median(col['cpu_warm']):.3f} | "
                  f"{col['evaluations_cold'].sum()} | {col['evaluations_warm'].sum()} | "
                  f"{col['warm_starts'].mean():.1f} | {np.median(col['moved_cold_mm']):.1f} | "
                  f"{np.median(col['moved_warm_mm']):.1f} |", flush=True)
    for group, keep in (('top-down', lambda b: not b.startswith('head')), ('head', lambda b: b.startswith('head'))):
        sel = [x for x in rows if keep(x['bag'])]
        ratio = np.median([x['cpu_cold'] / x['cpu_warm'] for x in sel])
        p_cold, p_warm = np.mean([x['p_f_cold'] for x in sel]), np.mean([x['p_f_warm'] for x in sel])
        print(f'{group}: P_F {p_cold:.3f} -> {p_warm:.3f}, planning CPU cold / warm median {ratio:.2f}x, evaluations '
              f"{sum(x['evaluations_cold'] for x in sel)} -> {sum(x['evaluations_warm'] for x in sel)}")
        for kind in ('cold', 'warm'):
            moved = np.array([x[f'moved_{kind}_mm'] for x in sel])
            print(f'  {kind}: grasp moved from the previous burst\'s median {np.median(moved):.1f} mm, within 3 mm '
                  f'{int((moved <= 3).sum())} / over 10 mm {int((moved > 10).sum())} of {moved.size} plans')
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
