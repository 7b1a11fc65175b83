"""The manifest of ``gpis-grasp evaluate-real``: real captures with ground truth, as raw files or imported bags.

A YAML mapping::

    root: ../data            # optional: the directory the capture paths are relative to (itself relative
                             # to the manifest file; --root DIR overrides it); default: the manifest's directory
    captures:
      - name: bottle                       # optional (default: the bag's or the colour image's file stem)
        rgb: 000000080-transparent-rgb-img.jpg
        depth: 000000080-transparent-depth-mm.png
        intrinsics: camera_intrinsics.yaml # a file, or a mapping fx, fy, cx, cy (px), width, height
        sensor: realsense_d400             # depth-noise model (default realsense_d400)
        gt_mask: 000000080-mask.png
        gt_depth: 000000080-opaque-depth-mm.png
        target_pixel: [882, 522]           # (u, v) in the full image
        crop: [440, 200, 1280, 720]        # optional (u0, v0, u1, v1): the capture also runs cropped
        scale: 0.5                         # optional downscale in (0, 1] (default 1)
        depth_scale: 0.001                 # optional m per unit of integer depth (default 0.001)
      - bag: bags/real/cleargrasp_000000080_bottle.mcap   # a bag already imported
        target_pixel: [220.8, 160.8]       # in the bag's image

Each raw capture gives a *whole*-frame unit and, with a crop, a *crop* unit; a bag gives one *bag* unit.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import yaml

from gpis_grasp_ros.core.noise_model import SENSOR_MODELS

RAW_FILES = ('rgb', 'depth', 'gt_mask', 'gt_depth')
RAW_KEYS = {'name', 'sensor', 'target_pixel', 'crop', 'scale', 'depth_scale', 'intrinsics', 'clear_body_height',
            *RAW_FILES}
BAG_KEYS = {'name', 'sensor', 'target_pixel', 'bag', 'clear_body_height'}
SENSORS = tuple(m for m in SENSOR_MODELS if m != 'custom')


@dataclass(frozen=True)
class Unit:
    """One capture in one variant ('whole', 'crop' or 'bag'), with absolute paths: what one fit is made of."""

    capture: str
    variant: str
    target_pixel: tuple[float, float]  # full image (raw) or bag image (bag)
    sensor: str = 'realsense_d400'
    clear_body_height_m: float = 0.0
    bag: str | None = None
    rgb: str | None = None
    depth: str | None = None
    intrinsics: str | dict[str, Any] | None = None
    gt_mask: str | None = None
    gt_depth: str | None = None
    crop: tuple[int, int, int, int] | None = None
    scale: float = 1.0
    depth_scale: float = 0.001

    @property
    def id(self) -> str:
        return f'{self.capture}|{self.variant}'

    def entry(self) -> dict[str, Any]:
        """The unit as a JSON-able task entry (``id`` first)."""
        return {'id': self.id, **asdict(self)}


def _pair(value: Any, what: str) -> tuple[float, float]:
    if not (isinstance(value, list | tuple) and len(value) == 2):
        raise ValueError(f'{what} must be two numbers [u, v], got {value!r}')
    return float(value[0]), float(value[1])


def _crop(value: Any, what: str) -> tuple[int, int, int, int]:
    if not (isinstance(value, list | tuple) and len(value) == 4):
        raise ValueError(f'{what} must be four integers [u0, v0, u1, v1], got {value!r}')
    u0, v0, u1, v1 = (int(c) for c in value)
    if not (0 <= u0 < u1 and 0 <= v0 < v1):
        raise ValueError(f'{what} must have 0 <= u0 < u1 and 0 <= v0 < v1, got {value!r}')
    return u0, v0, u1, v1


def _file(root: Path, value: Any, what: str) -> str:
    if not isinstance(value, str | os.PathLike):
        raise ValueError(f'{what} must be a path, got {value!r}')
    p = (root / value).resolve()
    if not p.is_file():
        raise FileNotFoundError(f'{what}: {p} does not exist')
    return str(p)


def _units(item: Mapping[str, Any], root: Path, k: int) -> list[Unit]:
    where = f'captures[{k}]'
    if not isinstance(item, Mapping):
        raise ValueError(f'{where} must be a mapping')
    is_bag = 'bag' in item
    unknown = set(item) - (BAG_KEYS if is_bag else RAW_KEYS)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {', '.join(sorted(unknown))} for a {'bag' if is_bag else 'raw'} "
                         'capture')
    if 'target_pixel' not in item:
        raise ValueError(f'{where}: target_pixel [u, v] is required')
    sensor = str(item.get('sensor', 'realsense_d400'))
    if sensor not in SENSORS:
        raise ValueError(f"{where}: sensor must be one of {', '.join(SENSORS)}, got '{sensor}'")
    common = {'target_pixel': _pair(item['target_pixel'], f'{where}.target_pixel'), 'sensor': sensor,
              'clear_body_height_m': float(item.get('clear_body_height', 0.0))}
    if is_bag:
        path = (root / str(item['bag'])).resolve()
        if not path.exists():
            raise FileNotFoundError(f'{where}.bag: {path} does not exist')
        name = str(item.get('name') or path.stem)
        return [Unit(name, 'bag', bag=str(path), **common)]
    missing = [key for key in (*RAW_FILES, 'intrinsics') if key not in item]
    if missing:
        raise ValueError(f"{where}: a raw capture needs {', '.join(missing)} (or give bag: PATH)")
    files = {key: _file(root, item[key], f'{where}.{key}') for key in RAW_FILES}
    intr = item['intrinsics']
    intrinsics = dict(intr) if isinstance(intr, Mapping) else _file(root, intr, f'{where}.intrinsics')
    scale = float(item.get('scale', 1.0))
    if not 0 < scale <= 1:
        raise ValueError(f'{where}.scale must be in (0, 1], got {scale}')
    raw = {**common, **files, 'intrinsics': intrinsics, 'scale': scale,
           'depth_scale': float(item.get('depth_scale', 0.001))}
    name = str(item.get('name') or Path(files['rgb']).stem)
    units = [Unit(name, 'whole', **raw)]
    if item.get('crop') is not None:
        units.append(Unit(name, 'crop', crop=_crop(item['crop'], f'{where}.crop'), **raw))
    return units


def load_manifest(path: str | os.PathLike[str], root: str | os.PathLike[str] | None = None) -> list[Unit]:
    """The units of a manifest file (module docstring); ``root`` overrides its ``root:`` key.

    Raises ValueError on a malformed manifest, FileNotFoundError on a missing file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f'manifest {path} does not exist')
    data = yaml.safe_load(path.read_text(encoding='utf8'))
    if not isinstance(data, Mapping) or not isinstance(data.get('captures'), list) or not data['captures']:
        raise ValueError(f'{path}: expected a mapping with a non-empty list captures: [...]')
    unknown = set(data) - {'root', 'captures'}
    if unknown:
        raise ValueError(f"{path}: unknown top-level key(s) {', '.join(sorted(unknown))}")
    base = Path(root) if root is not None else path.parent / str(data.get('root', '.'))
    units = [u for k, item in enumerate(data['captures']) for u in _units(item, base, k)]
    ids = [u.id for u in units]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise ValueError(f"{path}: capture names must be unique, repeated: {', '.join(dup)}")
    return units
