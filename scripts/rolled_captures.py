"""The raw captures of an ``evaluate-real`` manifest with the camera rolled or mirrored: the same scene, other pixels.

    python scripts/rolled_captures.py MANIFEST --root DATA --out DIR [--only TEXT]
    gpis-grasp evaluate-real DIR/rot180.yaml --seeds 5 --oracle --workers 2 --out DIR/out_rot180   # and mirror, rot90

Writes, for every raw capture of MANIFEST (bags are skipped), three copies under DIR/<kind>/ and a manifest
DIR/<kind>.yaml: ``rot180`` (the camera rolled half a turn about its optical axis: the same world), ``rot90`` (rolled
a quarter turn clockwise, a portrait mount) and ``mirror`` (the image flipped left to right: the mirrored world, as
valid a scene). Colour, depth, the ground-truth mask and depth move together; the intrinsics, the target pixel and
the crop follow (crops stay (u0, v0, u1, v1) with exclusive ends). Colour is written as PNG (a JPEG would be
compressed again). The sensor's shadow model is not moved: its projector or second imager stays at +x of the new
image, where the capture's own shadows are not. A perception and planner that do not depend on the pixel grid give
the same table on every copy; the differences measure how much they do. The copies are derived data: keep them out
of the repository when the captures' licence says so.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import yaml

from gpis_grasp_ros.data.rgbd_import import load_intrinsics

KINDS = ('rot180', 'mirror', 'rot90')


def transform_image(a: np.ndarray, kind: str) -> np.ndarray:
    """An (H, W, ...) image of the rolled or mirrored camera."""
    if kind == 'rot180':
        return np.ascontiguousarray(a[::-1, ::-1])
    if kind == 'mirror':
        return np.ascontiguousarray(a[:, ::-1])
    return np.ascontiguousarray(np.rot90(a, k=-1))  # clockwise: (u', v') = (H - 1 - v, u)


def transform_pixel(u: float, v: float, w: int, h: int, kind: str) -> tuple[float, float]:
    """A pixel (u, v) of a W x H image in the transformed image."""
    if kind == 'rot180':
        return w - 1 - u, h - 1 - v
    if kind == 'mirror':
        return w - 1 - u, v
    return h - 1 - v, u


def transform_box(box: list[int], w: int, h: int, kind: str) -> list[int]:
    """A crop (u0, v0, u1, v1), exclusive ends, in the transformed image."""
    u0, v0, u1, v1 = box
    if kind == 'rot180':
        return [w - u1, h - v1, w - u0, h - v0]
    if kind == 'mirror':
        return [w - u1, v0, w - u0, v1]
    return [h - v1, u0, h - v0, u1]


def transform_intrinsics(fx: float, fy: float, cx: float, cy: float, w: int, h: int, kind: str) -> dict:
    """Pinhole intrinsics of the transformed image (the principal point moves with the pixels)."""
    if kind == 'rot90':
        return dict(fx=fy, fy=fx, cx=h - 1 - cy, cy=cx, width=h, height=w)
    pcx, pcy = transform_pixel(cx, cy, w, h, kind)
    return dict(fx=fx, fy=fy, cx=pcx, cy=pcy, width=w, height=h)


def _read(path: Path) -> np.ndarray:
    if path.suffix == '.npy':
        return np.load(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f'cannot read {path}')
    return img


def _write(path: Path, a: np.ndarray) -> Path:
    if path.suffix == '.npy':
        np.save(path, a)
        return path
    path = path.with_suffix('.png')
    if not cv2.imwrite(str(path), a):
        raise ValueError(f'cannot write {path}')
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('manifest')
    ap.add_argument('--root', required=True, help='directory the manifest paths are relative to')
    ap.add_argument('--out', required=True, help='directory for the copies and their manifests')
    ap.add_argument('--only', default='', help='captures whose name contains this text')
    args = ap.parse_args(argv)
    root, out = Path(args.root), Path(args.out)
    captures = [c for c in yaml.safe_load(Path(args.manifest).read_text())['captures']
                if 'bag' not in c and args.only in c.get('name', c['rgb'])]
    for kind in KINDS:
        entries = []
        for cap in captures:
            name = cap.get('name', Path(cap['rgb']).stem)
            d = out / kind / name
            d.mkdir(parents=True, exist_ok=True)
            entry = {k: v for k, v in cap.items() if k not in ('rgb', 'depth', 'gt_mask', 'gt_depth', 'intrinsics')}
            entry['name'] = name
            size = None
            for key in ('rgb', 'depth', 'gt_mask', 'gt_depth'):
                a = _read(root / cap[key])
                size = size or (a.shape[1], a.shape[0])
                entry[key] = str(_write(d / Path(cap[key]).name, transform_image(a, kind)).relative_to(out / kind))
            w, h = size
            intr = cap['intrinsics']
            i = load_intrinsics(intr if isinstance(intr, dict) else root / intr, width=w, height=h)
            entry['intrinsics'] = transform_intrinsics(i.fx, i.fy, i.cx, i.cy, w, h, kind)
            entry['target_pixel'] = [float(x) for x in transform_pixel(*cap['target_pixel'], w, h, kind)]
            if cap.get('crop') is not None:
                entry['crop'] = transform_box(list(cap['crop']), w, h, kind)
            entries.append(entry)
        (out / f'{kind}.yaml').write_text(yaml.safe_dump({'root': str((out / kind).resolve()), 'captures': entries},
                                                         sort_keys=False))
        print(f'{out / kind}.yaml: {len(entries)} captures')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
