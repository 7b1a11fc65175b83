"""Signed distance function of an occupancy grid (paper section III-B).

"compute an SDF using a Euclidean distance transformation of the occupancy map": the SDF
is positive outside the object, negative inside and zero on the surface, in metres.

Boundary convention (half-cell): the object is the union of the *closed squares* of its
occupied cells, so the surface runs along the cell edges between an occupied and a free
neighbour. Distances are measured between cell centres by the exact Euclidean distance
transform (:func:`scipy.ndimage.distance_transform_edt`) and shifted by half a cell:

* free cell:     f = (d(centre, nearest occupied centre) - 1/2) * resolution  >= +res/2
* occupied cell: f = -(d(centre, nearest free centre) - 1/2) * resolution    <= -res/2

so two edge-adjacent cells of opposite state read +res/2 and -res/2 and the zero level set
of any interpolation lies on the shared edge. Along the grid axes this is the exact distance
to the cell boundary; in other directions it over-estimates the distance to the staircase
boundary by at most (sqrt(2) - 1) / 2 cell, and it differs from the distance to a smooth
curve sampled by the grid by less than one cell.

Space beyond the grid counts as free (the table): the grid is padded with one free cell
before the transform, so an object touching the grid edge gets its surface on that edge.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import distance_transform_edt

OCCUPANCY_THRESHOLD = 0.5


def signed_distance(occupied: np.ndarray, resolution_m: float) -> np.ndarray:
    """SDF (m) of a 2-D occupancy grid; positive outside, negative inside (section III-B).

    Args:
        occupied: ``(H, W)`` bool grid (True = object), or a float occupancy in [0, 1] that is
            thresholded as ``occupancy >= 0.5`` (ties count as object, like missing data).
        resolution_m: cell edge length in metres (square cells).

    Returns:
        ``(H, W)`` float64 signed distances in metres with the half-cell convention of the
        module docstring (|f| >= resolution / 2 everywhere).

    Raises:
        ValueError: non-2-D input, non-positive resolution, or a grid without any object cell.
    """
    occ = np.asarray(occupied)
    if occ.ndim != 2 or occ.size == 0:
        raise ValueError(f'occupancy must be a non-empty 2-D array, got shape {occ.shape}')
    if not (np.isfinite(resolution_m) and resolution_m > 0):
        raise ValueError(f'resolution must be a positive number of metres, got {resolution_m}')
    if occ.dtype != np.bool_:
        occ_f = occ.astype(np.float64)
        if not np.all(np.isfinite(occ_f)):
            raise ValueError('occupancy contains non-finite values')
        occ = occ_f >= OCCUPANCY_THRESHOLD
    if not occ.any():
        raise ValueError('occupancy grid has no object cell: the signed distance is undefined')
    padded = np.pad(occ, 1, mode='constant', constant_values=False)
    dist_outside = distance_transform_edt(~padded)  # free cells: to the nearest occupied centre
    dist_inside = distance_transform_edt(padded)  # occupied cells: to the nearest free centre
    sdf = np.where(padded, -(dist_inside - 0.5), dist_outside - 0.5)[1:-1, 1:-1]
    return (sdf * float(resolution_m)).astype(np.float64)


def sdf_gradient(sdf_m: np.ndarray, resolution_m: float,
                 valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference gradient of a grid SDF (dimensionless), for the GPIS gradient observations.

    d f / d x at cell (i, j) is (f[i, j+1] - f[i, j-1]) / (2 resolution), d f / d y uses the rows
    (grid x runs along columns, y along rows, like :meth:`GridGeometry.cell_centers`). A
    component is defined only where the cell and both neighbours along that axis lie inside the
    grid and are ``valid`` (e.g. the training mask: a missing neighbour has no measured distance).

    Args:
        sdf_m: ``(H, W)`` signed distances (m).
        resolution_m: cell edge length (m).
        valid: ``(H, W)`` bool cells whose SDF value may be used (default: all).

    Returns:
        ``(gradient, defined)``: ``(H, W, 2)`` float64 (d f / d x, d f / d y), 0 where undefined,
        and ``(H, W, 2)`` bool, True where the component is defined.
    """
    f = np.asarray(sdf_m, dtype=np.float64)
    if f.ndim != 2:
        raise ValueError(f'sdf must be a 2-D array, got shape {f.shape}')
    if not (np.isfinite(resolution_m) and resolution_m > 0):
        raise ValueError(f'resolution must be a positive number of metres, got {resolution_m}')
    ok = np.ones(f.shape, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    if ok.shape != f.shape:
        raise ValueError(f'valid mask {ok.shape} must match the sdf {f.shape}')
    grad = np.zeros((*f.shape, 2))
    defined = np.zeros((*f.shape, 2), dtype=bool)
    defined[:, 1:-1, 0] = ok[:, 1:-1] & ok[:, :-2] & ok[:, 2:]
    defined[1:-1, :, 1] = ok[1:-1, :] & ok[:-2, :] & ok[2:, :]
    grad[:, 1:-1, 0] = (f[:, 2:] - f[:, :-2]) / (2.0 * resolution_m)
    grad[1:-1, :, 1] = (f[2:, :] - f[:-2, :]) / (2.0 * resolution_m)
    grad[~defined] = 0.0
    return grad, defined
