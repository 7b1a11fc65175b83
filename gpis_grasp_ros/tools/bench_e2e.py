"""End-to-end replanning benchmark: camera frames → segmentation → GPIS (ML hyperparameters) → GP-GPIS-OPT → final P_F.

    python -m gpis_grasp_ros.bench e2e [--repeats N] [--seed S] [--blas-threads T] [--no-frames] [--grid-size M]

Each stage is the project's own call timed with ``time.perf_counter`` (one BLAS thread by default, through
threadpoolctl, as the GPIS fit sets it itself): segmentation = ``segment_frames`` + the published grids
(:func:`~gpis_grasp_ros.core.pipeline.publishable_grids`), GPIS = ``posterior_from_grids`` with the
maximum-likelihood search (and, as "of which search", that time minus a fit with C and l fixed at the values
found), GP-GPIS-OPT = the planner's planning time (``GraspResult.planning_time``, N_g = 20), final P_F = its
evaluation time (what follows the search: the S = 1000 fresh joint samples are drawn on the other core during it,
then the Monte-Carlo test), end to end = the wall time of the whole
chain (and its CPU time, less sensitive to a shared machine's load). ``--repeats`` runs of every stage after one
warm-up chain (which also loads the compiled kernels); the table gives median and min (s).

The GPIS and planning stages are timed cold (the multi-start search gpis_node runs on the first frame of a
``frame_id``; fresh initial grasps) and warm, as the nodes treat the next burst of the same scene: the warm-up
chain runs on the first half of the bag's frames (the previous burst), every timed chain on the second half
(the new burst: 5 of the bags' 10 frames; the real capture's one frame is both), and "warm" chains pass the
warm-up's fit as the GPIS ``warm_start`` (the score test keeps it or re-searches from it) and its plan's local
optima as the planner's (:class:`~gpis_grasp_ros.core.planners.WarmStart`); "drifted" fits
pass the fit with C x 1.5 and l x 0.85 (the test rejects it and the search runs from there; timed alone, not
in a chain); ev = likelihood evaluations.

The planning grid is the paper's M = 25 (the camera-rate targets are set there); ``--grid-size 0`` times
segmentation_node's default, the 3 mm cell rule (M = 30-100 on the shipped bags).

Rows: a top-down bag, a head-camera bag, a real D435 capture, and whole-frame segmentation (no crop) of
simulated 640 x 480 and 1280 x 720 frames, of the largest object and of the object at a target pixel (its window).
The machine may be shared: the load average is printed with the table.
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from gpis_grasp_ros.core.gpis import GpisParams, HyperparameterFit
from gpis_grasp_ros.core.noise_model import SensorModel
from gpis_grasp_ros.core.pipeline import posterior_from_grids, publishable_grids
from gpis_grasp_ros.core.planners import PlannerParams, WarmStart, plan
from gpis_grasp_ros.core.sensing import CameraIntrinsics, SensingParams, segment_frames
from gpis_grasp_ros.core.sensing.params import PAPER_GRID_SIZE
from gpis_grasp_ros.data.bags import load_bag
from gpis_grasp_ros.tools.bench_gpis import drifted

BAG_DIR = Path(__file__).resolve().parents[2] / 'bags'


@dataclass(frozen=True)
class BagCase:
    """One bag of the table: its path under ``bags/``, the frames read and the segmentation settings."""

    label: str
    path: str
    frames: int = 10
    sensing: SensingParams = SensingParams(grid_size=PAPER_GRID_SIZE)


def bag_cases(grid_size: int = PAPER_GRID_SIZE) -> list[BagCase]:
    """The benchmark's bags: top-down and head-camera object A (simulated), the real D435 bottle."""
    grid = SensingParams(grid_size=grid_size)
    bottle = SensingParams(sensor=SensorModel.named('realsense_d400'), target='pixel', target_point=(220.8, 160.8),
                           grid_size=grid_size)
    return [BagCase('top-down A', 'A_tape_dispenser.mcap', sensing=grid),
            BagCase('head A', 'head/A_tape_dispenser.mcap', sensing=grid),
            BagCase('real D435 bottle', 'real/cleargrasp_000000080_bottle.mcap', 1, bottle)]


def bursts(n_frames: int) -> tuple[slice, slice]:
    """(previous burst, timed burst) of a bag's frames: its two halves; the one frame twice if it holds one."""
    if n_frames < 2:
        return slice(0, 1), slice(0, 1)
    half = n_frames // 2
    return slice(0, half), slice(half, 2 * half)


def _stats(times: list[float]) -> tuple[float, float]:
    return float(np.min(times)), float(np.median(times))


def _load() -> str:
    try:
        return ' '.join(f'{v:.1f}' for v in os.getloadavg())
    except OSError:
        return 'n/a'


def time_chain(scene, sensing: SensingParams, planner: PlannerParams, seed: int, previous: dict | None = None,
               frames: slice = slice(None)) -> dict:
    """One timed chain on ``frames`` of a loaded bag: stage times (s), the planned grasp's P_F, the fit, its
    evaluations and the plan; ``previous`` (an earlier chain's output) warm-starts the GPIS fit and the planner
    (None: cold search, fresh initial grasps)."""
    fit_warm = None if previous is None else previous['fit']
    plan_warm = None if previous is None else WarmStart.from_result(previous['grasp'], previous['grids'][2])
    c0 = time.process_time()
    t0 = time.perf_counter()
    result = segment_frames(scene.rgb_frames[frames], scene.depth_frames[frames], scene.intrinsics, sensing,
                            frame_id=scene.frame_id)
    occ, noise, geometry = publishable_grids(result)
    t1 = time.perf_counter()
    posterior = posterior_from_grids(occ, noise, geometry, warm_start=fit_warm)
    t2 = time.perf_counter()
    grasp = plan('gp-gpis-opt', posterior, planner, seed=seed, warm_start=plan_warm)
    t3 = time.perf_counter()
    cpu = time.process_time() - c0
    # the same fit with C and l fixed at the values found: the rest of the GPIS time is the search
    fixed = GpisParams(optimize_hyperparameters=False, signal_variance=posterior.params.signal_variance,
                       length_scale=posterior.params.length_scale)
    t4 = time.perf_counter()
    posterior_from_grids(occ, noise, geometry, fixed)
    t5 = time.perf_counter()
    fit = posterior.hyperparameter_fit
    return {'segmentation': t1 - t0, 'gpis': t2 - t1, 'search': (t2 - t1) - (t5 - t4), 'plan': grasp.planning_time,
            'p_f': grasp.evaluation_time, 'e2e': t3 - t0, 'e2e_cpu': cpu, 'P_F': grasp.p_f, 'fit': fit,
            'ev': fit.n_evaluations, 'grids': (occ, noise, geometry), 'grasp': grasp}


def time_drifted(grids, fit: HyperparameterFit, repeats: int) -> tuple[list[float], HyperparameterFit]:
    """GPIS fit times (s) with the warm start ``fit`` off by C x 1.5, l x 0.85 (re-searched) and the last fit."""
    times, out = [], fit
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = posterior_from_grids(*grids, warm_start=drifted(fit)).hyperparameter_fit
        times.append(time.perf_counter() - t0)
    return times, out


def _cell(times: list[float]) -> str:
    lo, med = _stats(times)
    return f'{med:.3f} (min {lo:.3f})'


def _column(runs: list[dict], key: str) -> str:
    return _cell([r[key] for r in runs])


def whole_frame_scene(width: int, height: int, frames: int = 10):
    """A simulated object A on the table seen whole-frame (no crop) by a ``width`` x ``height`` camera
    (the Carmine's field of view: focal length scaled with the width)."""
    from gpis_grasp_ros.sim.scene import CameraModel, Scene, SceneSpec, load_polygon_csv

    f = 570.3 * width / 640.0
    cam = CameraModel(fx=f, fy=f, cx=(width - 1) / 2.0, cy=(height - 1) / 2.0, width=width, height=height)
    outline = load_polygon_csv(BAG_DIR / 'objects' / 'A_tape_dispenser.csv')
    scene = Scene(SceneSpec(outline=outline, frames=frames, camera=cam, crop_margin_px=10 ** 6))
    fr = list(scene.frames())
    return (np.stack([x.rgb for x in fr]), np.stack([x.depth for x in fr]).astype(np.float64),
            CameraIntrinsics(*scene.intrinsics))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m gpis_grasp_ros.bench e2e', description=__doc__.split('\n')[0])
    ap.add_argument('--repeats', type=int, default=3, help='timed runs of every stage (min and median reported)')
    ap.add_argument('--seed', type=int, default=0, help='planner seed')
    ap.add_argument('--blas-threads', type=int, default=1, help='BLAS threads during every timed call')
    ap.add_argument('--no-frames', action='store_true', help='skip the whole-frame segmentation rows')
    ap.add_argument('--grid-size', type=int, default=PAPER_GRID_SIZE,
                    help=f'M of the planning grid (default {PAPER_GRID_SIZE}, the paper\'s; 0 = the cell rule)')
    args = ap.parse_args(argv)
    planner = PlannerParams()
    print(f'end to end: segmentation -> GPIS (ML) -> GP-GPIS-OPT (N_g = {planner.n_initial_grasps}) -> final P_F '
          f'(S = {planner.n_shape_samples}); {args.repeats} runs after a warm-up, {args.blas_threads} BLAS thread(s); '
          f'load average before: {_load()}')
    print('\n| scene | segmentation (s) | GPIS cold (s) | ev | of which search (s) | GPIS warm (s) | ev '
          '| of which search (s) | GPIS drifted (s) | ev | GP-GPIS-OPT cold (s) | GP-GPIS-OPT warm (s) | final P_F (s) '
          '| end to end cold (s) | end to end warm (s) | end to end cold, CPU (s) | end to end warm, CPU (s) '
          '| P_F cold | P_F warm |')
    print('|---|' + '---:|' * 18)
    with threadpool_limits(args.blas_threads):
        for case in bag_cases(args.grid_size):
            scene = load_bag(BAG_DIR / case.path, frames=case.frames)
            before, burst = bursts(scene.depth_frames.shape[0])
            previous = time_chain(scene, case.sensing, planner, args.seed, frames=before)  # warm-up, warm-starts
            n = max(1, args.repeats)
            cold = [time_chain(scene, case.sensing, planner, args.seed, frames=burst) for _ in range(n)]
            warm = [time_chain(scene, case.sensing, planner, args.seed, previous, frames=burst) for _ in range(n)]
            drift, drift_fit = time_drifted(previous['grids'], previous['fit'], n)
            both = cold + warm
            col = _column
            cells = [col(both, 'segmentation'), col(cold, 'gpis'), str(cold[-1]['ev']), col(cold, 'search'),
                     col(warm, 'gpis'), str(warm[-1]['ev']), col(warm, 'search'), _cell(drift),
                     str(drift_fit.n_evaluations), col(cold, 'plan'), col(warm, 'plan'), col(both, 'p_f'),
                     col(cold, 'e2e'), col(warm, 'e2e'), col(cold, 'e2e_cpu'), col(warm, 'e2e_cpu'),
                     f'{cold[-1]["P_F"]:.3f}', f'{warm[-1]["P_F"]:.3f}']
            print(f'| {case.label} | ' + ' | '.join(cells) + ' |', flush=True)
        if not args.no_frames:
            print('\n| whole frame | segmentation, largest object (s) | segmentation, target pixel on it (s) |'
                  '\n|---|---:|---:|')
            for w, h in ((640, 480), (1280, 720)):
                rgb, depth, intr = whole_frame_scene(w, h)
                cells = []
                # the object stands on the optical axis: the principal point is on it (target:=pixel, its window)
                at_pixel = SensingParams(grid_size=args.grid_size, target='pixel', target_point=(intr.cx, intr.cy))
                for sensing in (SensingParams(grid_size=args.grid_size), at_pixel):
                    times = []
                    for _ in range(max(1, args.repeats) + 1):
                        t0 = time.perf_counter()
                        publishable_grids(segment_frames(rgb, depth, intr, sensing))
                        times.append(time.perf_counter() - t0)
                    lo, med = _stats(times[1:])
                    cells.append(f'{med:.3f} (min {lo:.3f})')
                print(f'| {w} x {h}, {rgb.shape[0]} frames | ' + ' | '.join(cells) + ' |', flush=True)
    print(f'\nload average after: {_load()}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
