"""``gpis-grasp make-bag``: simulate an RGB-D camera looking at one object on a table and write an MCAP bag.

Examples::

    gpis-grasp make-bag --polygon bags/objects/H_marker.csv --height 0.019 \\
        --region specular:-0.013,-0.011,0.013,0.011 --out /tmp/marker.mcap
    gpis-grasp make-bag --mask part.png --mpp 0.0005 --region-polygon transparent:lid.csv --out part.mcap
    gpis-grasp make-bag --polygon bags/objects/H_marker.csv --height 0.019 --camera-height 0.9 --tilt 50 \\
        --light 200,55 --distractor box:0.11,0,0.03,0.03,0.03/52,128,74 --sensor realsense_d400 --out head.mcap

Coordinates are metres in the table plane (table frame: for the default top-down camera the camera's
x (right) and y (down)); the camera looks at the table point (0, 0) from ``--camera-height`` metres
along its optical axis, tilted ``--tilt`` degrees from straight down (leaning back towards +y) and
turned ``--azimuth`` degrees about the table normal. Exit status 2 on bad input (nothing is written).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from gpis_grasp_ros.sim.scene import (
    MATERIAL_KINDS,
    SENSORS,
    Distractor,
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
    p.add_argument('--camera-height', type=float, default=0.7,
                   help='camera distance from the table point (0, 0) along the optical axis; the height for a '
                        'top-down camera (m, default 0.7)')
    p.add_argument('--tilt', type=float, default=0.0, help='camera tilt from straight down (degrees, default 0)')
    p.add_argument('--azimuth', type=float, default=0.0,
                   help='camera rig turned about the table normal (degrees, default 0)')
    p.add_argument('--light', default=None, metavar='AZIMUTH,ELEVATION',
                   help='direction towards the light in the table frame (degrees); casts shadows (default: none)')
    p.add_argument('--shadow-strength', type=float, default=0.5,
                   help='fraction of the light a shadow removes from the table colour (default 0.5)')
    p.add_argument('--distractor', action='append', default=[], metavar='box:x,y,l,w,h[,yaw] | can:x,y,r,h',
                   help="another (opaque) object on the table, m / degrees; optional colour suffix '/R,G,B'; "
                        'repeatable')
    p.add_argument('--sensor', default='carmine', choices=SENSORS,
                   help='depth sensor model and default intrinsics (default carmine)')
    p.add_argument('--frames', type=int, default=10, help='number of RGB-D frames at 30 Hz (default 10)')
    p.add_argument('--seed', type=int, default=0, help='random seed (default 0)')
    p.add_argument('--name', default=None, help='object name stored in the bag metadata (default: file stem)')
    p.add_argument('--out', required=True, metavar='BAG', help='output: BAG.mcap file, or a rosbag2 directory')
    p.add_argument('--overwrite', action='store_true', help='replace an existing output')
    return p


def _distractor(text: str) -> Distractor:
    kind, sep, rest = text.partition(':')
    kind = kind.strip().lower()
    values, _, color_text = rest.partition('/')
    color = _color(color_text, f"--distractor '{text}' colour") if color_text else (52, 128, 74)
    if kind == 'box':
        parts = [v for v in values.split(',') if v.strip()]
        x, y, length, width, height, *yaw = _floats(values, 6 if len(parts) == 6 else 5, f"--distractor '{text}'")
        if min(length, width, height) <= 0:
            raise ValueError(f"--distractor '{text}': length, width and height must be positive")
        return Distractor.box(x, y, length, width, height, yaw[0] if yaw else 0.0, color=color)
    if kind == 'can':
        x, y, radius, height = _floats(values, 4, f"--distractor '{text}'")
        if min(radius, height) <= 0:
            raise ValueError(f"--distractor '{text}': radius and height must be positive")
        return Distractor.cylinder(x, y, radius, height, color=color)
    raise ValueError(f"--distractor '{text}': expected box:x,y,l,w,h[,yaw] or can:x,y,r,h (m)")


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
                     frames=args.frames, seed=args.seed, name=args.name or source.stem, camera_tilt=args.tilt,
                     camera_azimuth=args.azimuth,
                     light=None if args.light is None else tuple(_floats(args.light, 2, '--light')),
                     shadow_strength=args.shadow_strength, distractors=[_distractor(t) for t in args.distractor],
                     sensor=args.sensor)


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
