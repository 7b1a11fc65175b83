"""Compiled (numba) per-pixel passes that replace chains of whole-image array operations.

Each does per pixel the same IEEE operations in the same order as the array code it replaces (kept in
``test/core/sensing/test_sensing_pixel_kernels.py`` as the reference), in one pass without temporaries."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


def raster_cells(xy: np.ndarray, origin: np.ndarray, res: float, shape: tuple[int, int]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(column, row, inside) of the raster cell ``floor((xy - origin) / res)`` under each table point ``xy``
    (..., 2) (m) of a raster of ``shape`` (rows, columns); (0, 0, False) outside it or where ``xy`` is not finite."""
    pts = np.ascontiguousarray(xy, dtype=np.float64)
    lead = pts.shape[:-1]
    ix, iy, ok = _raster_cells(pts.reshape(-1, 2), float(origin[0]), float(origin[1]), float(res), int(shape[1]),
                               int(shape[0]))
    return ix.reshape(lead), iy.reshape(lead), ok.reshape(lead)


@njit(cache=True, nogil=True)
def _raster_cells(xy, o0, o1, res, nx, ny):
    n = xy.shape[0]
    ix = np.zeros(n, np.int64)
    iy = np.zeros(n, np.int64)
    ok = np.zeros(n, np.bool_)
    for k in range(n):
        a = np.floor((xy[k, 0] - o0) / res)
        b = np.floor((xy[k, 1] - o1) / res)
        if math.isfinite(a) and math.isfinite(b) and 0.0 <= a < nx and 0.0 <= b < ny:
            ix[k] = int(a)
            iy[k] = int(b)
            ok[k] = True
    return ix, iy, ok
