"""Planar polygon geometry in metres: area, centroid, validation, inside test, signed distance, rasterisation.

Object outlines, material regions and distractors are all simple polygons in the table plane; these
functions are the only geometry the simulator and its ground truth need.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry


def polygon_area(poly: np.ndarray) -> float:
    """Signed area (m^2) of a closed polygon (N, 2); positive for counter-clockwise in (x, y)."""
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def polygon_centroid(poly: np.ndarray) -> np.ndarray:
    """Area centroid (x, y) in m of a simple polygon (uniform density: the centre of mass)."""
    x, y = poly[:, 0], poly[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = 0.5 * cross.sum()
    return np.array([np.sum((x + xn) * cross), np.sum((y + yn) * cross)]) / (6.0 * area)


def _orient(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """z of (b - a) x (c - a), broadcast over leading axes."""
    return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])


def _first_self_intersection(poly: np.ndarray) -> tuple[int, int] | None:
    """Indices (i, j) of two non-adjacent edges that touch or cross, or None for a simple polygon."""
    n = len(poly)
    a, b = poly, np.roll(poly, -1, axis=0)
    scale = float(np.ptp(poly, axis=0).max()) or 1.0
    eps = 1e-12 * scale * scale
    i, j = np.triu_indices(n, k=2)
    keep = ~((i == 0) & (j == n - 1))  # first and last edge share vertex 0
    i, j = i[keep], j[keep]
    if i.size == 0:
        return None
    p1, p2, p3, p4 = a[i], b[i], a[j], b[j]
    d1, d2 = _orient(p3, p4, p1), _orient(p3, p4, p2)
    d3, d4 = _orient(p1, p2, p3), _orient(p1, p2, p4)
    proper = (((d1 > eps) & (d2 < -eps)) | ((d1 < -eps) & (d2 > eps))) & \
             (((d3 > eps) & (d4 < -eps)) | ((d3 < -eps) & (d4 > eps)))

    def on_segment(p: np.ndarray, q: np.ndarray, r: np.ndarray, d: np.ndarray) -> np.ndarray:
        # r collinear with p-q and inside its bounding box
        lo, hi = np.minimum(p, q) - 1e-12 * scale, np.maximum(p, q) + 1e-12 * scale
        return (np.abs(d) <= eps) & np.all((r >= lo) & (r <= hi), axis=-1)

    touch = on_segment(p3, p4, p1, d1) | on_segment(p3, p4, p2, d2) | on_segment(p1, p2, p3, d3) | \
        on_segment(p1, p2, p4, d4)
    hit = np.flatnonzero(proper | touch)
    return (int(i[hit[0]]), int(j[hit[0]])) if hit.size else None


def validate_polygon(points: Any, what: str = 'polygon') -> np.ndarray:
    """Check and normalise a polygon: (N, 2) finite metres, >= 3 distinct vertices, non-zero area,
    not self-intersecting. Returns a float64 copy, counter-clockwise, without a repeated closing vertex.
    Raises ValueError with a message naming ``what``.
    """
    try:
        poly = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f'{what}: vertices must be numbers') from None
    if poly.size == 0:
        raise ValueError(f'{what} is empty: at least 3 vertices (x, y in metres) are needed')
    if poly.ndim != 2 or poly.shape[1] != 2:
        raise ValueError(f'{what} must be an (N, 2) array of x, y vertices in metres, got shape {poly.shape}')
    if not np.isfinite(poly).all():
        raise ValueError(f'{what} has non-finite vertices')
    # drop consecutive duplicates (including a closing vertex equal to the first)
    keep = np.any(np.abs(poly - np.roll(poly, 1, axis=0)) > 1e-12, axis=1)
    poly = poly[keep] if keep.any() else poly[:1]
    if len(poly) < 3:
        raise ValueError(f'{what} is degenerate: {len(poly)} distinct vertices, at least 3 are needed')
    scale = float(np.ptp(poly, axis=0).max())
    spread = np.linalg.svd(poly - poly.mean(axis=0), compute_uv=False)
    if scale <= 0 or spread[-1] <= 1e-9 * max(scale, 1e-12):
        raise ValueError(f'{what} is degenerate: all vertices lie on one line (zero area)')
    hit = _first_self_intersection(poly)
    if hit is not None:
        i, j = hit
        raise ValueError(f'{what} is self-intersecting: edge {i} ({poly[i].tolist()} -> '
                         f'{poly[(i + 1) % len(poly)].tolist()}) meets edge {j} ({poly[j].tolist()} -> '
                         f'{poly[(j + 1) % len(poly)].tolist()})')
    area = polygon_area(poly)
    if abs(area) < 1e-10:
        raise ValueError(f'{what} is degenerate: area {abs(area):.3g} m^2 (less than 1e-4 mm^2)')
    return poly if area > 0 else poly[::-1].copy()


def points_in_polygon(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd inside test of metric points (..., 2) against a polygon (N, 2); boolean (...)."""
    pts = np.asarray(points, dtype=np.float64)
    flat = pts.reshape(-1, 2)
    a, b = poly, np.roll(poly, -1, axis=0)
    inside = np.zeros(len(flat), dtype=bool)
    for start in range(0, len(flat), 8192):
        p = flat[start:start + 8192, None, :]
        y = p[..., 1]
        spans = (a[None, :, 1] <= y) != (b[None, :, 1] <= y)
        with np.errstate(divide='ignore', invalid='ignore'):
            xc = a[None, :, 0] + (y - a[None, :, 1]) * (b[None, :, 0] - a[None, :, 0]) / (b[None, :, 1] - a[None, :, 1])
        inside[start:start + 8192] = (np.count_nonzero(spans & (xc > p[..., 0]), axis=1) % 2) == 1
    return inside.reshape(pts.shape[:-1])


def polygon_signed_distance(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Signed distance (m) from points (..., 2) to the polygon boundary: positive outside, negative inside."""
    pts = np.asarray(points, dtype=np.float64)
    flat = pts.reshape(-1, 2)
    a = poly
    ab = np.roll(poly, -1, axis=0) - a
    len2 = np.maximum(np.sum(ab * ab, axis=1), 1e-300)
    dist = np.empty(len(flat))
    for start in range(0, len(flat), 4096):
        p = flat[start:start + 4096, None, :]
        t = np.clip(np.sum((p - a) * ab, axis=-1) / len2, 0.0, 1.0)
        d = p - (a + t[..., None] * ab)
        dist[start:start + 4096] = np.sqrt(np.min(np.sum(d * d, axis=-1), axis=1))
    inside = points_in_polygon(flat, poly)
    return np.where(inside, -dist, dist).reshape(pts.shape[:-1])


def rasterise_polygon(poly: np.ndarray, geometry: GridGeometry) -> np.ndarray:
    """Boolean (H, W) grid: cell centres inside the polygon (even-odd rule, scanline, vectorised)."""
    centers_y = geometry.origin_y + (np.arange(geometry.height) + 0.5) * geometry.resolution
    centers_x = geometry.origin_x + (np.arange(geometry.width) + 0.5) * geometry.resolution
    a, b = poly, np.roll(poly, -1, axis=0)
    y = centers_y[:, None]
    spans = (a[None, :, 1] <= y) != (b[None, :, 1] <= y)
    with np.errstate(divide='ignore', invalid='ignore'):
        xc = a[None, :, 0] + (y - a[None, :, 1]) * (b[None, :, 0] - a[None, :, 0]) / (b[None, :, 1] - a[None, :, 1])
    xc = np.sort(np.where(spans, xc, np.inf), axis=1)
    k = int(spans.sum(axis=1).max(initial=0))
    if k == 0:
        return np.zeros(geometry.shape, dtype=bool)
    xc = xc[:, :k]
    count = np.sum(xc[:, None, :] < centers_x[None, :, None], axis=2)
    return (count % 2) == 1
