"""Target pixels a user might click: segmentation at random pixels on each object, whole frame and cropped.

    python scripts/target_pixel_sweep.py MANIFEST --root DATA [--clicks 8] [--only NAME] [--rows FILE]
    python scripts/target_pixel_sweep.py MANIFEST --root DATA --from-rows FILE

For every unit of an ``evaluate-real`` manifest (e.g. ``manifests/realdata_dev.yaml``), ``--clicks`` pixels are drawn
(seeded by the capture's name) inside the target's ground-truth mask component, eroded by 3 px and kept 5 px inside
the crop, and the unit is segmented and fitted at each as its target pixel, as ``evaluate-real`` does. Printed per
unit: clicks refused (with the reasons), occupancy IoU and mean-shape IoU (min / mean over the accepted ones) and
the objects seen. A target pixel anywhere on the object should give the same object.
"""

from __future__ import annotations

import argparse
import json
import re
import zlib
from collections import Counter

import cv2
import numpy as np

from gpis_grasp_ros.tools.evaluate_real.manifest import load_manifest
from gpis_grasp_ros.tools.evaluate_real.tasks import _prepared


def clicks(unit, n: int) -> list[tuple[float, float]]:
    """``n`` pixels inside the unit's target mask component (eroded 3 px, 5 px inside its crop)."""
    mask = cv2.imread(unit.gt_mask, cv2.IMREAD_UNCHANGED)
    if mask.ndim == 3:
        mask = mask[..., 0]
    u0, v0 = int(unit.target_pixel[0]), int(unit.target_pixel[1])
    comp = (mask == mask[v0, u0]) if mask[v0, u0] > 0 else (mask > 0)
    _, labels = cv2.connectedComponents(comp.astype(np.uint8), connectivity=8)
    inner = cv2.erode((labels == labels[v0, u0]).astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    if unit.crop is not None:
        c, box = unit.crop, np.zeros_like(inner)
        box[c[1] + 5:c[3] - 5, c[0] + 5:c[2] - 5] = True
        inner &= box
    vs, us = np.nonzero(inner)
    rng = np.random.default_rng(zlib.crc32(unit.capture.encode()))
    pick = rng.choice(len(vs), size=min(n, len(vs)), replace=False)
    return [(float(us[k]), float(vs[k])) for k in pick]


def click_row(unit, px: tuple[float, float]) -> dict:
    """The unit segmented and fitted with ``px`` as its target pixel."""
    entry = unit.entry()
    entry['target_pixel'] = list(px)
    fit, why, _ = _prepared(json.dumps(entry, sort_keys=True), 0)
    return dict(unit=unit.id, px=list(px), refused=why,
                occ=None if fit is None else round(float(fit.occupancy_iou), 3),
                ms=None if fit is None else round(float(fit.mean_shape_iou), 3),
                seen=None if fit is None else int(fit.fit.sensing.objects_seen))


def table_row(unit_id: str, rows: list[dict]) -> str:
    """One unit's line: refusals grouped by reason (numbers and parentheses dropped), IoU spans, objects seen."""
    ok = [r for r in rows if not r['refused']]
    reasons = Counter(' '.join(re.sub(r'\d+', 'N', re.sub(r'\([^)]*\)', '', r['refused'].split(': ', 1)[-1]))
                               .split())[:48] for r in rows if r['refused'])
    refused = f'{len(rows) - len(ok)}' + (f" ({'; '.join(f'{k}... x{v}' for k, v in reasons.items())})"
                                         if reasons else '')

    def span(key):
        vals = [r[key] for r in ok]
        return f'{min(vals):.2f} / {np.mean(vals):.2f}' if vals else '-'
    seen = sorted({r['seen'] for r in ok})
    seen_txt = '-' if not seen else str(seen[0]) if len(seen) == 1 else f'{seen[0]}-{seen[-1]}'
    return f"| {unit_id} | {len(rows)} | {refused} | {span('occ')} | {span('ms')} | {seen_txt} |"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('manifest')
    ap.add_argument('--root', required=True, help='directory the manifest paths are relative to')
    ap.add_argument('--clicks', type=int, default=8, help='target pixels per unit (default 8)')
    ap.add_argument('--only', default='', help='units whose id contains this text')
    ap.add_argument('--rows', help='also write one JSON row per click to this file')
    ap.add_argument('--from-rows', help='print the table of rows written by --rows instead of segmenting')
    args = ap.parse_args(argv)
    units = [u for u in load_manifest(args.manifest, args.root) if args.only in u.id]
    print('| unit | clicks | refused | occupancy IoU min / mean | mean-shape IoU min / mean | objects seen |')
    print('|---|---:|---|---|---|---|')
    rows = []
    for unit in units:
        if args.from_rows:
            mine = [r for r in map(json.loads, open(args.from_rows)) if r['unit'] == unit.id]
        else:
            mine = [click_row(unit, px) for px in clicks(unit, args.clicks)]
        rows += mine
        print(table_row(unit.id, mine), flush=True)
    ok = [r for r in rows if not r['refused']]
    print(f'{len(rows)} clicks, {len(rows) - len(ok)} refused; accepted: occupancy IoU mean '
          f"{np.mean([r['occ'] for r in ok]) if ok else float('nan'):.3f}, mean-shape IoU "
          f"{np.mean([r['ms'] for r in ok]) if ok else float('nan'):.3f}")
    if args.rows:
        with open(args.rows, 'w') as f:
            f.writelines(json.dumps(r) + '\n' for r in rows)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
