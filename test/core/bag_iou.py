"""Mean-shape and occupancy IoU of the shipped bags, top-down (``bags/``) vs head camera (``bags/head/``).

Segmentation as the nodes run it (``SensingParams()``, the benchmark's fallback without the
too-wide check when the target is refused), GPIS as :func:`~gpis_grasp_ros.data.bags.posterior_from_scene`;
the truth is sampled at the planning grid's cell centres through the camera frame (as the
benchmark's ``TrueShape.iou_on``). ``python test/core/bag_iou.py`` prints the table (about 1 min).
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from gpis_grasp_ros.core.contacts import bilinear
from gpis_grasp_ros.core.pipeline import posterior_from_grids, publishable_grids
from gpis_grasp_ros.core.sensing import SensingParams, SensingResult, segment_frames
from gpis_grasp_ros.data.bags import BagScene, load_bag

BAG_DIR = Path(__file__).resolve().parents[2] / 'bags'


def segment(scene: BagScene, params: SensingParams = SensingParams()) -> SensingResult:
    """Segmentation with the node defaults; a refused too-wide target is segmented without that check."""
    try:
        return segment_frames(scene.rgb_frames, scene.depth_frames, scene.intrinsics, params, scene.frame_id)
    except ValueError:
        return segment_frames(scene.rgb_frames, scene.depth_frames, scene.intrinsics,
                              dataclasses.replace(params, max_opening_m=0.0), scene.frame_id)


def bag_iou(path: Path) -> tuple[float, float, float, float]:
    """(mean-shape IoU, occupancy IoU, measured object height m, segmentation time s) of one bag."""
    scene = load_bag(path)
    t0 = time.perf_counter()
    result = segment(scene)
    seconds = time.perf_counter() - t0
    occ, noise, geometry = publishable_grids(result)
    posterior = posterior_from_grids(occ, noise, geometry)
    tg = scene.true_geometry
    truth = bilinear(scene.true_sdf.astype(np.float64), tg,
                     tg.from_sensor(geometry.to_sensor(geometry.cell_centers()))[0]) < 0

    def iou(a: np.ndarray) -> float:
        return float((a & truth).sum() / max((a | truth).sum(), 1))

    height = float(getattr(result, 'object_height', float('nan')))
    return iou(posterior.mean < 0), iou(result.occupancy >= 0.5), height, seconds


def main() -> None:
    names = sorted(p.name for p in BAG_DIR.glob('*.mcap'))
    print('| object | top-down mean-shape IoU | head | head - top-down | occupancy IoU top-down / head '
          '| object height top-down / head (mm) | segmentation s top-down / head |')
    print('|---|---|---|---|---|---|---|')
    rows = []
    for name in names:
        top, head = bag_iou(BAG_DIR / name), bag_iou(BAG_DIR / 'head' / name)
        rows.append((top, head))
        print(f'| {name[0]} | {top[0]:.2f} | {head[0]:.2f} | {head[0] - top[0]:+.2f} | {top[1]:.2f} / {head[1]:.2f} '
              f'| {top[2] * 1000:.1f} / {head[2] * 1000:.1f} | {top[3]:.3f} / {head[3]:.3f} |')
        sys.stdout.flush()
    t, h = np.array([r[0] for r in rows]), np.array([r[1] for r in rows])
    print(f'| mean | {t[:, 0].mean():.2f} | {h[:, 0].mean():.2f} | {h[:, 0].mean() - t[:, 0].mean():+.2f} '
          f'| {t[:, 1].mean():.2f} / {h[:, 1].mean():.2f} | | {t[:, 3].mean():.3f} / {h[:, 3].mean():.3f} |')
    print(f'head within 0.05 of top-down: {int(np.sum(h[:, 0] >= t[:, 0] - 0.05))} / {len(rows)}')


if __name__ == '__main__':
    main()
