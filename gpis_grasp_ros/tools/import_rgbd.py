"""``gpis-grasp import-rgbd``: a real RGB-D capture (colour + depth + intrinsics) → a bag in the shipped layout.

Examples::

    gpis-grasp import-rgbd --rgb scene.jpg --depth scene-depth-mm.png --intrinsics camera.yaml out.mcap
    gpis-grasp import-rgbd --rgb c.png --depth d.npy --fx 615 --fy 615 --cx 320 --cy 240 out.mcap \\
        --crop 100 50 540 430 --scale 0.5
    # with ground truth for the simulated gripper / benchmark (mask of the objects + depth of the true shape)
    gpis-grasp import-rgbd --rgb c.jpg --depth d.png --intrinsics cam.yaml out.mcap \\
        --gt-mask mask.png --gt-depth opaque-depth.png --target-pixel 882 522

The bag holds one frame (RGB, 32FC1 depth, camera infos, organized XYZRGB cloud) and, with
``--gt-mask``, the ground truth of the mask component containing ``--target-pixel`` in the
table frame (see :mod:`gpis_grasp_ros.data.rgbd_import`). Replay it with ``gpis-grasp play``
into ``segmentation_node`` (``frames_to_average:=1``, ``sensor_model:=realsense_d400`` for a
RealSense, ``target:=pixel target_point:=[u, v]`` in the written image's pixels, printed below).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.core.noise_model import SENSOR_MODELS, SensorModel
from gpis_grasp_ros.core.pipeline import posterior_from_grids
from gpis_grasp_ros.core.planners import METHODS, PlannerParams, plan
from gpis_grasp_ros.core.sensing import SensingParams, SensingResult
from gpis_grasp_ros.data import rgbd_import as ri
from gpis_grasp_ros.data.bags import load_bag
from gpis_grasp_ros.tools.evaluation.tasks import fit_scene
from gpis_grasp_ros.tools.evaluation.truth import TrueShape


@dataclass
class RealEvaluation:
    """Figures of one imported capture (see :func:`evaluate_bag`)."""

    bag: str
    occupancy_iou: float  # target occupancy (>= 0.5) vs the ground truth, on the segmentation grid
    mean_shape_iou: float  # GPIS mean shape {mean < 0} vs the ground truth
    successes: int  # of ``trials`` simulated executions of the GP-GPIS-OPT grasp in force closure on the truth
    trials: int
    p_f: float
    jaw_clearance_m: float  # smallest distance (m) from a jaw centre to another object seen on the table
    #                          (evidence more than 1 cm outside the true target)
    objects_seen: int
    tilt_deg: float
    message: str = ''


def _other_objects_xy(result: SensingResult) -> np.ndarray:
    """Table-plane feet (grid x, y in m) of the evidence pixels of objects other than the target."""
    other = (result.labels_px > 0) & ~result.object_mask & np.isfinite(result.mean_depth)
    pts = result.intrinsics.rays()[other] * result.mean_depth[other][:, None]
    feet = pts - (pts @ result.table.n + result.table.offset_m)[:, None] * result.table.n
    return result.geometry.from_sensor(feet)[0]


#: SDF noise variance (m^2) of every cell when planning on the ground truth (``oracle``): a near-certain shape
ORACLE_NOISE_M2 = 1e-6


def evaluate_bag(path: str | Path, target_px: tuple[float, float], sensor: str = 'realsense_d400',
                 trials: int = 20, seed: int = 0, oracle: bool = False, grid_size: int = 25,
                 method: str = 'gp-gpis-opt', clear_body_height_m: float = 0.0,
                 uncertainty_penalty: float | None = None) -> RealEvaluation:
    """Segment an imported capture as segmentation_node does (one frame, ``target:=pixel``), fit the
    GPIS, plan GP-GPIS-OPT (or ``method``, one of :data:`~gpis_grasp_ros.core.planners.METHODS`) and execute it
    ``trials`` times on the bag's ground truth (through the camera frame: plan grid → camera → ground-truth grid).

    ``oracle``: plan on the ground truth itself instead of the perceived shape - its occupancy sampled at
    the planning grid's cell centres (0 or 100), every cell trained with ``ORACLE_NOISE_M2`` - the best any
    perception can give the planner at the grid's resolution. The IoUs are still the perceived ones.
    ``grid_size``: M of the M x M planning grid (segmentation_node's ``grid_size``); ``clear_body_height_m``: a
    clear target body's known height (m; segmentation_node's ``clear_body_height``, 0 = the priors);
    ``uncertainty_penalty``: λ of eq. 4/6 per cell² (planner_node's ``uncertainty_penalty``; None = its default)."""
    return evaluate_seeds(path, target_px, [seed], sensor, trials, oracle, grid_size, method, clear_body_height_m,
                          uncertainty_penalty)[0]


def evaluate_seeds(path: str | Path, target_px: tuple[float, float], seeds: Sequence[int],
                   sensor: str = 'realsense_d400', trials: int = 20, oracle: bool = False, grid_size: int = 25,
                   method: str = 'gp-gpis-opt', clear_body_height_m: float = 0.0,
                   uncertainty_penalty: float | None = None) -> list[RealEvaluation]:
    """:func:`evaluate_bag` for each planner and execution seed of ``seeds``: the capture is segmented and the
    GPIS fitted once."""
    planner = PlannerParams() if uncertainty_penalty is None else PlannerParams(
        uncertainty_penalty=float(uncertainty_penalty))  # checked before the segmentation
    scene = load_bag(path, frames=1)
    if scene.true_sdf is None or scene.true_geometry is None:
        raise ValueError(f'{path}: no ground truth in the bag')
    params = SensingParams(sensor=SensorModel.named(sensor), target='pixel', target_point=tuple(target_px),
                           grid_size=int(grid_size), clear_body_height_m=float(clear_body_height_m))
    fit = fit_scene(scene, params)
    posterior, result = fit.posterior, fit.sensing
    g = result.geometry
    true_shape = TrueShape(scene.true_sdf, scene.true_geometry, g)
    truth = true_shape.values_at(g.cell_centers()) < 0
    mean_shape = posterior.mean < 0
    if oracle:
        posterior = posterior_from_grids(np.where(truth, 100, 0).astype(np.int8), np.full(g.shape, ORACLE_NOISE_M2), g)

    def iou(a: np.ndarray) -> float:
        return float((a & truth).sum() / max((a | truth).sum(), 1))

    occupancy_iou, mean_shape_iou = iou(result.occupancy >= 0.5), iou(mean_shape)
    gripper = GripperParams().resolved(g)
    others = _other_objects_xy(result)  # other objects seen, minus fragments of the true target (1 cm)
    if len(others):
        others = others[~(true_shape.values_at(others) < 0.01)]
    out = []
    for seed in seeds:
        grasp = plan(method, posterior, planner, seed=seed)
        if not grasp.success:
            out.append(RealEvaluation(str(path), occupancy_iou, mean_shape_iou, 0, trials, float('nan'), float('nan'),
                                      result.objects_seen, result.table.tilt_deg, grasp.message))
            continue
        ok = true_shape.execute(grasp.jaw1, grasp.jaw2, gripper, trials, np.random.default_rng(seed))
        clearance = (float(min(np.linalg.norm(others - np.asarray(j), axis=1).min() for j in (grasp.jaw1, grasp.jaw2)))
                     if len(others) else float('inf'))
        out.append(RealEvaluation(str(path), occupancy_iou, mean_shape_iou, int(ok), trials, float(grasp.p_f),
                                  clearance, result.objects_seen, result.table.tilt_deg, grasp.message))
    return out


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='gpis-grasp import-rgbd', description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('output', help='bag to write (NAME.mcap = one MCAP file, any other name = a rosbag2 '
                   'directory); with --evaluate: the bag to evaluate')
    p.add_argument('--rgb', help='colour image, 8-bit, any format OpenCV reads (PNG, JPEG, ...); required '
                   'unless --evaluate')
    p.add_argument('--depth', help='depth registered to the colour image: 16-bit PNG (integer units of '
                   '--depth-scale, 0 = no return), 32-bit float TIFF, PFM or OpenEXR .exr (m), or .npy (integer = '
                   'units of --depth-scale, float = m); required unless --evaluate')
    p.add_argument('--depth-scale', type=float, default=0.001,
                   help='m per unit of integer depth (--depth, --gt-depth); float depth is always m '
                        '(default 0.001: mm)')
    p.add_argument('--intrinsics', help='YAML or JSON file with fx, fy, cx, cy (px) or _fx, _fy, _cx, _cy, and '
                   'optionally width, height (px; default: the image size), or CameraInfo-like K / camera_matrix; '
                   'no default: give this or all of --fx --fy --cx --cy')
    for name in ('fx', 'fy', 'cx', 'cy'):
        p.add_argument(f'--{name}', type=float,
                       help=f'{name} in px of the full-resolution image (instead of --intrinsics; no default)')
    p.add_argument('--crop', type=int, nargs=4, metavar=('U0', 'V0', 'U1', 'V1'),
                   help='keep pixels U0 <= u < U1, V0 <= v < V1 (px of the full-resolution image; intrinsics '
                        'follow; default: no crop)')
    p.add_argument('--scale', type=float, default=1.0,
                   help='downscale factor in (0, 1] applied after cropping (1 = full resolution; default 1)')
    p.add_argument('--gt-mask', help='ground truth: mask image of the objects, size of the capture (red or grey '
                   'channel > 0 = object; the component containing --target-pixel is the target; default: no '
                   'ground truth)')
    p.add_argument('--gt-depth', help='ground truth: depth of the true shape, e.g. opaque copies of clear objects '
                   '(same formats and units as --depth; default: no ground truth)')
    p.add_argument('--target-pixel', type=float, nargs=2, metavar=('U', 'V'),
                   help='a pixel (px) on the target: of the full-resolution image when importing (for the ground '
                        'truth), of the bag image with --evaluate; no default')
    p.add_argument('--sensor', default='realsense_d400', choices=[m for m in SENSOR_MODELS if m != 'custom'],
                   help='depth-noise model of the camera: sets both the table-plane fit of the ground truth when '
                        'importing and the segmentation of --evaluate (segmentation_node\'s sensor_model; '
                        'default realsense_d400)')
    p.add_argument('--frame-id', default=ri.FRAME_ID,
                   help=f'frame_id written into every message header (default {ri.FRAME_ID})')
    p.add_argument('--overwrite', action='store_true',
                   help='replace an existing OUTPUT (default: refuse to overwrite)')
    p.add_argument('--evaluate', action='store_true',
                   help='instead of importing: evaluate the bag OUTPUT (segmentation with --sensor and target pixel '
                        '--target-pixel in the bag image, the --method planner, --trials simulated executions on its '
                        'ground truth; default: import)')
    p.add_argument('--trials', type=int, default=20,
                   help='--evaluate: simulated executions of the planned grasp on the ground truth (default 20)')
    p.add_argument('--seed', type=int, default=0, help='--evaluate: planner and execution seed (default 0)')
    p.add_argument('--seeds', type=int, default=1,
                   help='--evaluate: run seeds SEED ... SEED + SEEDS - 1 and print their successes and mean '
                        '(default 1)')
    p.add_argument('--grid-size', type=int, default=25,
                   help='--evaluate: M of the M x M planning grid, cells (default 25)')
    p.add_argument('--method', default='gp-gpis-opt', choices=METHODS,
                   help='--evaluate: planner (default gp-gpis-opt, as planner_node)')
    p.add_argument('--clear-body-height', type=float, default=0.0, metavar='M',
                   help='--evaluate: a clear target body\'s known height in m (segmentation_node\'s '
                        'clear_body_height; default 0 = the priors)')
    p.add_argument('--lambda', dest='uncertainty_penalty', type=float, default=None, metavar='L',
                   help='--evaluate: λ of eq. 4/6 per cell² of SDF variance (planner_node\'s uncertainty_penalty; '
                        'default: its default, 2)')
    p.add_argument('--oracle', action='store_true',
                   help='--evaluate: plan on the ground truth sampled at the planning grid (the best any perception '
                        'can do at that resolution) instead of the perceived shape (default: the perceived shape)')
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.evaluate:
        if not args.target_pixel:
            print('import-rgbd: error: --evaluate needs --target-pixel U V (pixels of the bag image)', file=sys.stderr)
            return 2
        if args.seeds < 1:
            print('import-rgbd: error: --seeds must be >= 1', file=sys.stderr)
            return 2
        seeds = range(args.seed, args.seed + args.seeds)
        try:
            evs = evaluate_seeds(args.output, tuple(args.target_pixel), seeds, args.sensor, args.trials, args.oracle,
                                 args.grid_size, args.method, args.clear_body_height, args.uncertainty_penalty)
        except (ValueError, FileNotFoundError) as exc:
            print(f'import-rgbd: error: {exc}', file=sys.stderr)
            return 2
        for seed, ev in zip(seeds, evs, strict=True):
            print(f'{ev.bag}{" (planned on the ground truth)" if args.oracle else ""} seed {seed}: tilt '
                  f'{ev.tilt_deg:.1f} deg, {ev.objects_seen} object(s) seen; target occupancy IoU '
                  f'{ev.occupancy_iou:.2f}, mean-shape IoU {ev.mean_shape_iou:.2f}; {args.method} {ev.successes}/'
                  f'{ev.trials} in force closure on the true shape (P_F {ev.p_f:.2f}); nearest other object '
                  f'{ev.jaw_clearance_m * 1000:.0f} mm from a jaw {ev.message}')
        if len(evs) > 1:
            wins = [e.successes for e in evs]
            print(f'seeds {args.seed}-{args.seed + args.seeds - 1}: successes {wins}, mean {np.mean(wins):.1f} of '
                  f'{args.trials}; P_F {min(e.p_f for e in evs):.2f}-{max(e.p_f for e in evs):.2f}')
        return 0
    try:
        if not (args.rgb and args.depth):
            raise ValueError('give --rgb and --depth')
        if args.intrinsics:
            intr = args.intrinsics
        elif None not in (args.fx, args.fy, args.cx, args.cy):
            intr = {'fx': args.fx, 'fy': args.fy, 'cx': args.cx, 'cy': args.cy}
        else:
            raise ValueError('give --intrinsics FILE or all of --fx --fy --cx --cy')
        capture = ri.load_capture(args.rgb, args.depth, intr, args.depth_scale)
        extra = {}
        if args.gt_mask or args.gt_depth or args.target_pixel:
            if not (args.gt_mask and args.gt_depth and args.target_pixel):
                raise ValueError('ground truth needs all of --gt-mask, --gt-depth and --target-pixel')
            extra['mask'] = ri.load_rgb(args.gt_mask)[..., 0]
            extra['true_depth'] = ri.load_depth(args.gt_depth, args.depth_scale)
            if extra['mask'].shape != capture.depth.shape or extra['true_depth'].shape != capture.depth.shape:
                raise ValueError('--gt-mask and --gt-depth must have the size of the capture')
        crop = tuple(args.crop) if args.crop else None
        small, _ = ri.crop_and_scale(capture, crop, args.scale)
        truth, target = None, None
        if args.target_pixel:
            target = ri.map_pixel(*args.target_pixel, crop, args.scale)
            table = ri.capture_table(small, SensorModel.named(args.sensor))
            # the ground truth keeps the full resolution: only the crop applies to it (module docstring)
            full, extra = ri.crop_and_scale(capture, crop, 1.0, extra)
            truth = ri.ground_truth_from_mask(full, extra['mask'], extra['true_depth'], ri.map_pixel(*args.target_pixel,
                                              crop, 1.0), table, frame_id=args.frame_id)
        meta = {'rgb': str(args.rgb), 'depth': str(args.depth), 'crop': args.crop, 'scale': args.scale,
                'target_pixel': None if target is None else [round(target[0], 2), round(target[1], 2)],
                'sensor': args.sensor}
        path = ri.write_capture_bag(small, args.output, truth, meta, overwrite=args.overwrite,
                                    frame_id=args.frame_id)
    except (ValueError, FileNotFoundError, FileExistsError) as exc:
        print(f'import-rgbd: error: {exc}', file=sys.stderr)
        return 2
    i = small.intrinsics
    print(f'wrote {path}: 1 frame {i.width} x {i.height}, fx {i.fx:.1f} fy {i.fy:.1f} cx {i.cx:.1f} cy {i.cy:.1f}'
          + ('' if truth is None else f'; ground truth {truth.geometry.width} x {truth.geometry.height} cells in the '
             f'table frame (tilt {truth.table.tilt_deg:.1f} deg); target pixel in the bag ({target[0]:.1f}, '
             f'{target[1]:.1f})'))
    return 0


if __name__ == '__main__':
    sys.exit(main())
