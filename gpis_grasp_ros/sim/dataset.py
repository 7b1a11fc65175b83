"""Deterministic object sets for dataset-scale evaluation and cross-validation of the hyperparameters.

The paper tunes λ "using cross-validation over a set of validation shapes" (section VI-A) and α
likewise (eq. 5); eight objects cannot support that. :func:`make_dataset` writes a *manifest*
(``manifest.json``, one entry per object, plus a flat ``manifest.csv``) from which every scene is
rebuilt exactly, in memory, by whichever worker evaluates it (:func:`render_entry`): no bags need
to be shipped to workers. A bag per object is written on request (``bags=True`` or
:func:`write_entry_bag`). The paper's eight objects (:mod:`gpis_grasp_ros.sim.objects`) and
users' own bags can be mixed in.

Generated objects
-----------------
Object ``i`` of a dataset with seed ``S`` is drawn from ``np.random.SeedSequence([S, i])`` alone,
so a dataset of N objects is a prefix of one of N' > N objects with the same seed, and the same
(S, i) always gives the same manifest entry (bytes) and the same rendered frames.

* **Outline families** (``family``): ``polygon`` (random star-shaped polygon, 5-12 vertices,
  stretched), ``superellipse`` (|x/a|^p + |y/b|^p = 1, p in [0.6, 4]: pinched/concave for p < 1,
  boxy for large p), ``union`` (2-4 overlapping rectangles and discs), ``thin`` (a stick 3-12 mm
  wide with an optional head: nails, pens, cables) and ``concave`` (L, U, T shapes and deep stars).
  Every outline is a valid simple polygon (:func:`~gpis_grasp_ros.sim.scene.validate_polygon`).
* **Size**: the largest extent is log-uniform in ``size_range_m`` (default 2 cm ... 14 cm, i.e.
  beyond the PR2-like maximum opening w_g = 9 cm). ``size_class``: ``small`` (< 4 cm),
  ``medium`` (<= w_g), ``large`` (> w_g: some directions cannot be grasped). ``min_width_m`` is the
  smallest caliper width (over 180 directions), the narrowest opening that can enclose the object.
* **Materials**: with probability 0.35 the object is plain opaque; otherwise 1-2 regions of
  ``transparent``, ``specular``, ``dark`` or ``noisy`` material (see :mod:`~gpis_grasp_ros.sim.scene.spec`),
  each a box around a random interior point covering 30-80 % of the bounding box per side, or
  (probability 0.2) the whole object. ``material_class`` is ``opaque``, the single kind, or ``mixed``.
* **Camera**: 0.5-0.8 m from the table point under the object; ``head`` (tilt 40-55° from straight
  down, random azimuth: a PR2-like head camera) for ``head_fraction`` of the objects when the
  simulator supports tilted cameras (:data:`TILTED_CAMERA`), else ``top-down``.
  :data:`CAMERA_POSES` lists what this simulator supports; the manifest's ``meta.note`` says it.
* **Scene noise seed** and object colour (at least 60 RGB units from the table colour) are drawn too.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import json
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.sensing import CameraIntrinsics
from gpis_grasp_ros.data.bags import BagScene, load_bag
from gpis_grasp_ros.sim import objects as paper_objects
from gpis_grasp_ros.sim.scene import (
    FRAME_ID,
    MATERIAL_KINDS,
    MaterialRegion,
    Scene,
    SceneSpec,
    points_in_polygon,
    polygon_area,
    validate_polygon,
    write_scene_bag,
)

MANIFEST_VERSION = 1
MANIFEST_NAME = 'manifest.json'
FAMILIES: tuple[str, ...] = ('polygon', 'superellipse', 'union', 'thin', 'concave')
SPECIAL_MATERIALS: tuple[str, ...] = tuple(k for k in MATERIAL_KINDS if k != 'opaque')
#: Whether the simulator supports a tilted camera (``SceneSpec.camera_tilt`` / ``camera_azimuth``).
TILTED_CAMERA = {'camera_tilt', 'camera_azimuth'} <= {f.name for f in dataclasses.fields(SceneSpec)}
CAMERA_POSES: tuple[str, ...] = ('top-down', 'head') if TILTED_CAMERA else ('top-down',)
HEAD_TILT_DEG = (40.0, 55.0)  # a PR2-like head camera looking down at the table
DEFAULT_SIZE_RANGE_M = (0.02, 0.14)
DEFAULT_MAX_OPENING_M = 0.09  # w_g of GripperParams
SMALL_SIZE_M = 0.04
TABLE_COLOR = paper_objects.TABLE_COLOR
CSV_COLUMNS = ('id', 'source', 'name', 'family', 'size_m', 'min_width_m', 'size_class', 'material_class',
               'materials', 'camera', 'camera_tilt_deg', 'camera_height_m', 'height_m', 'area_m2', 'n_vertices',
               'scene_seed', 'bag')


# =========================================================================== outline families
def _scale_to(poly: np.ndarray, size: float) -> np.ndarray:
    """Scale a polygon about its bounding-box centre so that its largest caliper width
    (:func:`caliper_widths`, i.e. its diameter to 4e-5 relative) is ``size`` m."""
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    return (poly - 0.5 * (lo + hi)) * (size / float(caliper_widths(poly).max()))


def _rotation(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]])


def _star_polygon(rng: np.random.Generator) -> np.ndarray:
    """Random star-shaped polygon around the origin (simple by construction), stretched."""
    n = int(rng.integers(5, 13))
    gaps = rng.uniform(0.5, 1.5, n)
    angles = np.cumsum(gaps) / gaps.sum() * 2 * math.pi
    radii = rng.uniform(0.45, 1.0, n)
    poly = np.stack([radii * np.cos(angles), radii * np.sin(angles)], axis=1)
    return poly * np.array([1.0, rng.uniform(0.4, 1.0)])  # an affine stretch keeps it simple


def _superellipse(rng: np.random.Generator) -> np.ndarray:
    p = float(np.exp(rng.uniform(math.log(0.6), math.log(4.0))))
    b = float(rng.uniform(0.3, 1.0))
    t = np.linspace(0.0, 2 * math.pi, 72, endpoint=False)
    c, s = np.cos(t), np.sin(t)
    return np.stack([np.sign(c) * np.abs(c) ** (2 / p), b * np.sign(s) * np.abs(s) ** (2 / p)], axis=1)


def _union_of_primitives(rng: np.random.Generator) -> np.ndarray:
    """2-4 rectangles/discs (cm scale), each centred inside the previous one, merged by raster."""
    parts: list[np.ndarray] = []
    center = np.zeros(2)
    for k in range(int(rng.integers(2, 5))):
        if k:
            prev = parts[-1]
            lo, hi = prev.min(axis=0), prev.max(axis=0)
            for _ in range(50):  # a point inside the previous primitive (always found in practice)
                cand = rng.uniform(lo, hi)
                if points_in_polygon(cand[None], prev)[0]:
                    center = cand
                    break
            else:
                center = prev.mean(axis=0)
        if rng.random() < 0.5:
            w, h = rng.uniform(0.8, 4.0), rng.uniform(0.5, 2.0)
            rect = np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) / 2
            parts.append(rect @ _rotation(rng.uniform(0, math.pi)).T + center)
        else:
            parts.append(paper_objects.circle(center[0], center[1], rng.uniform(0.4, 1.4), 48))
    return _union(parts)


def _union(parts_cm: Sequence[np.ndarray]) -> np.ndarray:
    """Union outline (cm) of primitives (cm), at 1/300 of the union's extent."""
    pts = np.concatenate(parts_cm)
    res = float(np.max(np.ptp(pts, axis=0))) / 300.0
    return paper_objects.union_outline([p * paper_objects.CM for p in parts_cm], resolution=res * paper_objects.CM) \
        / paper_objects.CM


def _thin(rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """A stick (unit length) and its width in units of the length; optional head or bend."""
    width = float(rng.uniform(0.04, 0.15))
    parts = [np.array([[-0.5, -width / 2], [0.5, -width / 2], [0.5, width / 2], [-0.5, width / 2]])]
    style = rng.integers(3)
    if style == 1:  # nail/pen head
        hw = width * rng.uniform(1.5, 2.5)
        parts.append(np.array([[-0.5, -hw / 2], [-0.45, -hw / 2], [-0.45, hw / 2], [-0.5, hw / 2]]))
    elif style == 2:  # bent: a second, shorter arm at an angle
        arm = rng.uniform(0.25, 0.5)
        a = np.array([[0.0, -width / 2], [arm, -width / 2], [arm, width / 2], [0.0, width / 2]])
        parts.append(a @ _rotation(rng.uniform(0.6, 2.0)).T + np.array([0.5 - width / 2, 0.0]))
    return _union([p * 10 for p in parts]) / 10, width


def _concave(rng: np.random.Generator) -> np.ndarray:
    kind = int(rng.integers(4))
    t = rng.uniform(0.18, 0.35)  # arm thickness (fraction of the size)
    if kind == 3:  # deep star
        n = int(rng.integers(4, 8))
        a = np.linspace(0, 2 * math.pi, 2 * n, endpoint=False)
        r = np.where(np.arange(2 * n) % 2 == 0, 1.0, rng.uniform(0.3, 0.55))
        return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    h = rng.uniform(0.6, 1.0)
    if kind == 0:  # L
        return np.array([[0, 0], [1, 0], [1, t], [t, t], [t, h], [0, h]], dtype=np.float64)
    if kind == 1:  # U
        return np.array([[0, 0], [1, 0], [1, h], [1 - t, h], [1 - t, t], [t, t], [t, h], [0, h]], dtype=np.float64)
    # T
    return np.array([[0, h - t], [(1 - t) / 2, h - t], [(1 - t) / 2, 0], [(1 + t) / 2, 0], [(1 + t) / 2, h - t],
                     [1, h - t], [1, h], [0, h]], dtype=np.float64)


def generate_outline(family: str, size_m: float, rng: np.random.Generator) -> np.ndarray:
    """A random outline (m) of ``family`` with largest extent ``size_m``, randomly rotated, centred on
    the optical axis to within 1 cm; validated (simple, counter-clockwise)."""
    if family == 'polygon':
        shape = _star_polygon(rng)
    elif family == 'superellipse':
        shape = _superellipse(rng)
    elif family == 'union':
        shape = _union_of_primitives(rng)
    elif family == 'thin':
        shape, _ = _thin(rng)
    elif family == 'concave':
        shape = _concave(rng)
    else:
        raise ValueError(f"unknown outline family '{family}'; expected one of {', '.join(FAMILIES)}")
    shape = _scale_to(np.asarray(shape, dtype=np.float64), 1.0) @ _rotation(rng.uniform(0, 2 * math.pi)).T
    outline = _scale_to(shape, size_m) + rng.uniform(-0.01, 0.01, 2)
    return validate_polygon(outline, what=f'{family} outline')


def caliper_widths(poly: np.ndarray, n_directions: int = 180) -> np.ndarray:
    """Width (m) of the polygon's projection on ``n_directions`` directions over 180°."""
    a = np.arange(n_directions) * math.pi / n_directions
    proj = poly @ np.stack([np.cos(a), np.sin(a)])
    return np.ptp(proj, axis=0)


def size_class(size_m: float, max_opening_m: float = DEFAULT_MAX_OPENING_M) -> str:
    """``small`` (< 4 cm), ``medium`` (<= w_g) or ``large`` (> w_g) from the largest extent."""
    if not math.isfinite(size_m):
        return 'unknown'
    return 'small' if size_m < SMALL_SIZE_M else 'medium' if size_m <= max_opening_m else 'large'


def material_class(kinds: Iterable[str]) -> str:
    """``opaque`` without special regions, the kind if all regions share it, else ``mixed``."""
    special = sorted({k for k in kinds if k != 'opaque'})
    return 'opaque' if not special else special[0] if len(special) == 1 else 'mixed'


def _random_regions(outline: np.ndarray, rng: np.random.Generator) -> list[dict[str, Any]]:
    if rng.random() < 0.35:
        return []
    lo, hi = outline.min(axis=0), outline.max(axis=0)
    regions = []
    for _ in range(int(rng.integers(1, 3))):
        kind = SPECIAL_MATERIALS[int(rng.integers(len(SPECIAL_MATERIALS)))]
        if rng.random() < 0.2:
            box_lo, box_hi = lo - 0.002, hi + 0.002
        else:
            inside = np.zeros(2)
            for _ in range(200):
                cand = rng.uniform(lo, hi)
                if points_in_polygon(cand[None], outline)[0]:
                    inside = cand
                    break
            half = 0.5 * rng.uniform(0.3, 0.8, 2) * (hi - lo)
            box_lo, box_hi = inside - half, inside + half
        poly = np.array([[box_lo[0], box_lo[1]], [box_hi[0], box_lo[1]], [box_hi[0], box_hi[1]],
                         [box_lo[0], box_hi[1]]])
        color = [int(v) for v in rng.integers(30, 230, 3)] if kind == 'transparent' else None
        regions.append({'kind': kind, 'polygon': poly.tolist(), 'color': color})
    return regions


def _object_color(rng: np.random.Generator) -> list[int]:
    table = np.array(TABLE_COLOR, dtype=np.float64)
    for _ in range(100):
        c = rng.integers(0, 256, 3)
        if np.linalg.norm(c - table) >= 60:
            break
    return [int(v) for v in c]


def generate_entry(seed: int, index: int, size_range_m: tuple[float, float] = DEFAULT_SIZE_RANGE_M,
                   max_opening_m: float = DEFAULT_MAX_OPENING_M, frames: int = 10,
                   head_fraction: float = 0.5) -> dict[str, Any]:
    """Manifest entry of generated object ``index`` of a dataset with ``seed`` (see the module docstring).

    ``head_fraction`` of the objects are seen by a tilted head camera when the simulator supports it
    (:data:`TILTED_CAMERA`), the others top-down."""
    lo, hi = (float(v) for v in size_range_m)
    if not (0 < lo <= hi):
        raise ValueError(f'size range must satisfy 0 < min <= max (m), got {size_range_m}')
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]))
    family = FAMILIES[int(rng.integers(len(FAMILIES)))]
    size = float(np.exp(rng.uniform(math.log(lo), math.log(hi))))
    outline = generate_outline(family, size, rng)
    height = float(rng.uniform(0.004, 0.012) if family == 'thin' else rng.uniform(0.008, 0.05))
    regions = _random_regions(outline, rng)
    camera_height = float(rng.uniform(0.5, 0.8))
    spec = {
        'outline': outline.tolist(), 'regions': regions, 'height': height, 'camera_height': camera_height,
        'object_color': _object_color(rng), 'table_color': list(TABLE_COLOR), 'frames': int(frames),
        'seed': int(rng.integers(0, 2**31 - 1)), 'name': f'gen_{index:05d}',
    }
    # camera pose drawn last and always, so the rest of the entry does not depend on simulator support
    head = rng.random() < head_fraction
    tilt, azimuth = float(rng.uniform(*HEAD_TILT_DEG)), float(rng.uniform(0.0, 360.0))
    camera = 'top-down'
    if head and TILTED_CAMERA:
        spec.update({'camera_tilt': tilt, 'camera_azimuth': azimuth})
        camera = 'head'
    return _entry(f'gen_{index:05d}', 'generated', f'gen_{index:05d}', family, spec, max_opening_m, camera=camera)


def _entry(entry_id: str, source: str, name: str, family: str, spec: dict[str, Any] | None, max_opening_m: float,
           camera: str, **extra: Any) -> dict[str, Any]:
    if spec is not None:
        outline = np.asarray(spec['outline'], dtype=np.float64)
        widths = caliper_widths(outline)
        size, min_width = float(widths.max()), float(widths.min())
        kinds = [r['kind'] for r in spec['regions']]
        area, n_vertices = abs(polygon_area(outline)), len(outline)
    else:
        size = min_width = area = float('nan')
        kinds, n_vertices = [], 0
    entry = {
        'id': entry_id, 'source': source, 'name': name, 'family': family, 'size_m': size, 'min_width_m': min_width,
        'size_class': size_class(size, max_opening_m), 'materials': kinds,
        'material_class': material_class(kinds) if spec is not None else 'unknown', 'camera': camera,
        'area_m2': area, 'n_vertices': n_vertices, 'spec': spec,
    }
    entry.update(extra)
    return entry


def spec_to_dict(spec: SceneSpec) -> dict[str, Any]:
    """JSON-able form of the parts of a :class:`SceneSpec` the dataset varies (camera model default)."""
    return {
        'outline': np.asarray(spec.outline, dtype=np.float64).tolist(),
        'regions': [{'kind': r.kind, 'polygon': np.asarray(r.polygon, dtype=np.float64).tolist(),
                     'color': None if r.color is None else [int(v) for v in r.color]} for r in spec.regions],
        'height': float(spec.height), 'camera_height': float(spec.camera_height),
        'object_color': [int(v) for v in spec.object_color], 'table_color': [int(v) for v in spec.table_color],
        'frames': int(spec.frames), 'seed': int(spec.seed), 'name': spec.name,
    }


def spec_from_dict(d: dict[str, Any], frames: int | None = None) -> SceneSpec:
    """:class:`SceneSpec` of a manifest ``spec`` (``frames`` overrides the number of frames)."""
    regions = [MaterialRegion(r['kind'], np.asarray(r['polygon'], dtype=np.float64),
                              None if r.get('color') is None else tuple(int(v) for v in r['color']))
               for r in d['regions']]
    return SceneSpec(outline=np.asarray(d['outline'], dtype=np.float64), regions=regions, height=float(d['height']),
                     table_color=tuple(d['table_color']), object_color=tuple(d['object_color']),
                     camera_height=float(d['camera_height']), frames=int(d['frames'] if frames is None else frames),
                     seed=int(d['seed']), name=str(d['name']),
                     **{k: float(d[k]) for k in ('camera_tilt', 'camera_azimuth') if k in d})


def paper_entry(letter: str, max_opening_m: float = DEFAULT_MAX_OPENING_M) -> dict[str, Any]:
    """Manifest entry of the paper's object ``letter`` (A-H, :mod:`gpis_grasp_ros.sim.objects`)."""
    key = letter.strip().upper()
    if key not in paper_objects.OBJECTS:
        raise ValueError(f"unknown paper object '{letter}'; choose from {', '.join(paper_objects.OBJECTS)}")
    obj = paper_objects.OBJECTS[key]
    return _entry(f'paper_{key}', 'paper', f'{key}_{obj.name}', 'paper', spec_to_dict(obj.build()), max_opening_m,
                  camera='top-down', letter=key)


def bag_entry(path: str | os.PathLike[str], max_opening_m: float = DEFAULT_MAX_OPENING_M) -> dict[str, Any]:
    """Manifest entry of a user's bag (read at evaluation time; the path is stored absolute).

    Size and material class come from the bag's ground truth if it has one (size only), else NaN/unknown.
    """
    p = Path(path).resolve()
    if not p.exists():
        raise ValueError(f'bag not found: {p}')
    entry = _entry(f'bag_{p.stem}', 'bag', p.stem, 'bag', None, max_opening_m, camera='unknown', bag=str(p))
    try:
        scene = load_bag(p, frames=1)
    except (ValueError, OSError, KeyError) as err:
        raise ValueError(f'bag {p} is not readable as a camera bag: {err}') from err
    if scene.true_sdf is not None and scene.true_geometry is not None:
        inside = scene.true_geometry.cell_centers()[scene.true_sdf < 0]
        if len(inside):
            widths = caliper_widths(inside)
            entry['size_m'] = float(widths.max())
            entry['min_width_m'] = float(widths.min())
            entry['size_class'] = size_class(entry['size_m'], max_opening_m)
            entry['area_m2'] = float(len(inside) * scene.true_geometry.resolution ** 2)
    return entry


# =========================================================================== datasets
@dataclass
class Dataset:
    """A loaded manifest: ``entries`` (dicts as written) and dataset-level ``meta``; ``root`` its folder."""

    root: Path
    meta: dict[str, Any]
    entries: list[dict[str, Any]]

    def entry(self, entry_id: str) -> dict[str, Any]:
        for e in self.entries:
            if e['id'] == entry_id:
                return e
        raise KeyError(f"no object '{entry_id}' in {self.root / MANIFEST_NAME}")


def build_manifest(n: int, seed: int, paper: Sequence[str] = (), bags: Sequence[str | os.PathLike[str]] = (),
                   size_range_m: tuple[float, float] = DEFAULT_SIZE_RANGE_M,
                   max_opening_m: float = DEFAULT_MAX_OPENING_M, frames: int = 10,
                   head_fraction: float = 0.5) -> dict[str, Any]:
    """The manifest (JSON-able dict) of ``n`` generated objects plus paper objects and user bags."""
    if int(n) != n or n < 0:
        raise ValueError(f'the number of objects must be a non-negative integer, got {n}')
    if int(seed) != seed or seed < 0:
        raise ValueError(f'the seed must be a non-negative integer, got {seed}')
    if int(frames) != frames or frames < 1:
        raise ValueError(f'frames must be a positive integer, got {frames}')
    entries = [generate_entry(int(seed), i, size_range_m, max_opening_m, int(frames), head_fraction)
               for i in range(int(n))]
    entries += [paper_entry(x, max_opening_m) for x in paper]
    entries += [bag_entry(b, max_opening_m) for b in bags]
    ids = [e['id'] for e in entries]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise ValueError(f"duplicate object ids in the dataset: {', '.join(dup)}")
    if not entries:
        raise ValueError('the dataset is empty: ask for --n > 0 objects, --paper letters or --bag files')
    meta = {
        'version': MANIFEST_VERSION, 'seed': int(seed), 'n_generated': int(n), 'frames': int(frames),
        'size_range_m': [float(v) for v in size_range_m], 'max_opening_m': float(max_opening_m),
        'families': list(FAMILIES), 'camera_poses': list(CAMERA_POSES),
        'head_fraction': float(head_fraction) if TILTED_CAMERA else 0.0,
        'note': ('camera poses: top-down and tilted head camera' if TILTED_CAMERA else
                 'camera pose: top-down only (this simulator has no tilted head-camera pose)'),
    }
    return {'meta': meta, 'objects': entries}


def manifest_bytes(manifest: dict[str, Any]) -> bytes:
    """Canonical JSON bytes of a manifest (sorted keys, floats round-trip exact): the same inputs give
    the same bytes."""
    return (json.dumps(manifest, sort_keys=True, indent=1, allow_nan=True) + '\n').encode('utf8')


def make_dataset(out: str | os.PathLike[str], n: int, seed: int, paper: Sequence[str] = (),
                 bags: Sequence[str | os.PathLike[str]] = (), write_bags: bool = False,
                 size_range_m: tuple[float, float] = DEFAULT_SIZE_RANGE_M,
                 max_opening_m: float = DEFAULT_MAX_OPENING_M, frames: int = 10,
                 head_fraction: float = 0.5) -> Dataset:
    """Write ``out/manifest.json`` and ``out/manifest.csv`` (and ``out/bags/<id>.mcap`` with
    ``write_bags``); returns the loaded dataset."""
    manifest = build_manifest(n, seed, paper, bags, size_range_m, max_opening_m, frames, head_fraction)
    root = Path(out)
    root.mkdir(parents=True, exist_ok=True)
    (root / MANIFEST_NAME).write_bytes(manifest_bytes(manifest))
    write_manifest_csv(root / 'manifest.csv', manifest['objects'])
    dataset = load_dataset(root)
    if write_bags:
        for entry in dataset.entries:
            if entry['spec'] is not None:
                write_entry_bag(entry, root / 'bags' / f"{entry['id']}.mcap")
    return dataset


def write_manifest_csv(path: Path, entries: Sequence[dict[str, Any]]) -> None:
    """One row per object with the columns of :data:`CSV_COLUMNS`."""
    with open(path, 'w', newline='', encoding='utf8') as fh:
        w = csv.DictWriter(fh, fieldnames=CSV_COLUMNS, lineterminator='\n')
        w.writeheader()
        for e in entries:
            spec = e.get('spec') or {}
            w.writerow({
                'id': e['id'], 'source': e['source'], 'name': e['name'], 'family': e['family'],
                'size_m': f"{e['size_m']:.5f}", 'min_width_m': f"{e['min_width_m']:.5f}",
                'size_class': e['size_class'], 'material_class': e['material_class'],
                'materials': '+'.join(e['materials']), 'camera': e['camera'],
                'camera_tilt_deg': f"{spec.get('camera_tilt', 0.0):.2f}" if spec else '',
                'camera_height_m': f"{spec['camera_height']:.4f}" if spec else '',
                'height_m': f"{spec['height']:.4f}" if spec else '', 'area_m2': f"{e['area_m2']:.6g}",
                'n_vertices': e['n_vertices'], 'scene_seed': spec.get('seed', ''), 'bag': e.get('bag', ''),
            })


def load_dataset(path: str | os.PathLike[str]) -> Dataset:
    """Read ``manifest.json`` of a dataset folder (or the file itself); ValueError with the reason."""
    p = Path(path)
    file = p / MANIFEST_NAME if p.is_dir() else p
    if not file.is_file():
        raise ValueError(f'no dataset manifest at {file} (make one with: gpis-grasp make-dataset --n N --out DIR)')
    try:
        manifest = json.loads(file.read_text(encoding='utf8'))
    except json.JSONDecodeError as err:
        raise ValueError(f'{file} is not valid JSON: {err}') from None
    if not isinstance(manifest, dict) or manifest.get('meta', {}).get('version') != MANIFEST_VERSION:
        raise ValueError(f'{file}: not a version-{MANIFEST_VERSION} gpis_grasp_ros dataset manifest')
    return Dataset(file.parent, manifest['meta'], list(manifest['objects']))


def manifest_digest(dataset: Dataset) -> str:
    """SHA-256 (hex, 16 chars) of the dataset's canonical manifest: identifies it in result files."""
    return hashlib.sha256(manifest_bytes({'meta': dataset.meta, 'objects': dataset.entries})).hexdigest()[:16]


# =========================================================================== rendering
def scene_of(entry: dict[str, Any], frames: int | None = None) -> Scene:
    """The simulator :class:`Scene` of a generated or paper entry (ValueError for bag entries)."""
    if entry.get('spec') is None:
        raise ValueError(f"object {entry['id']} is a recorded bag, not a simulated scene")
    return Scene(spec_from_dict(entry['spec'], frames))


def render_entry(entry: dict[str, Any], frames: int | None = None) -> BagScene:
    """The camera frames and ground truth of an entry, as :func:`~gpis_grasp_ros.data.bags.load_bag`
    returns them: rendered in memory for simulated entries (RGB + depth images, float64 depth,
    cropped intrinsics: what the ``images`` input path of segmentation_node sees), read from the bag
    for ``bag`` entries (``frames`` default 10)."""
    if entry.get('spec') is None:
        return load_bag(entry['bag'], frames=10 if frames is None else int(frames))
    scene = scene_of(entry, frames)
    rendered = list(scene.frames())
    gt = scene.ground_truth()
    return BagScene(rgb_frames=np.stack([f.rgb for f in rendered]),
                    depth_frames=np.stack([f.depth for f in rendered]).astype(np.float64),
                    intrinsics=CameraIntrinsics(*scene.intrinsics), frame_id=FRAME_ID,
                    stamp_ns=rendered[-1].stamp_ns, true_sdf=gt.sdf.astype(np.float64), true_geometry=gt.geometry,
                    true_center_of_mass=true_com_xy(gt.center_of_mass, gt.geometry),
                    true_obstacles=None if gt.obstacles is None else gt.obstacles.astype(np.float64))


def true_com_xy(center_of_mass: np.ndarray, geometry: GridGeometry) -> np.ndarray:
    """Grid (x, y) (m) of the ground-truth centre of mass: a sensor-frame 3D point on the table plane,
    or already (x, y) for 2-vector input."""
    com = np.asarray(center_of_mass, dtype=np.float64).reshape(-1)
    return com[:2].copy() if com.size == 2 else geometry.from_sensor(com[:3])[0]


def write_entry_bag(entry: dict[str, Any], path: str | os.PathLike[str], overwrite: bool = True) -> Path:
    """Write the MCAP bag of a simulated entry (the same streams as ``gpis-grasp make-bag``)."""
    if entry.get('spec') is None:
        raise ValueError(f"object {entry['id']} is already a bag: {entry.get('bag')}")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return write_scene_bag(spec_from_dict(entry['spec']), path, overwrite=overwrite)


__all__ = [
    'CAMERA_POSES', 'FAMILIES', 'Dataset', 'bag_entry', 'build_manifest', 'caliper_widths', 'generate_entry',
    'generate_outline', 'load_dataset', 'make_dataset', 'manifest_bytes', 'manifest_digest', 'material_class',
    'paper_entry', 'render_entry', 'scene_of', 'size_class', 'spec_from_dict', 'spec_to_dict', 'write_entry_bag',
]
