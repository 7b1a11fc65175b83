"""The paper's eight test objects (Mahler et al. 2015, Fig. 1 and section VII-A) as simulated scenes.

Each object is a planar outline built from simple primitives (sizes in centimetres in the code,
metres everywhere else) plus material regions that reproduce what the Carmine could not sense:

====  ==================  ==========================================================================
A     tape dispenser      opaque tape roll in a transparent dispenser (table seen through it)
B     nail                thin steel nail; specular tip (no depth)
C     signal splitter     black (dark) body; specular F-connectors (no depth)
D     metal toy plane     painted fuselage; specular wings and tailplane
E     mechanical switch   limit switch: plastic body; specular lever, roller and terminals
F     crystal knob        transparent faceted crystal; specular metal base seen through it
G     squirt bottle       large transparent body with a specular highlight band; opaque cap
H     marker              white barrel; specular label band mid-body; dark cap
====  ==================  ==========================================================================

``gpis-grasp make-bags [--out DIR] [--only A,B]`` regenerates the bags (deterministic: the same
code and seeds give byte-identical files) and writes each outline to ``DIR/objects/<name>.csv``.

**Head-camera set** (``gpis-grasp make-bags --head``, written to ``DIR/head/``): the same eight
objects seen the way the paper's PR2 sees them, by a Carmine on the robot's head about 0.9 m from
the object and tilted 45-55 degrees from straight down (:data:`HEAD_VIEWS`), with a light casting
the object's shadow on the table and one or two smaller distractor objects (boxes, cans) on the
table beside it (each distractor's table-plane area is at most half the target's, so the
segmentation's default ``target: largest`` picks the paper object). Ground truth is the target's,
in the table frame (:class:`~gpis_grasp_ros.sim.scene.GroundTruth`).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.sim.scene import (
    Distractor,
    MaterialRegion,
    SceneSpec,
    mask_to_polygon,
    rasterise_polygon,
    save_polygon_csv,
    write_scene_bag,
)

CM = 0.01
TABLE_COLOR = (146, 136, 120)  # medium wood laminate


def _default_bag_dir() -> Path:
    """``bags/`` of the source checkout (also with a symlink install), else ``./bags``."""
    repo = Path(__file__).resolve().parents[2]
    return repo / 'bags' if (repo / 'package.xml').is_file() else Path.cwd() / 'bags'


DEFAULT_BAG_DIR = _default_bag_dir()
UNION_RESOLUTION = 1e-4  # m, raster used to merge primitives into one outline


# --------------------------------------------------------------------------- primitives (cm)
def rect(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    """Axis-aligned rectangle (cm)."""
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)


def circle(cx: float, cy: float, r: float, n: int = 96) -> np.ndarray:
    """Regular n-gon approximating a circle (cm)."""
    a = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    return np.stack([cx + r * np.cos(a), cy + r * np.sin(a)], axis=1)


def rotate(poly: np.ndarray, degrees: float, about: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Rotate a polygon by ``degrees`` (from +x toward +y) about a point."""
    t = math.radians(degrees)
    r = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    c = np.asarray(about, dtype=np.float64)
    return (np.asarray(poly, dtype=np.float64) - c) @ r.T + c


def mirror_y(poly: np.ndarray) -> np.ndarray:
    """Mirror a polygon about the x axis (y -> -y)."""
    return np.asarray(poly, dtype=np.float64) * np.array([1.0, -1.0])


def union_outline(parts: Sequence[np.ndarray], resolution: float = UNION_RESOLUTION) -> np.ndarray:
    """Outline (m) of the union of primitive polygons (m), via a fine raster (``resolution`` m).

    The result is accurate to about one raster cell (0.1 mm by default).
    """
    pts = np.concatenate(parts)
    lo = np.floor(pts.min(axis=0) / resolution) * resolution - 4 * resolution
    hi = np.ceil(pts.max(axis=0) / resolution) * resolution + 4 * resolution
    w, h = (int(round(v)) for v in (hi - lo) / resolution)
    geom = GridGeometry(float(lo[0]), float(lo[1]), resolution, w, h)
    mask = np.zeros(geom.shape, dtype=bool)
    for part in parts:
        mask |= rasterise_polygon(np.asarray(part, dtype=np.float64), geom)
    center = (geom.origin_x + w * resolution / 2.0, geom.origin_y + h * resolution / 2.0)
    return mask_to_polygon(mask, resolution, center=center, tolerance_px=1.0)


# --------------------------------------------------------------------------- object table
@dataclass(frozen=True)
class ObjectDef:
    """One test object: letter, file name, description and a builder of its scene."""

    letter: str
    name: str
    description: str
    size_cm: str
    materials: str
    build: Callable[[], SceneSpec]

    @property
    def filename(self) -> str:
        return f'{self.letter}_{self.name}.mcap'


def _spec(name: str, seed: int, parts_cm: Sequence[np.ndarray], regions_cm: Sequence[tuple], *, height_cm: float,
          color: tuple[int, int, int], offset_cm: tuple[float, float] = (0.0, 0.0), rotation_deg: float = 0.0,
          camera_height: float = 0.7) -> SceneSpec:
    """Scene of an object made of primitives (cm), rotated then shifted, with material regions
    ``(kind, polygon_cm[, color])`` in the same object coordinates."""

    def place(poly_cm: np.ndarray) -> np.ndarray:
        return (rotate(poly_cm, rotation_deg) + np.asarray(offset_cm)) * CM

    outline = union_outline([place(p) for p in parts_cm])
    regions = [MaterialRegion(r[0], place(r[1]), r[2] if len(r) > 2 else None) for r in regions_cm]
    return SceneSpec(outline=outline, regions=regions, height=height_cm * CM, table_color=TABLE_COLOR,
                     object_color=color, camera_height=camera_height, frames=10, seed=seed, name=name)


def tape_dispenser() -> SceneSpec:
    """A: Scotch-tape roll (opaque, 6.4 cm) in a clear plastic dispenser with a cutter arm."""
    roll_c = (-2.0, 0.0)
    shell = circle(*roll_c, 3.7)
    arm = np.array([[-2.0, 1.0], [5.2, 1.0], [6.0, 2.3], [5.6, 3.7], [-2.0, 3.7]])
    regions = [('transparent', rect(-6.0, -4.0, 6.5, 4.0), (205, 215, 225)),
               ('opaque', circle(*roll_c, 3.2)),
               ('transparent', circle(*roll_c, 1.3), (205, 215, 225))]  # clear hub inside the roll's core
    return _spec('tape_dispenser', 2015_01, [shell, arm], regions, height_cm=2.5, color=(226, 221, 200),
                 offset_cm=(0.4, 0.3), rotation_deg=-8.0)


def nail() -> SceneSpec:
    """B: 10.2 cm common nail (5 mm shank, 11 mm head); its tip is specular."""
    head = rect(-5.1, -0.55, -4.9, 0.55)
    shank = rect(-4.9, -0.25, 4.2, 0.25)
    tip = np.array([[4.2, -0.25], [5.1, 0.0], [4.2, 0.25]])
    regions = [('specular', rect(2.2, -0.6, 5.3, 0.6))]
    return _spec('nail', 2015_02, [head, shank, tip], regions, height_cm=0.5, color=(112, 114, 122),
                 offset_cm=(-0.3, 0.2), rotation_deg=15.0)


def signal_splitter() -> SceneSpec:
    """C: 2-way coax splitter: black body 7 x 4.2 cm, three metal F-connectors (specular)."""
    parts = [rect(-3.5, -2.1, 3.5, 2.1)]
    connectors = []
    for side, yc in ((-1, 0.0), (1, -1.1), (1, 1.1)):
        hex_nut = rect(3.5, yc - 0.55, 4.1, yc + 0.55)
        barrel = rect(4.1, yc - 0.47, 5.1, yc + 0.47)
        if side < 0:
            hex_nut, barrel = hex_nut * [-1, 1], barrel * [-1, 1]
        parts += [hex_nut, barrel]
        connectors.append(rect(3.45, yc - 0.7, 5.3, yc + 0.7) * ([-1, 1] if side < 0 else [1, 1]))
    regions = [('dark', rect(-3.6, -2.2, 3.6, 2.2))] + [('specular', c) for c in connectors]
    return _spec('signal_splitter', 2015_03, parts, regions, height_cm=2.2, color=(70, 72, 78),
                 offset_cm=(0.2, -0.4), rotation_deg=4.0)


def toy_plane() -> SceneSpec:
    """D: die-cast toy plane, 15 cm long, 14 cm span; painted fuselage, specular (bare metal) wings."""
    fuselage = rect(-7.0, -0.9, 6.0, 0.9)
    nose = circle(6.0, 0.0, 0.9, 48)
    tail = np.array([[-7.0, -0.9], [-8.0, -0.4], [-8.0, 0.4], [-7.0, 0.9]])
    wing = np.array([[3.2, -0.8], [2.4, -7.0], [0.8, -7.0], [0.0, -0.8]])
    stab = np.array([[-5.6, -0.8], [-6.6, -3.0], [-7.6, -3.0], [-7.6, -0.8]])
    parts = [fuselage, nose, tail, wing, mirror_y(wing), stab, mirror_y(stab)]
    wing_region = np.array([[3.4, -0.95], [2.5, -7.2], [0.7, -7.2], [-0.2, -0.95]])
    stab_region = np.array([[-5.4, -0.95], [-6.5, -3.2], [-7.8, -3.2], [-7.8, -0.95]])
    regions = [('specular', wing_region), ('specular', mirror_y(wing_region)),
               ('specular', stab_region), ('specular', mirror_y(stab_region))]
    return _spec('toy_plane', 2015_04, parts, regions, height_cm=2.0, color=(178, 44, 40),
                 offset_cm=(0.3, 0.0), rotation_deg=-10.0)


def mechanical_switch() -> SceneSpec:
    """E: roller-lever limit switch: 6.4 x 3.6 cm plastic body; metal lever, roller and terminals specular."""
    body = rect(-3.2, -1.8, 3.2, 1.8)
    terminals = [rect(x - 0.3, 1.8, x + 0.3, 2.9) for x in (-1.8, 0.0, 1.8)]
    pivot, end = np.array([2.3, -1.5]), np.array([-2.2, -6.2])
    d = (end - pivot) / np.linalg.norm(end - pivot)
    n = np.array([-d[1], d[0]]) * 0.3
    lever = np.array([pivot + n, end + n, end - n, pivot - n])
    roller = circle(*end, 0.9, 64)
    parts = [body, *terminals, lever, roller]
    regions = [('specular', t) for t in terminals] + [('specular', lever), ('specular', circle(*end, 0.95, 64))]
    return _spec('mechanical_switch', 2015_05, parts, regions, height_cm=2.0, color=(86, 98, 118),
                 offset_cm=(0.0, 1.3), rotation_deg=0.0)


def crystal_knob() -> SceneSpec:
    """F: 7.2 cm faceted crystal knob (transparent, 12 facets); the metal base shows through (specular).

    Camera at 0.5 m (PR2 head lowered) so the small knob still spans about 80 pixels."""
    a = np.linspace(0.0, 2.0 * math.pi, 24, endpoint=False)
    r = np.where(np.arange(24) % 2 == 0, 3.6, 3.38)
    knob = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    regions = [('transparent', rect(-4.0, -4.0, 4.0, 4.0)), ('specular', circle(0.0, 0.0, 0.9, 48))]
    return _spec('crystal_knob', 2015_06, [knob], regions, height_cm=3.5, color=(222, 230, 244),
                 offset_cm=(0.2, 0.1), rotation_deg=7.0, camera_height=0.5)


def squirt_bottle() -> SceneSpec:
    """G: squirt bottle lying on its side, 21.5 cm: clear body (transparent, specular highlight band),
    opaque red cap, translucent nozzle."""
    body = rect(-8.0, -3.3, 5.0, 3.3)  # 6.6 cm cylinder seen from above
    bottom = [circle(-8.0, -2.3, 1.0, 48), circle(-8.0, 2.3, 1.0, 48), rect(-9.0, -2.3, -8.0, 2.3)]
    shoulder = np.array([[5.0, -3.3], [7.0, -1.5], [7.0, 1.5], [5.0, 3.3]])
    cap = rect(7.0, -1.5, 9.5, 1.5)
    nozzle = np.array([[9.5, -0.6], [12.5, -0.25], [12.5, 0.25], [9.5, 0.6]])
    parts = [body, *bottom, shoulder, cap, nozzle]
    clear = (214, 226, 236)
    regions = [('transparent', rect(-9.5, -3.6, 7.0, 3.6), clear),
               ('specular', rect(-8.4, -0.9, 5.2, 0.7)),
               ('opaque', rect(7.0, -1.6, 9.5, 1.6), (196, 32, 38)),
               ('noisy', rect(9.5, -0.7, 12.7, 0.7), (236, 236, 228))]
    return _spec('squirt_bottle', 2015_07, parts, regions, height_cm=6.6, color=clear,
                 offset_cm=(-1.6, -0.2), rotation_deg=3.0)


def marker() -> SceneSpec:
    """H: 13.5 cm marker: white barrel, specular label band in the middle, black (dark) cap with clip."""
    barrel = rect(-5.85, -0.9, 4.0, 0.9)
    end = circle(-5.85, 0.0, 0.9, 48)  # rounded back end
    cap = rect(4.0, -1.0, 6.75, 1.0)
    clip = rect(4.4, -1.3, 6.3, -1.0)
    parts = [barrel, end, cap, clip]
    regions = [('specular', rect(-1.3, -1.1, 1.3, 1.1)), ('dark', rect(3.95, -1.4, 6.9, 1.1), (32, 32, 34))]
    return _spec('marker', 2015_08, parts, regions, height_cm=1.9, color=(236, 236, 230),
                 offset_cm=(0.6, -0.3), rotation_deg=25.0)


OBJECTS: dict[str, ObjectDef] = {o.letter: o for o in (
    ObjectDef('A', 'tape_dispenser', 'plastic tape dispenser', '11.7 x 7.4 x 2.5',
              'opaque tape roll; transparent dispenser and hub', tape_dispenser),
    ObjectDef('B', 'nail', 'nail', '10.2 x 1.1 x 0.5', 'steel; specular tip (last 3 cm)', nail),
    ObjectDef('C', 'signal_splitter', 'signal splitter', '10.2 x 4.2 x 2.2',
              'dark plastic body; specular metal connectors', signal_splitter),
    ObjectDef('D', 'toy_plane', 'metal toy plane', '14.9 x 14.0 x 2.0',
              'painted fuselage; specular wings and tailplane', toy_plane),
    ObjectDef('E', 'mechanical_switch', 'mechanical switch', '6.4 x 10.0 x 2.0',
              'plastic body; specular lever, roller, terminals', mechanical_switch),
    ObjectDef('F', 'crystal_knob', 'crystal knob', '7.2 diameter x 3.5',
              'transparent crystal; specular metal base', crystal_knob),
    ObjectDef('G', 'squirt_bottle', 'squirt bottle', '21.5 x 6.6 x 6.6',
              'transparent body with specular band; opaque cap; noisy nozzle', squirt_bottle),
    ObjectDef('H', 'marker', 'marker', '13.5 x 2.3 x 1.9',
              'white barrel; specular mid-body band; dark cap', marker),
)}


# --------------------------------------------------------------------------- head-camera views
@dataclass(frozen=True)
class HeadView:
    """A PR2-like head-camera view of one object: camera pose (degrees, m), light (azimuth, elevation in
    degrees) and distractors given as (kind, side, gap_cm, size_cm, height_cm, colour): a ``box`` (size =
    (length, width)) or ``can`` (size = (diameter,)) placed ``gap_cm`` beyond the object's bounding box on
    ``side`` (``+x``, ``-x``, ``+y``, ``-y``), centred on the box's other axis."""

    tilt_deg: float
    azimuth_deg: float
    light: tuple[float, float]
    distractors: tuple[tuple, ...]
    distance_m: float = 0.9


GREEN, YELLOW, BLUE, ORANGE = (52, 128, 74), (204, 186, 58), (48, 84, 164), (212, 118, 46)

HEAD_VIEWS: dict[str, HeadView] = {
    'A': HeadView(50.0, 0.0, (210.0, 60.0), (('can', '+x', 3.0, (4.0,), 5.0, GREEN),)),
    'B': HeadView(45.0, -10.0, (160.0, 55.0), (('box', '+x', 3.0, (1.5, 1.5), 2.0, ORANGE),
                                                ('box', '-y', 3.0, (1.8, 1.2), 1.5, BLUE))),
    'C': HeadView(55.0, 15.0, (230.0, 62.0), (('box', '-x', 3.0, (3.0, 2.5), 2.5, YELLOW),)),
    'D': HeadView(48.0, -5.0, (200.0, 58.0), (('can', '+x', 3.0, (3.0,), 6.0, BLUE),)),
    'E': HeadView(52.0, 8.0, (150.0, 60.0), (('box', '+x', 3.0, (2.5, 2.5), 3.0, GREEN),)),
    'F': HeadView(50.0, -15.0, (220.0, 65.0), (('can', '-x', 3.0, (2.4,), 4.0, ORANGE),), distance_m=0.85),
    'G': HeadView(46.0, 5.0, (190.0, 60.0), (('box', '-x', 3.0, (3.0, 3.0), 4.0, ORANGE),)),
    'H': HeadView(54.0, -8.0, (200.0, 55.0), (('box', '+x', 3.0, (2.0, 3.0), 2.5, GREEN),
                                               ('can', '-x', 3.0, (3.0,), 5.0, YELLOW))),
}
HEAD_SEED_OFFSET = 1000
HEAD_DIR = 'head'


def _place_distractor(outline: np.ndarray, kind: str, side: str, gap_cm: float, size_cm: tuple[float, ...],
                      height_cm: float, color: tuple[int, int, int]) -> Distractor:
    lo, hi = outline.min(axis=0), outline.max(axis=0)
    mid = (lo + hi) / 2.0
    axis = 0 if side[1] == 'x' else 1
    half = (size_cm[0] if kind == 'can' or axis == 0 else size_cm[1]) * CM / 2.0
    centre = mid.copy()
    centre[axis] = hi[axis] + gap_cm * CM + half if side[0] == '+' else lo[axis] - gap_cm * CM - half
    if kind == 'can':
        return Distractor.cylinder(float(centre[0]), float(centre[1]), size_cm[0] * CM / 2.0, height_cm * CM, color)
    if kind == 'box':
        return Distractor.box(float(centre[0]), float(centre[1]), size_cm[0] * CM, size_cm[1] * CM, height_cm * CM,
                              color=color)
    raise ValueError(f"unknown distractor kind '{kind}' (box or can)")


def head_spec(letter: str) -> SceneSpec:
    """Scene of object ``letter`` seen by the head camera of :data:`HEAD_VIEWS` (own seed)."""
    base = OBJECTS[letter.upper()].build()
    view = HEAD_VIEWS[letter.upper()]
    distractors = [_place_distractor(base.outline, *d) for d in view.distractors]
    return replace(base, camera_height=view.distance_m, camera_tilt=view.tilt_deg, camera_azimuth=view.azimuth_deg,
                   light=view.light, distractors=distractors, seed=base.seed + HEAD_SEED_OFFSET,
                   name=f'{base.name}_head')


def make_head_bag(letter: str, out_dir: str | Path = DEFAULT_BAG_DIR / HEAD_DIR) -> Path:
    """Simulate object ``letter`` seen by the head camera and (over)write ``out_dir/<letter>_<name>.mcap``."""
    obj = OBJECTS[letter.upper()]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return write_scene_bag(head_spec(letter), out / obj.filename, overwrite=True)


def make_object_bag(letter: str, out_dir: str | Path = DEFAULT_BAG_DIR, write_outline: bool = True) -> Path:
    """Simulate object ``letter`` and (over)write ``out_dir/<letter>_<name>.mcap``; returns the path."""
    obj = OBJECTS[letter.upper()]
    spec = obj.build()
    out = Path(out_dir)
    if write_outline:
        (out / 'objects').mkdir(parents=True, exist_ok=True)
        save_polygon_csv(out / 'objects' / f'{obj.letter}_{obj.name}.csv', spec.outline,
                         comment=f'Object {obj.letter} ({obj.description}) outline, Mahler et al. ICRA 2015 Fig. 1')
    return write_scene_bag(spec, out / obj.filename, overwrite=True)


def main(argv: list[str] | None = None) -> int:
    """``gpis-grasp make-bags``: regenerate the eight object bags (``--head``: the head-camera set)."""
    parser = argparse.ArgumentParser(prog='gpis-grasp make-bags', description=__doc__.split('\n\n')[0])
    parser.add_argument('--out', default=str(DEFAULT_BAG_DIR), help='output directory (default: %(default)s)')
    parser.add_argument('--only', default='', help='comma-separated object letters, e.g. A,B (default: all)')
    parser.add_argument('--head', action='store_true',
                        help=f'the head-camera set (tilted camera, shadows, distractors) into OUT/{HEAD_DIR}/')
    args = parser.parse_args(argv)
    letters = [x.strip().upper() for x in args.only.split(',') if x.strip()] or list(OBJECTS)
    unknown = [x for x in letters if x not in OBJECTS]
    if unknown:
        print(f"gpis-grasp make-bags: unknown object(s) {', '.join(unknown)}; choose from {', '.join(OBJECTS)}",
              file=sys.stderr)
        return 2
    for letter in letters:
        try:
            path = make_head_bag(letter, Path(args.out) / HEAD_DIR) if args.head else make_object_bag(letter, args.out)
        except (ValueError, OSError) as err:
            print(f'gpis-grasp make-bags: object {letter}: {err}', file=sys.stderr)
            return 1
        print(f'{path}  {path.stat().st_size / 1e6:.2f} MB')
    return 0


if __name__ == '__main__':
    sys.exit(main())
