"""Segmentation figures of real captures, whole frame and cropped (docs/perception.md, "Real captures").

    python scripts/segmentation_report.py DATA [--only NAME ...]

``DATA`` holds ``cleargrasp-d435/`` (ClearGrasp D435 captures) and ``gqcnn-primesense/`` (GQ-CNN PrimeSense
captures) in their published layouts. For every capture and both views (the whole frame, and the crop of the
capture's table), the target is segmented at its target pixel (``target:=pixel``, one frame, the capture's
sensor model) and compared with the ground truth of its mask component: the fraction of that component's
pixels the target covers, the occupancy IoU with the true footprint at the grid's cell centres, the objects
seen, the smallest other object (table-plane area and height) and the refusal reason, if any.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from gpis_grasp_ros.core.noise_model import SensorModel
from gpis_grasp_ros.core.sensing import SensingParams, segment_frames
from gpis_grasp_ros.data import rgbd_import as ri
from gpis_grasp_ros.data.ground_truth import ground_truth_from_mask
from gpis_grasp_ros.tools.evaluation.truth import TrueShape

# name, kind, id, target pixel (full image), crop (u0, v0, u1, v1), scale
CAPTURES = [
    ('clear 080', 'cleargrasp', '000000080', (882, 522), (440, 200, 1280, 720), 0.5),
    ('clear 123', 'cleargrasp', '000000123', (602, 396), (200, 150, 1000, 650), 0.5),
    ('single 0', 'gqcnn', 'single_0', (337, 282), (212, 72, 502, 409), 1.0),
    ('single 1', 'gqcnn', 'single_1', (315, 223), (171, 91, 469, 361), 1.0),
    ('single 2', 'gqcnn', 'single_2', (329, 216), (205, 61, 455, 365), 1.0),
    ('single 3', 'gqcnn', 'single_3', (363, 216), (203, 95, 486, 372), 1.0),
    ('single 4', 'gqcnn', 'single_4', (323, 210), (208, 75, 471, 328), 1.0),
    ('clutter 0', 'gqcnn', 'clutter_0', (406, 259), (237, 88, 561, 436), 1.0),
    ('clutter 1', 'gqcnn', 'clutter_1', (319, 237), (149, 43, 560, 405), 1.0),
]


def load(data: Path, kind: str, ident: str) -> tuple[ri.Capture, np.ndarray, np.ndarray, str]:
    """The capture, its object mask, the true depth and the sensor model's name."""
    if kind == 'cleargrasp':
        d = data / 'cleargrasp-d435'
        cap = ri.load_capture(d / f'{ident}-transparent-rgb-img.jpg', d / f'{ident}-transparent-depth-mm.png',
                              d / 'camera_intrinsics.yaml')
        mask = ri.load_rgb(d / f'{ident}-mask.png')[..., 0] > 127
        true_depth = ri.load_depth(d / f'{ident}-opaque-depth-mm.png')
        return cap, mask, true_depth, 'realsense_d400'
    d = data / 'gqcnn-primesense'
    i = ident.split('_')[1]
    stem = ident.split('_')[0]
    cap = ri.load_capture(d / f'{stem}_color_{i}.png', d / f'{stem}_depth_{i}.npy', d / 'primesense.intr')
    mask = ri.load_rgb(d / f'{stem}_segmask_{i}.png')[..., 0] > 127
    return cap, mask, cap.depth.copy(), 'carmine'


def _areas(result, labels: np.ndarray) -> np.ndarray:
    """Table-plane area (m^2) of every label's pixels: each pixel's footprint on the plane."""
    intr, table = result.intrinsics, result.table
    rays = intr.rays()
    z = np.where(np.isfinite(result.mean_depth), result.mean_depth, -table.offset_m / np.maximum(
        np.abs(rays @ table.n), 1e-6))
    per_px = (z / intr.fx) * (z / intr.fy) / np.maximum(np.abs(rays @ table.n) / np.linalg.norm(rays, axis=-1), 0.05)
    return np.bincount(labels.ravel(), weights=per_px.ravel(), minlength=int(labels.max()) + 1)


def measure(cap: ri.Capture, mask: np.ndarray, true_depth: np.ndarray, target: tuple[float, float],
            crop: tuple[int, int, int, int] | None, scale: float, sensor: str) -> dict:
    small, extra = ri.crop_and_scale(cap, crop, scale, {'mask': mask.astype(np.uint8)})
    full, extra_full = ri.crop_and_scale(cap, crop, 1.0, {'mask': mask.astype(np.uint8), 'true': true_depth})
    tp = ri.map_pixel(*target, crop, scale)
    model = SensorModel.named(sensor)
    table = ri.capture_table(small, model)
    truth = ground_truth_from_mask(full, extra_full['mask'] > 0, extra_full['true'], ri.map_pixel(*target, crop, 1.0),
                                   table)
    _, comp_lab = cv2.connectedComponents(extra['mask'].astype(np.uint8), connectivity=8)
    u, v = (int(round(c)) for c in tp)
    comp = comp_lab == comp_lab[v, u] if comp_lab[v, u] > 0 else np.zeros_like(comp_lab, bool)
    params = SensingParams(sensor=model, target='pixel', target_point=tuple(tp))
    t0 = time.perf_counter()
    out = {'size': f'{small.intrinsics.width}x{small.intrinsics.height}'}
    try:
        res = segment_frames(small.rgb, small.depth, small.intrinsics, params)
    except ValueError as exc:
        out.update(error=str(exc), time=time.perf_counter() - t0)
        return out
    out['time'] = time.perf_counter() - t0
    g = res.geometry
    shape = TrueShape(truth.sdf, truth.geometry, g)
    true_occ = shape.values_at(g.cell_centers()) < 0
    occ = res.occupancy >= 0.5
    out['iou'] = float((occ & true_occ).sum() / max((occ | true_occ).sum(), 1))
    out['coverage'] = float((res.object_mask & comp).sum() / max(comp.sum(), 1))
    out['target_px'] = int(res.object_mask.sum())
    out['objects'] = int(res.objects_seen)
    labels = np.where(res.object_mask, 0, res.labels_px)
    kept = getattr(res, 'object_labels', None)
    areas = _areas(res, labels)
    ids = np.arange(areas.size)
    if kept is None:  # the objects the segmentation counts (its speck rule: 30 px and 1 cm^2)
        px = np.bincount(labels.ravel(), minlength=areas.size)
        ids = ids[(ids > 0) & (px >= params.min_object_area_px) & (areas >= params.min_object_area_m2)]
    else:
        ids = np.asarray([k for k in kept if 0 < k < areas.size], dtype=np.int64)
    ids = ids[np.isin(ids, np.unique(labels))]
    if ids.size:
        k = ids[np.argmin(areas[ids])]
        h = res.height[(labels == k) & np.isfinite(res.height)]
        out['smallest'] = (float(areas[k]) * 1e4, float(np.percentile(h, 95)) * 1e3 if h.size else float('nan'),
                           int((labels == k).sum()))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('data', type=Path)
    p.add_argument('--only', nargs='*', default=None, help='capture names (e.g. "single 0")')
    args = p.parse_args(argv)
    ious: dict[str, list[float]] = {'whole': [], 'crop': []}
    print('| capture | view | image | coverage | occupancy IoU | objects | smallest other (cm², mm, px) | '
          'refused | s |')
    print('|---|---|---|---|---|---|---|---|---|')
    for name, kind, ident, target, crop, scale in CAPTURES:
        if args.only and name not in args.only:
            continue
        cap, mask, true_depth, sensor = load(args.data, kind, ident)
        for view, c in (('whole', None), ('crop', crop)):
            r = measure(cap, mask, true_depth, target, c, scale, sensor)
            ious[view].append(r.get('iou', 0.0))
            sm = r.get('smallest')
            sm_s = '-' if sm is None else f'{sm[0]:.2f}, {sm[1]:.0f}, {sm[2]}'
            if 'error' in r:
                print(f'| {name} | {view} | {r["size"]} | - | - | - | - | {r["error"]} | {r["time"]:.1f} |')
            else:
                print(f'| {name} | {view} | {r["size"]} | {r["coverage"]:.2f} | {r["iou"]:.2f} | {r["objects"]} | '
                      f'{sm_s} | | {r["time"]:.1f} |')
            sys.stdout.flush()
    print(f'mean occupancy IoU (refused = 0): whole {np.mean(ious["whole"]):.3f}, crop {np.mean(ious["crop"]):.3f}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
