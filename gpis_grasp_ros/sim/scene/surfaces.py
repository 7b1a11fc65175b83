"""Scene composition: the target, its material regions and the distractors as one raster of surface ids.

Every surface gets an id (0 = table, 1 = target body, 2 + i = region i, then one per distractor) with
its material label, colour, top height and object index; a fine raster of ids over the table plane is
what the ray tracer samples. The light's cast shadow on the table is a raster too.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.sim.scene.polygons import rasterise_polygon
from gpis_grasp_ros.sim.scene.spec import FRAME_ID, L_OPAQUE, L_TRANSPARENT, MATERIAL_LABEL

#: Tolerance (m) of the "sample at or below a surface's top" tests.
HEIGHT_EPS_M = 1e-9


def shadow_shift(light: tuple[float, float] | None) -> np.ndarray | None:
    """Table-frame shift (m per m of height) from an occluder point to its shadow on the table, for a light
    at (azimuth, elevation) degrees (:mod:`~gpis_grasp_ros.sim.scene.spec`); None without a light."""
    if light is None:
        return None
    az, el = (math.radians(float(v)) for v in light)
    return -np.array([math.cos(az), math.sin(az)]) * (math.cos(el) / math.sin(el))


class SurfaceRaster:
    """Surface-id tables (``kind_of_id``, ``color_of_id``, ``top_of_id``, ``obj_of_id``), the id raster
    ``ids`` on ``geometry`` and the cast-shadow raster ``shadow`` (None without a light).

    ``regions`` are validated (kind, polygon) pairs, ``distractors`` (polygon, height, kind, colour)
    tuples; ValueError when a region misses the target or a distractor overlaps another object."""

    RESOLUTION = 0.00025  # m, material raster used for ray tracing

    def __init__(self, outline: np.ndarray, height: float, regions: Sequence[tuple[str, np.ndarray]],
                 region_colors: Sequence[np.ndarray], distractors: Sequence[tuple[np.ndarray, float, str, np.ndarray]],
                 table_color: np.ndarray, object_color: np.ndarray, table_depth: float, hmax: float,
                 shift: np.ndarray | None) -> None:
        n_main = 2 + len(regions)
        self.kind_of_id = np.array([0, L_OPAQUE] + [MATERIAL_LABEL[k] for k, _ in regions]
                                   + [MATERIAL_LABEL[d[2]] for d in distractors], dtype=np.uint8)
        self.color_of_id = np.array([table_color, object_color] + list(region_colors)
                                    + [d[3] for d in distractors], dtype=np.float64)
        #: height (m) of each surface's top above the table; object index (0 table, 1 target, 2 + j distractor j)
        self.top_of_id = np.array([0.0] + [float(height)] * (n_main - 1) + [d[1] for d in distractors])
        self.obj_of_id = np.array([0] + [1] * (n_main - 1) + [2 + j for j in range(len(distractors))])
        self.hmax = hmax

        res = self.RESOLUTION
        pts = np.concatenate([outline] + [d[0] for d in distractors])
        if shift is not None:
            pts = np.concatenate([pts, pts + hmax * shift])
        lo = np.floor(pts.min(axis=0) / res) * res - 2 * res
        hi = np.ceil(pts.max(axis=0) / res) * res + 2 * res
        w, h = (int(round(v)) for v in (hi - lo) / res)
        self.geometry = GridGeometry(float(lo[0]), float(lo[1]), res, w, h, table_depth, FRAME_ID)
        inside = rasterise_polygon(outline, self.geometry)
        n_ids = len(self.kind_of_id)
        ids = np.where(inside, 1, 0).astype(np.uint8 if n_ids < 250 else np.uint16)
        for i, (kind, poly) in enumerate(regions):
            cells = rasterise_polygon(poly, self.geometry) & inside
            if not cells.any():
                raise ValueError(f"region {i} ('{kind}') does not overlap the object outline")
            ids[cells] = i + 2
        for j, (poly, *_rest) in enumerate(distractors):
            cells = rasterise_polygon(poly, self.geometry)
            if (cells & (ids > 0)).any():
                raise ValueError(f'distractor {j} overlaps the object or another distractor')
            ids[cells] = 2 + len(regions) + j
        self.ids = ids
        self.shadow = None if shift is None else self._cast_shadow(shift)

    def _cast_shadow(self, shift: np.ndarray) -> np.ndarray:
        """Boolean raster of the table cells in the light's shadow: a cell p is dark when p - s * shift... i.e.
        some non-transparent column of top height >= s lies at p + s * |shift| towards the light, s in [0, top]."""
        res = self.RESOLUTION
        kinds = self.kind_of_id[self.ids]
        solid = (kinds > 0) & (kinds != L_TRANSPARENT)
        top = self.top_of_id[self.ids]
        shadow = np.zeros_like(solid)
        n = max(2, int(math.ceil(self.hmax * float(np.abs(shift).max()) / res)) + 1)
        done: set[tuple[int, int]] = set()
        for s in np.linspace(0.0, self.hmax, n):
            dc, dr = (int(round(v)) for v in s * shift / res)
            if (dc, dr) in done and s > 0:
                continue
            done.add((dc, dr))
            src = solid & (top >= s - HEIGHT_EPS_M)
            h, w = src.shape
            shadow[max(dr, 0):h + min(dr, 0), max(dc, 0):w + min(dc, 0)] |= \
                src[max(-dr, 0):h - max(dr, 0), max(-dc, 0):w - max(dc, 0)]
        return shadow

    def lookup(self, xy: np.ndarray, raster: np.ndarray | None = None) -> np.ndarray:
        """Surface id (or ``raster`` value) at metric table-plane points (..., 2); 0 outside the raster."""
        g = self.geometry
        values = self.ids if raster is None else raster
        col = np.floor((xy[..., 0] - g.origin_x) / g.resolution).astype(np.int64)
        row = np.floor((xy[..., 1] - g.origin_y) / g.resolution).astype(np.int64)
        ok = (col >= 0) & (col < g.width) & (row >= 0) & (row < g.height)
        out = np.zeros(xy.shape[:-1], dtype=values.dtype)
        out[ok] = values[row[ok], col[ok]]
        return out
