"""``gpis-grasp make-bag``: simulate a Carmine looking down at one object and write an MCAP bag.

Examples::

    gpis-grasp make-bag --polygon bags/objects/H_marker.csv --height 0.019 \\
        --region specular:-0.013,-0.011,0.013,0.011 --out /tmp/marker.mcap
    gpis-grasp make-bag --mask part.png --mpp 0.0005 --region-polygon transparent:lid.csv --out part.mcap

Coordinates are metres on the table plane, which are the camera's x (right) and y (down);
the optical axis meets the table at (0, 0). Exit status 2 on bad input (nothing is written).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from gpis_grasp_ros.sim.scene import (
    MATERIAL_KINDS,
    MaterialRegion,
    SceneSpec,
    load_mask_png,
    load_polygon_csv,
    write_scene_bag,
)


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors go through the same path as input errors (exit 2)."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise _UsageError(message)


class _UsageError(Exception):
    pass


def _floats(text: str, n: int, what: str) -> list[float]:
    parts = [p for p in text.split(',') if p.strip()]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ValueError(f"{what}: expected {n} comma-separated numbers, got '{text}'") from None
    if len(values) != n or not all(np.isfinite(values)):
        raise ValueError(f"{what}: expected {n} comma-separated finite numbers, got '{text}'")
    return values


def _color(text: str, what: str) -> tuple[int, int, int]:
    values = _floats(text, 3, what)
    if any(v != int(v) or v < 0 or v > 255 for v in values):
        raise ValueError(f"{what}: expected R,G,B integers in 0..255, got '{text}'")
    return int(values[0]), int(values[1]), int(values[2])


def _split_kind(text: str, option: str) -> tuple[str, str]:
    kind, sep, rest = text.partition(':')
    kind = kind.strip().lower()
    if not sep or not rest:
        raise ValueError(f"{option} '{text}': expected KIND:..., KIND one of {', '.join(MATERIAL_KINDS)}")
    if kind not in MATERIAL_KINDS:
        raise ValueError(f"{option} '{text}': unknown material '{kind}'; expected one of {', '.join(MATERIAL_KINDS)}")
    return kind, rest


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog='gpis-grasp make-bag', description=__doc__.split('\n\n')[0],
                epilog=f"materials: {', '.join(MATERIAL_KINDS)}; later regions override earlier ones",
                formatter_class=argparse.RawDescriptionHelpFormatter)
    shape = p.add_mutually_exclusive_group(required=True)
    shape.add_argument('--polygon', metavar='FILE.csv', help="object outline, one 'x,y' vertex per line (m)")
    shape.add_argument('--mask', metavar='FILE.png', help='object mask image (white = object), needs --mpp')
    p.add_argument('--mpp', type=float, help='mask scale: metres per mask pixel (mask centred on the optical axis)')
    p.add_argument('--region', action='append', default=[], metavar='KIND:x0,y0,x1,y1',
                   help='material box (m); repeatable')
    p.add_argument('--region-polygon', action='append', default=[], metavar='KIND:FILE.csv',
                   help='material polygon from a CSV file (m); repeatable')
    p.add_argument('--height', type=float, default=0.02, help='object height above the table (m, default 0.02)')
    p.add_argument('--table-color', default='186,176,160', metavar='R,G,B', help='table colour (default %(default)s)')
    p.add_argument('--object-color', default='70,90,150', metavar='R,G,B', help='object colour (default %(default)s)')
    p.add_argument('--camera-height', type=float, default=0.7, help='camera above the table (m, default 0.7)')
    p.add_argument('--frames', type=int, default=10, help='number of RGB-D frames at 30 Hz (default 10)')
    p.add_argument('--seed', type=int, default=0, help='random seed (default 0)')
    p.add_argument('--name', default=None, help='object name stored in the bag metadata (default: file stem)')
    p.add_argument('--out', required=True, metavar='BAG', help='output: BAG.mcap file, or a rosbag2 directory')
    p.add_argument('--overwrite', action='store_true', help='replace an existing output')
    return p


def spec_from_args(args: argparse.Namespace) -> SceneSpec:
    """Turn parsed arguments into a :class:`SceneSpec` (ValueError on bad input)."""
    if args.mask is not None:
        if args.mpp is None:
            raise ValueError('--mask needs --mpp (metres per mask pixel)')
        outline = load_mask_png(args.mask, args.mpp)
        source = Path(args.mask)
    else:
        if args.mpp is not None:
            raise ValueError('--mpp only applies to --mask')
        outline = load_polygon_csv(args.polygon)
        source = Path(args.polygon)
    regions: list[MaterialRegion] = []
    for text in args.region:
        kind, rest = _split_kind(text, '--region')
        x0, y0, x1, y1 = _floats(rest, 4, f"--region '{text}'")
        if x0 == x1 or y0 == y1:
            raise ValueError(f"--region '{text}': the box has zero area")
        regions.append(MaterialRegion.box(kind, x0, y0, x1, y1))
    for text in args.region_polygon:
        kind, rest = _split_kind(text, '--region-polygon')
        regions.append(MaterialRegion(kind, load_polygon_csv(rest)))
    return SceneSpec(outline=outline, regions=regions, height=args.height,
                     table_color=_color(args.table_color, '--table-color'),
                     object_color=_color(args.object_color, '--object-color'), camera_height=args.camera_height,
                     frames=args.frames, seed=args.seed, name=args.name or source.stem)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gpis-grasp make-bag``; returns 0, or 2 on bad input, 1 on I/O errors."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        out = Path(args.out)
        if out.exists() and not args.overwrite:
            raise ValueError(f'{out} exists already (use --overwrite to replace it)')
        spec = spec_from_args(args)
        path = write_scene_bag(spec, out, overwrite=args.overwrite)
    except SystemExit as done:  # --help
        return int(done.code or 0)
    except _UsageError as err:
        parser.print_usage(sys.stderr)
        print(f'gpis-grasp make-bag: error: {err}', file=sys.stderr)
        return 2
    except ValueError as err:
        print(f'gpis-grasp make-bag: error: {err}', file=sys.stderr)
        return 2
    except OSError as err:
        print(f'gpis-grasp make-bag: error: {err}', file=sys.stderr)
        return 1
    print(f'wrote {path} ({path.stat().st_size / 1e6:.2f} MB)' if path.is_file() else f'wrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
