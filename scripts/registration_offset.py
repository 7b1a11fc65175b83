"""Where the depth sees an object against where its mask (and colour) says it is: the depth-colour registration.

    python scripts/registration_offset.py DATA [--only NAME ...] [--radius 8] [--shift DV DU]

``DATA`` holds ``cleargrasp-d435/`` and ``gqcnn-primesense/`` as for ``scripts/segmentation_report.py`` (the same
captures, target pixels and crops). For each capture, cropped, the target is segmented as segmentation_node does
it and the depth evidence (``SensingResult.depth_mask``) near the target is compared with the ground-truth mask:
the integer image shift (rows, columns) within ``--radius`` pixels that maximises their IoU, the IoU unshifted and
at that shift, and the same for the colour evidence. A registered sensor gives a best shift of (0, 0) for both.
With ``--shift DV DU`` the depth image is moved by that many rows and columns before segmentation (the rows or
columns it leaves are copied from the edge) and the occupancy IoU against the true footprint is printed as well,
to see what a registration correction would change.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from segmentation_report import CAPTURES, load, measure  # noqa: E402

from gpis_grasp_ros.core.noise_model import SensorModel  # noqa: E402
from gpis_grasp_ros.core.sensing import SensingParams, segment_frames  # noqa: E402
from gpis_grasp_ros.data import rgbd_import as ri  # noqa: E402


def best_shift(moving: np.ndarray, fixed: np.ndarray, radius: int) -> tuple[float, int, int]:
    """(IoU, rows, columns) of the integer shift of ``moving`` within ``radius`` that overlaps ``fixed`` most."""
    best = (-1.0, 0, 0)
    for dv in range(-radius, radius + 1):
        for du in range(-radius, radius + 1):
            s = np.roll(moving, (dv, du), axis=(0, 1))
            iou = float((s & fixed).sum() / max((s | fixed).sum(), 1))
            best = max(best, (iou, dv, du))
    return best


def shifted(depth: np.ndarray, dv: int, du: int) -> np.ndarray:
    """``depth`` moved by ``dv`` rows and ``du`` columns, the vacated rows and columns copied from the edge."""
    h, w = depth.shape
    rows = np.clip(np.arange(h) - dv, 0, h - 1)
    cols = np.clip(np.arange(w) - du, 0, w - 1)
    return depth[np.ix_(rows, cols)]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('data', type=Path)
    p.add_argument('--only', nargs='*', default=None, help='capture names (e.g. "single 0")')
    p.add_argument('--radius', type=int, default=8, help='largest shift tried (px)')
    p.add_argument('--shift', type=int, nargs=2, default=None, metavar=('DV', 'DU'),
                   help='also segment with the depth moved by DV rows and DU columns')
    a = p.parse_args(argv)
    head = ('| capture | depth IoU at (0, 0) | best depth shift (rows, cols): IoU | colour IoU at (0, 0) '
            '| best colour shift |')
    if a.shift:
        head += f' occupancy IoU | with the depth moved by ({a.shift[0]}, {a.shift[1]}) |'
    print(head)
    print('|' + '---|' * (head.count('|') - 1))
    for name, kind, ident, target, crop, scale in CAPTURES:
        if a.only and name not in a.only:
            continue
        cap, mask, true_depth, sensor = load(a.data, kind, ident)
        small, extra = ri.crop_and_scale(cap, crop, scale, {'mask': mask.astype(np.uint8)})
        tp = ri.map_pixel(*target, crop, scale)
        params = SensingParams(sensor=SensorModel.named(sensor), target='pixel', target_point=tuple(tp))
        res = segment_frames(small.rgb, small.depth, small.intrinsics, params)
        gt = extra['mask'] > 0
        vv, uu = np.nonzero(gt | res.object_mask)
        near = np.zeros_like(gt)
        near[max(vv.min() - 20, 0):vv.max() + 20, max(uu.min() - 20, 0):uu.max() + 20] = True
        d, c = res.depth_mask & near, res.rgb_mask & near
        d0 = float((d & gt).sum() / max((d | gt).sum(), 1))
        c0 = float((c & gt).sum() / max((c | gt).sum(), 1))
        bd, bc = best_shift(d, gt, a.radius), best_shift(c, gt, a.radius)
        row = (f'| {name} | {d0:.2f} | ({bd[1]:+d}, {bd[2]:+d}): {bd[0]:.2f} | {c0:.2f} | '
               f'({bc[1]:+d}, {bc[2]:+d}): {bc[0]:.2f} |')
        if a.shift:
            before = measure(cap, mask, true_depth, target, crop, scale, sensor)
            moved = dataclasses.replace(cap, depth=shifted(cap.depth, *a.shift))
            after = measure(moved, mask, true_depth, target, crop, scale, sensor)
            row += f' {before.get("iou", 0.0):.2f} | {after.get("iou", 0.0):.2f} |'
        print(row)
        sys.stdout.flush()
    return 0


if __name__ == '__main__':
    sys.exit(main())
