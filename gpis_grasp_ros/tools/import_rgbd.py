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

import numpy as np

from gpis_grasp_ros.core.noise_model import SENSOR_MODELS
from gpis_grasp_ros.core.planners import METHODS
from gpis_grasp_ros.core.planners.params import UNCERTAINTY_PENALTY
from gpis_grasp_ros.core.sensing.params import SensingParams
from gpis_grasp_ros.data import rgbd_import as ri
from gpis_grasp_ros.tools.evaluation.real import evaluate_seeds


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
    p.add_argument('--grid-size', type=int, default=SensingParams.grid_size,
                   help=f'--evaluate: force M of the M x M planning grid, cells (default {SensingParams.grid_size}, as '
                        'segmentation_node: from the object and the cell size)')
    p.add_argument('--method', default='gp-gpis-opt', choices=METHODS,
                   help='--evaluate: planner (default gp-gpis-opt, as planner_node)')
    p.add_argument('--clear-body-height', type=float, default=0.0, metavar='M',
                   help='--evaluate: a clear target body\'s known height in m (segmentation_node\'s '
                        'clear_body_height; default 0 = the priors)')
    p.add_argument('--lambda', dest='uncertainty_penalty', type=float, default=None, metavar='L',
                   help='--evaluate: λ of eq. 4/6 per m² of SDF variance (planner_node\'s uncertainty_penalty; '
                        f'default: its default, {UNCERTAINTY_PENALTY:g})')
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
            executed = ev.outcome.describe() if ev.outcome else f'0/{ev.trials} in force closure (no grasp)'
            truth_clear = ('none in the truth' if np.isinf(ev.true_clearance_m) else
                           f'of the truth {ev.true_clearance_m * 1000:.0f} mm')
            print(f'{ev.bag}{" (planned on the ground truth)" if args.oracle else ""} seed {seed}: tilt '
                  f'{ev.tilt_deg:.1f} deg, {ev.objects_seen} object(s) seen; target occupancy IoU '
                  f'{ev.occupancy_iou:.2f}, mean-shape IoU {ev.mean_shape_iou:.2f}; {args.method} {executed} '
                  f'on the true shape (P_F {ev.p_f:.2f}); nearest other object seen '
                  f'{ev.jaw_clearance_m * 1000:.0f} mm from a jaw, {truth_clear} {ev.message}')
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
        crop = tuple(args.crop) if args.crop else None
        imported = ri.import_capture(args.rgb, args.depth, intr, args.depth_scale, crop, args.scale, args.gt_mask,
                                     args.gt_depth, tuple(args.target_pixel) if args.target_pixel else None,
                                     args.sensor, args.frame_id)
        small, truth, target = imported.capture, imported.truth, imported.target_px
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
