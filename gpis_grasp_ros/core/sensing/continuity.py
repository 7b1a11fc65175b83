"""Objects are connected solids: 3D continuity of the depth-seen surface, and the height that is surely solid.

Two neighbouring pixels see one continuous surface when their depths differ by no more than that surface
can change between two rays one pixel apart, plus the sensor's noise. A surface seen at incidence phi (angle
between the ray and its normal) changes depth by z tan(phi) / f per pixel, and a sensor returns no depth beyond
a grazing incidence (``GRAZING_DEG``), so a larger step is a discontinuity: an occluding edge, or one object
standing against another of a different height. A tool whose parts stand at different heights is joined by
the sloping surfaces between them and stays one piece.

A pixel is *solid* when its height exceeds what the table's own noise reaches: ``SOLID_SIGMAS`` times the
table inliers' measured residual, scaled to the pixel's range by the sensor model. Evidence below it (depth
noise, a flat print on the table seen only in colour) is not an object.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.special import ndtri

from gpis_grasp_ros.core.noise_model import SensorModel

#: Incidence (degrees from the surface normal) beyond which a depth sensor returns nothing (stereo matching and
#: structured light both fail on grazing surfaces).
GRAZING_DEG = 80.0
#: One-sided false-alarm probability per independent depth sample of a pixel being taken as solid above a flat
#: table (3.1 sigma).
SOLID_FALSE_ALARM = 1e-3
SOLID_SIGMAS = float(-ndtri(SOLID_FALSE_ALARM))
#: Sigmas of the noise of the depth difference of two neighbouring pixels allowed on a continuous surface.
CONTINUITY_SIGMAS = 3.0


def solid_height(z: np.ndarray, table_residual: np.ndarray, table_z: np.ndarray, sensor: SensorModel,
                 floor_m: float) -> np.ndarray:
    """Per-pixel height (m) above which depth-seen evidence is surely solid, at depths ``z`` (m).

    ``table_residual``, ``table_z``: heights (m) and depths (m) of the table plane's inliers. Their RMS residual,
    relative to the sensor model's sigma at their depths, scales the model to the pixel's depth (a filtered
    depth image is less noisy than the raw sensor, a rough table more). At least ``floor_m``."""
    res = np.asarray(table_residual, dtype=np.float64)
    if res.size == 0:
        return np.full(np.shape(z), floor_m)
    model = sensor.sigma(np.asarray(table_z, dtype=np.float64))
    ratio = math.sqrt(float(np.mean(res ** 2)) / max(float(np.mean(model ** 2)), 1e-18))
    return np.maximum(floor_m, SOLID_SIGMAS * ratio * sensor.sigma(np.asarray(z, dtype=np.float64)))


def max_depth_step(z: np.ndarray, var_z: np.ndarray, focal_px: float) -> np.ndarray:
    """Largest depth step (m) between a pixel and its neighbour on one continuous surface, at depth ``z``."""
    return z * math.tan(math.radians(GRAZING_DEG)) / focal_px + CONTINUITY_SIGMAS * np.sqrt(2.0 * var_z)


def surface_pieces(z: np.ndarray, seen: np.ndarray, var_z: np.ndarray, focal_px: float) -> np.ndarray:
    """Label the ``seen`` pixels by 3D continuity (4-neighbours whose depth step a continuous surface allows).

    ``z`` (m), ``var_z`` (m^2, variance of the depth). Returns (H, W) int labels, 0 = not seen, 1.. pieces."""
    h, w = seen.shape
    step = max_depth_step(np.nan_to_num(z), np.nan_to_num(var_z), focal_px)
    idx = np.arange(h * w).reshape(h, w)
    rows, cols = [], []
    for a, b in ((np.s_[:, :-1], np.s_[:, 1:]), (np.s_[:-1, :], np.s_[1:, :])):
        ok = seen[a] & seen[b] & (np.abs(np.nan_to_num(z[a]) - np.nan_to_num(z[b])) <= np.minimum(step[a], step[b]))
        rows.append(idx[a][ok])
        cols.append(idx[b][ok])
    r, c = np.concatenate(rows), np.concatenate(cols)
    _, lab = connected_components(coo_matrix((np.ones(r.size), (r, c)), shape=(h * w, h * w)), directed=False)
    lab = lab.reshape(h, w)
    # renumber the seen pieces 1..n
    uniq, inv = np.unique(lab[seen], return_inverse=True)
    out = np.zeros((h, w), np.int64)
    out[seen] = inv + 1
    return out
