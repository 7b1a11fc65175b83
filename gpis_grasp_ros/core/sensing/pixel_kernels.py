"""Per-pixel passes that replace slower whole-image array operations: compiled (numba) loops and array helpers.

Each does per pixel the same IEEE operations in the same order as the array code it replaces (kept in the tests
``test/core/sensing/test_sensing_pixel_kernels.py`` and ``test_sensing_compiled_morphology.py`` as the reference),
in one pass without temporaries or without numpy's strided reduction of a short last axis."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


def vector_norm(x: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(x, axis=-1)`` of a float array ``(..., k)``, k small: numpy reduces a short axis left to
    right (``sqrt((x0 x0 + x1 x1) + x2 x2)``, its initial zero adding nothing), as this does per component."""
    return norm_of([x[..., k] for k in range(x.shape[-1])])


def norm_of(components: list[np.ndarray]) -> np.ndarray:
    """:func:`vector_norm` of the vectors whose components are given (``x - y`` as ``[x[..., k] - y[k], ...]``:
    the same differences, without the (..., k) array)."""
    total = components[0] * components[0]
    for c in components[1:]:
        total = total + c * c
    return np.sqrt(total)


def masked_rows(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``x[mask]`` of an (H, W, k) array and an (H, W) mask: the same rows in the same order, gathered in one pass."""
    rows = np.ascontiguousarray(x).reshape(-1, x.shape[-1])
    flat = np.ascontiguousarray(mask, dtype=bool).ravel()
    out = np.empty((int(np.count_nonzero(flat)), rows.shape[1]), dtype=x.dtype)
    _masked_rows(rows, flat, out)
    return out


@njit(cache=True, nogil=True)
def _masked_rows(rows, flat, out):
    j = 0
    for i in range(flat.size):
        if flat[i]:
            for c in range(rows.shape[1]):
                out[j, c] = rows[i, c]
            j += 1


def nan_to_num(x: np.ndarray, nan: float = 0.0) -> np.ndarray:
    """``np.nan_to_num(x, nan=nan)`` of a float array (NaN -> ``nan``, +-inf -> +-the largest float) in one pass."""
    x = np.asarray(x)
    if x.dtype not in (np.float64, np.float32):
        return np.nan_to_num(x, nan=nan)
    src = np.ascontiguousarray(x)
    out = np.empty(src.shape, dtype=x.dtype)
    big = np.finfo(x.dtype).max
    _nan_to_num(src.reshape(-1), x.dtype.type(nan), big, -big, out.reshape(-1))
    return out[()] if out.ndim == 0 else out


@njit(cache=True, nogil=True)
def _nan_to_num(x, nan, big, small, out):
    for k in range(x.size):
        v = x[k]
        if math.isnan(v):
            v = nan
        elif math.isinf(v):
            v = big if v > 0 else small
        out[k] = v


def mask_bounds(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(first row, last row, first column, last column) of the True pixels of an (H, W) mask: the extremes of
    ``np.nonzero(mask)``, from the rows and columns that hold one; ValueError (as their ``min``) when there is none."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        raise ValueError('zero-size array to reduction operation minimum which has no identity')
    cols = np.flatnonzero(mask.any(axis=0))
    return int(rows[0]), int(rows[-1]), int(cols[0]), int(cols[-1])


def has_label(labels: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """``np.isin(labels, wanted)`` of non-negative integer labels, by a lookup table over the labels."""
    wanted = np.asarray(wanted)
    if labels.size == 0 or wanted.size == 0:
        return np.zeros(labels.shape, dtype=bool)
    lut = np.zeros(max(int(labels.max()), int(wanted.max())) + 1, dtype=bool)
    lut[wanted[wanted >= 0]] = True
    return lut[labels]


def all_finite(x: np.ndarray) -> np.ndarray:
    """``np.isfinite(x).all(axis=-1)``, per component of the last axis."""
    out = np.isfinite(x[..., 0])
    for k in range(1, x.shape[-1]):
        out &= np.isfinite(x[..., k])
    return out


def raster_cells(xy: np.ndarray, origin: np.ndarray, res: float, shape: tuple[int, int],
                 first: tuple[int, int] = (0, 0)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(column, row, inside) of the raster cell ``floor((xy - origin) / res) - first`` under each table point
    ``xy`` (..., 2) (m) of a raster of ``shape`` (rows, columns) whose first cell is ``first`` (column, row) of the
    lattice from ``origin``; (0, 0, False) outside it or where ``xy`` is not finite."""
    pts = np.ascontiguousarray(xy, dtype=np.float64)
    lead = pts.shape[:-1]
    ix, iy, ok = _raster_cells(pts.reshape(-1, 2), float(origin[0]), float(origin[1]), float(res), int(shape[1]),
                               int(shape[0]), float(first[0]), float(first[1]))
    return ix.reshape(lead), iy.reshape(lead), ok.reshape(lead)


@njit(cache=True, nogil=True)
def _raster_cells(xy, o0, o1, res, nx, ny, first_x, first_y):
    n = xy.shape[0]
    ix = np.zeros(n, np.int64)
    iy = np.zeros(n, np.int64)
    ok = np.zeros(n, np.bool_)
    for k in range(n):
        a = np.floor((xy[k, 0] - o0) / res) - first_x
        b = np.floor((xy[k, 1] - o1) / res) - first_y
        if math.isfinite(a) and math.isfinite(b) and 0.0 <= a < nx and 0.0 <= b < ny:
            ix[k] = int(a)
            iy[k] = int(b)
            ok[k] = True
    return ix, iy, ok


def pixel_feet(rays, ray_dot, points, height, h_missing, valid, hit, normal, offset) -> np.ndarray:
    """(H, W, 3) camera-frame feet of the pixels (``place_feet``): ``points - nan_to_num(height) normal`` where
    ``valid``; elsewhere the ray's point ``h_missing`` above the plane dropped onto it, ``rays t - h_missing normal``
    with ``t = (h_missing - offset) / ray_dot`` where the ray hits the plane (``hit``), NaN where it does not."""
    out = np.empty(points.shape)
    _pixel_feet(np.ascontiguousarray(rays).reshape(-1, 3), np.ascontiguousarray(ray_dot).ravel(),
                np.ascontiguousarray(points).reshape(-1, 3), np.ascontiguousarray(height).ravel(),
                np.ascontiguousarray(h_missing, dtype=np.float64).ravel(), np.ascontiguousarray(valid).ravel(),
                np.ascontiguousarray(hit).ravel(), np.ascontiguousarray(normal, dtype=np.float64), float(offset),
                out.reshape(-1, 3))
    return out


@njit(cache=True, nogil=True, error_model='numpy')
def _pixel_feet(rays, ray_dot, points, height, h_missing, valid, hit, normal, offset, out):
    big = np.finfo(np.float64).max
    for k in range(out.shape[0]):
        if valid[k]:
            h = height[k]  # np.nan_to_num
            if math.isnan(h):
                h = 0.0
            elif math.isinf(h):
                h = big if h > 0 else -big
            for c in range(3):
                out[k, c] = points[k, c] - h * normal[c]
        else:
            hm = h_missing[k]
            t = (hm - offset) / ray_dot[k] if hit[k] else np.nan
            for c in range(3):
                out[k, c] = rays[k, c] * t - hm * normal[c]


def ray_cosine(rays: np.ndarray, ray_dot: np.ndarray) -> np.ndarray:
    """``np.maximum(np.abs(ray_dot) / vector_norm(rays), 1e-3)`` of rays (..., 3) and their dot products with a
    unit normal (...,) in one pass (NaN kept)."""
    src = np.ascontiguousarray(rays, dtype=np.float64)
    out = np.empty(src.shape[:-1])
    _ray_cosine(src.reshape(-1, 3), np.ascontiguousarray(ray_dot, dtype=np.float64).reshape(-1), out.reshape(-1))
    return out


@njit(cache=True, nogil=True)
def _ray_cosine(rays, dot, out):
    for k in range(dot.size):
        total = rays[k, 0] * rays[k, 0]
        total = total + rays[k, 1] * rays[k, 1]
        total = total + rays[k, 2] * rays[k, 2]
        c = abs(dot[k]) / math.sqrt(total)
        out[k] = c if (c >= 1e-3 or c != c) else 1e-3  # np.maximum


def max_tangent(cos: np.ndarray) -> float:
    """``np.nanmax(sqrt(max(1 - cos^2, 0)) / cos)``: the largest tangent of the angles whose cosines are ``cos``
    (NaN ones ignored)."""
    return float(_max_tangent(np.ascontiguousarray(cos, dtype=np.float64).ravel()))


@njit(cache=True, nogil=True, error_model='numpy')
def _max_tangent(cos):
    best = np.nan
    for k in range(cos.size):
        c = cos[k]
        s = 1.0 - c * c
        if not s >= 0.0 and not math.isnan(s):  # np.maximum(s, 0.0), NaN kept
            s = 0.0
        t = math.sqrt(s) / c
        if not math.isnan(t) and (math.isnan(best) or t > best):
            best = t
    return best


def nearer_difference_area(xy: np.ndarray) -> np.ndarray:
    """``|a_x b_y - a_y b_x|`` per pixel of the feet ``xy`` (H, W, 2): a and b their one-sided differences along the
    image columns and rows towards the neighbour whose foot is nearer (``np.diff`` padded with NaN on either side,
    the squared lengths ``nan_to_num(.., nan=inf)`` compared with ``<=``, the backward one kept on a tie)."""
    src = np.ascontiguousarray(xy, dtype=np.float64)
    out = np.empty(src.shape[:2])
    _nearer_difference_area(src, np.finfo(np.float64).max, out)
    return out


@njit(cache=True, nogil=True, inline='always')
def _squared_or_inf(x, y, big):
    s = x * x + y * y
    if math.isnan(s):
        return np.inf
    if math.isinf(s):
        return big
    return s


@njit(cache=True, nogil=True, inline='always')
def _nearer(x0, y0, x1, y1, big):
    """The backward difference (x0, y0) or the forward one (x1, y1), whichever is nearer (backward on a tie)."""
    if _squared_or_inf(x0, y0, big) <= _squared_or_inf(x1, y1, big):
        return x0, y0
    return x1, y1


@njit(cache=True, nogil=True)
def _nearer_difference_area(xy, big, out):
    rows, cols = out.shape
    for r in range(rows):
        for c in range(cols):
            bx = xy[r, c, 0] - xy[r, c - 1, 0] if c > 0 else np.nan
            by = xy[r, c, 1] - xy[r, c - 1, 1] if c > 0 else np.nan
            fx = xy[r, c + 1, 0] - xy[r, c, 0] if c < cols - 1 else np.nan
            fy = xy[r, c + 1, 1] - xy[r, c, 1] if c < cols - 1 else np.nan
            ax, ay = _nearer(bx, by, fx, fy, big)
            bx = xy[r, c, 0] - xy[r - 1, c, 0] if r > 0 else np.nan
            by = xy[r, c, 1] - xy[r - 1, c, 1] if r > 0 else np.nan
            fx = xy[r + 1, c, 0] - xy[r, c, 0] if r < rows - 1 else np.nan
            fy = xy[r + 1, c, 1] - xy[r, c, 1] if r < rows - 1 else np.nan
            vx, vy = _nearer(bx, by, fx, fy, big)
            out[r, c] = abs(ax * vy - ay * vx)


def distinct_cells_per_label(labels: np.ndarray, cells: np.ndarray, n_cells: int, n_labels: int) -> np.ndarray:
    """Per label, the number of distinct ``cells`` (0 .. n_cells - 1) its entries hold: ``np.bincount`` of the
    labels of ``np.unique(labels * n_cells + cells)`` (minlength ``n_labels``), labels and cells non-negative."""
    labels = np.ascontiguousarray(labels, dtype=np.int64).ravel()
    cells = np.ascontiguousarray(cells, dtype=np.int64).ravel()
    size = max(n_labels, int(labels.max()) + 1 if labels.size else 0)
    count = np.zeros(size, np.int64)
    if not _distinct_cells(labels, cells, np.zeros(n_cells, np.int64), count):  # a cell shared by two labels
        keys = np.unique(labels * n_cells + cells)
        count = np.bincount(keys // n_cells, minlength=n_labels)
    return count


@njit(cache=True, nogil=True)
def _distinct_cells(labels, cells, owner, count):
    """Counts into ``count`` while every cell holds one label (``owner``: label + 1 of each cell); False if not."""
    for k in range(labels.size):
        c = cells[k]
        if owner[c] == 0:
            owner[c] = labels[k] + 1
            count[labels[k]] += 1
        elif owner[c] != labels[k] + 1:
            return False
    return True


def feet_box(xy: np.ndarray) -> tuple[float, float, float, float]:
    """(x_min, y_min, x_max, y_max) of the points ``xy`` (..., 2) whose coordinates are both finite (infinities
    when there are none)."""
    return _feet_box(np.ascontiguousarray(xy, dtype=np.float64).reshape(-1, 2))


@njit(cache=True, nogil=True)
def _feet_box(xy):
    x0 = y0 = np.inf
    x1 = y1 = -np.inf
    for k in range(xy.shape[0]):
        x, y = xy[k, 0], xy[k, 1]
        if math.isfinite(x) and math.isfinite(y):
            x0, x1 = min(x0, x), max(x1, x)
            y0, y1 = min(y0, y), max(y1, y)
    return x0, y0, x1, y1
