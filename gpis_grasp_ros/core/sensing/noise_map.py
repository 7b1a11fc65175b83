"""The SDF noise map: per-cell variance of the signed distance the GP observes, and the cells it is not trained on
(unknown: missing, extended regions where the masks disagree, foreign no-return pixels)."""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np
from numba import njit

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.sdf import signed_distance
from gpis_grasp_ros.core.sensing.params import SensingParams
from gpis_grasp_ros.core.sensing.pixel_kernels import nan_to_num
from gpis_grasp_ros.core.sensing.rasterise import Cells


def _foreign_missing_fraction(row: np.ndarray, col: np.ndarray, in_grid: np.ndarray, informative: np.ndarray,
                              foreign: np.ndarray, m: int) -> np.ndarray:
    """Per cell: share of its pixels that are no-return pixels not given to the target (``foreign``).

    Such pixels (a specular wing the segmentation split from the seen body, D of the shipped bags) are
    otherwise dropped, and the cell is then filled from its neighbours as observed table - the GPIS
    would be confidently wrong exactly where nothing was measured. Unweighted pixel counts of the
    cell's informative pixels plus the foreign ones; 0 where no pixel falls in the cell.
    """
    idx = np.where(in_grid, nan_to_num(row) * m + nan_to_num(col), -1).astype(np.int64)
    n_foreign = np.bincount(idx[in_grid & foreign], minlength=m * m)
    n_seen = np.bincount(idx[informative], minlength=m * m)
    with np.errstate(invalid='ignore', divide='ignore'):
        frac = np.where(n_foreign > 0, n_foreign / np.maximum(n_foreign + n_seen, 1), 0.0)
    return frac.reshape(m, m)


def _extended_regions(mask: np.ndarray) -> np.ndarray:
    """The 8-connected components of ``mask`` that hold a cell whose four neighbours are all in ``mask``.

    Drops thin bands (one or two cells wide): where the colour mask bleeds a pixel or two past a seen
    object's edge the masks disagree along a ring, which is edge noise, not an unseen part.
    """
    if not mask.any():
        return np.zeros_like(mask)
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    core = cv2.erode(mask.astype(np.uint8), cross, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    count, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    keep = np.zeros(count, dtype=bool)
    keep[np.unique(labels[core])] = True
    keep[0] = False
    return keep[labels]


@njit(cache=True, nogil=True)
def _squared_distances(win, feature_value, out):  # pragma: no cover - compiled
    """``out`` = squared Euclidean distance (cells, exact integers) of every cell of the boolean ``win`` to the
    nearest cell whose value is ``feature_value`` (0 on those cells): Felzenszwalb and Huttenlocher's two 1-D
    passes, the columns' distances then the lower envelope of each row's parabolas. ``win`` holds such a cell."""
    h, w = win.shape
    inf = 1e300
    g = np.empty((h, w))
    for j in range(w):  # vertical distance to the nearest feature of the column
        d = inf
        for i in range(h):
            d = 0.0 if win[i, j] == feature_value else d + 1.0
            g[i, j] = d
        d = inf
        for i in range(h - 1, -1, -1):
            d = 0.0 if win[i, j] == feature_value else d + 1.0
            if d < g[i, j]:
                g[i, j] = d
    v = np.empty(w, np.int64)
    z = np.empty(w + 1)
    f = np.empty(w)
    for i in range(h):
        k = -1
        for q in range(w):
            if g[i, q] >= inf:
                continue
            f[q] = g[i, q] * g[i, q]
            while k >= 0:
                sq = ((f[q] + q * q) - (f[v[k]] + v[k] * v[k])) / (2.0 * (q - v[k]))
                if sq <= z[k]:
                    k -= 1
                else:
                    break
            k += 1
            v[k] = q
            z[k] = -inf if k == 0 else ((f[q] + q * q) - (f[v[k - 1]] + v[k - 1] * v[k - 1])) \
                / (2.0 * (q - v[k - 1]))
            z[k + 1] = inf
        k = 0
        for q in range(w):
            while z[k + 1] < q:
                k += 1
            out[i, q] = (q - v[k]) * (q - v[k]) + f[v[k]]


@njit(cache=True, nogil=True)
def _window_sdf_kernel(win, inner, e, res, sdf):  # pragma: no cover - compiled
    """The window's signed distance into ``sdf`` (m, as :func:`~gpis_grasp_ros.core.sdf.signed_distance`); False
    where an ``inner`` cell's distance exceeds its bound ``e`` (not proven exact)."""
    h, w = win.shape
    d_out = np.empty((h, w))
    d_in = np.empty((h, w))
    _squared_distances(win, True, d_out)
    _squared_distances(win, False, d_in)
    for i in range(h):
        for j in range(w):
            if win[i, j]:
                d = math.sqrt(d_in[i, j])
                if inner[i, j] and d > e[i, j]:
                    return False
                sdf[i, j] = -(d - 0.5) * res
            else:
                d = math.sqrt(d_out[i, j])
                if inner[i, j] and d > e[i, j]:
                    return False
                sdf[i, j] = (d - 0.5) * res
    return True


def _window_sdf(padded: np.ndarray, rows: slice, cols: slice, inner: np.ndarray, res: float) -> np.ndarray | None:
    """:func:`~gpis_grasp_ros.core.sdf.signed_distance` of the one-cell-padded occupancy ``padded`` on the window
    (``rows``, ``cols``) of it, exact on the window's cells ``inner`` (bool, window-shaped), or None if not proven so.

    Each distance transform sees only the window's cells (none beyond it is a feature), so a cell's distance d_w is
    its distance to the nearest feature in the window; one outside lies at least e = the cell's axis distance to the
    first row or column beyond the window. Where d_w <= e no feature outside can be nearer, and d_w is the whole
    grid's distance - the same squared integer distance, so the same float (the compiled transform's squared
    distances are exact integers, as scipy's Euclidean transform's)."""
    win = np.ascontiguousarray(padded[rows, cols])
    if not win.any() or win.all():  # the window holds no feature of one of the two transforms
        return None
    i = np.arange(win.shape[0])[:, None]
    j = np.arange(win.shape[1])[None, :]
    h, w = padded.shape
    e = np.full(win.shape, np.inf)  # axis distance to the nearest cell beyond the window
    for beyond, axis_distance in ((rows.start > 0, i + 1.0), (rows.stop < h, win.shape[0] - i),
                                  (cols.start > 0, j + 1.0), (cols.stop < w, win.shape[1] - j)):
        if beyond:
            e = np.minimum(e, axis_distance)
    sdf = np.empty(win.shape)
    if not _window_sdf_kernel(win, np.ascontiguousarray(inner), e, float(res), sdf):
        return None
    return sdf


def _sdf_change_near(occ_bin: np.ndarray, comp: np.ndarray, near: np.ndarray, res: float) -> np.ndarray:
    """signed_distance(occ_bin | comp) - signed_distance(occ_bin & ~comp) on the cells ``near`` (0 elsewhere).

    Computed on a window around ``near`` that is widened until :func:`_window_sdf` proves both distance fields
    exact on those cells (the whole grid at worst): bit for bit the whole grid's difference there."""
    if not near.any():
        return np.zeros(occ_bin.shape)
    padded_a = np.pad(occ_bin | comp, 1, mode='constant', constant_values=False)
    padded_b = np.pad(occ_bin & ~comp, 1, mode='constant', constant_values=False)
    vs, us = np.nonzero(near)
    lo_v, hi_v, lo_u, hi_u = vs.min() + 1, vs.max() + 2, us.min() + 1, us.max() + 2  # padded coordinates
    h, w = padded_a.shape
    margin = max(4, (hi_v - lo_v + hi_u - lo_u) // 4)
    while True:
        rows = slice(max(lo_v - margin, 0), min(hi_v + margin, h))
        cols = slice(max(lo_u - margin, 0), min(hi_u + margin, w))
        inner = np.zeros((rows.stop - rows.start, cols.stop - cols.start), dtype=bool)
        inner[lo_v - rows.start:hi_v - rows.start, lo_u - cols.start:hi_u - cols.start] = \
            near[lo_v - 1:hi_v - 1, lo_u - 1:hi_u - 1]
        sdf_a = _window_sdf(padded_a, rows, cols, inner, res)
        sdf_b = None if sdf_a is None else _window_sdf(padded_b, rows, cols, inner, res)
        if sdf_b is not None:
            delta = np.zeros((h, w))
            delta[rows, cols] = np.where(inner, sdf_a - sdf_b, 0.0)
            return delta[1:-1, 1:-1]
        if rows == slice(0, h) and cols == slice(0, w):  # the whole padded grid: always exact
            raise AssertionError('the whole grid is exact by construction')  # pragma: no cover
        margin *= 2


def _propagation_variance(occ_bin: np.ndarray, uncertain: np.ndarray, train: np.ndarray, geometry: GridGeometry,
                          params: SensingParams) -> np.ndarray:
    """SDF variance (m^2) induced by uncertain cells on every cell's distance (docs/segmentation-stages.md)."""
    out = np.zeros(geometry.shape)
    if not uncertain.any():
        return out
    res = geometry.resolution
    n_local = math.pi * (params.error_correlation_length_m / res) ** 2
    count, labels = cv2.connectedComponents(uncertain.astype(np.uint8), connectivity=8)
    for c in range(1, count):
        comp = labels == c
        rest = occ_bin & ~comp
        if not rest.any():  # the component is the only object evidence: "free" would mean no object at all
            continue
        reach = cv2.distanceTransform((~comp).astype(np.uint8), cv2.DIST_L2, 5) * res
        delta = _sdf_change_near(occ_bin, comp, reach <= params.propagation_radius_m, res)
        affected = int(np.count_nonzero((np.abs(delta) > 1e-12) & train))
        n_eff = max(1.0, min(float(affected), n_local))
        out += params.alternative_weight * n_eff * delta ** 2
    return out


def prism_variance(sdf_object: np.ndarray, body: np.ndarray, alternatives: tuple[np.ndarray, ...],
                   train: np.ndarray, geometry: GridGeometry, params: SensingParams) -> np.ndarray:
    """SDF variance (m^2) of every cell from a clear body's unknown height: its prism is a prior, not a measurement.

    The body's footprint under the heights H / k, H, H x k (``alternatives``: the prism cells under the outer
    two, :func:`~gpis_grasp_ros.core.sensing.clear_body.prism_alternatives`), weighted 1/4, 1/2, 1/4 - a
    discretised prior of the height. Each cell's SDF differs between them by delta (0 where its nearest surface
    is not the body's), and its variance is E[delta^2] - E[delta]^2, times the effective number of cells that
    share the error, as in :func:`_propagation_variance` (the footprint moves as a whole: the GP must not pool
    its cells' errors away as independent). Counting every cell it changes instead (all of the grid when the
    body is the only object) made the mean shape follow the prior: G's IoU at 1 mm 0.89 -> 0.76."""
    out = np.zeros(geometry.shape)
    if not alternatives or not body.any():
        return out
    res = geometry.resolution
    base = signed_distance(sdf_object, res)
    deltas = [signed_distance((sdf_object & ~body) | alt, res) - base for alt in alternatives if alt.any()]
    if not deltas:
        return out
    weight = 0.25  # each outer height; the nominal one (delta = 0) 1/2
    mean = weight * sum(deltas)
    var = weight * sum(d ** 2 for d in deltas) - mean ** 2
    affected = int(np.count_nonzero((var > 1e-12) & train))
    n_eff = max(1.0, min(float(affected), math.pi * (params.error_correlation_length_m / res) ** 2))
    return n_eff * np.maximum(var, 0.0)


class NoiseMap(NamedTuple):
    """What the GPIS is trained on."""

    noise: np.ndarray  # (M, M) m^2, SDF observation-noise variance
    train_mask: np.ndarray  # (M, M) bool, training cells (not unknown)
    uncertain: np.ndarray  # (M, M) bool, missing, disagreeing or mostly foreign no-return cells


def noise_map(cells: Cells, missing_px: np.ndarray, target_px: np.ndarray, off_hull: np.ndarray,
              params: SensingParams) -> NoiseMap:
    """SDF noise = depth + disagreement + propagation + a clear body's height (:func:`prism_variance`).

    Unknown cells are not trained and count as object in the SDF, so the prior governs them (section III-B); a
    clear body's prism cells and the table seen through it stay trained, with the disagreement variance plus
    the variance of the prism's unknown height."""
    geometry, missing, disagreement, body, behind = (cells.geometry, cells.missing, cells.disagreement, cells.body,
                                                     cells.behind)
    disagree = disagreement > params.uncertainty_threshold
    uncertain = missing | disagree
    unknown = missing.copy()
    foreign = _foreign_missing_fraction(cells.row, cells.col, cells.in_grid, cells.informative,
                                        missing_px & ~target_px & ~off_hull, geometry.width
                                        ) > params.missing_cell_fraction
    uncertain |= foreign
    # a clear body's prism and another object in contact: table or object by a prior or a split, trained
    trained_prior = behind | (body & params.train_clear_body) | cells.contact
    unknown |= foreign | (_extended_regions(disagree) & ~trained_prior)
    noise = (cells.depth_var + params.disagreement_variance_m2 * disagreement
             + params.disagreement_variance_m2 * np.where(missing, 0.0, cells.miss_c))
    occ_bin = cells.occupancy >= 0.5
    if not occ_bin.any():
        raise ValueError('no object found: the target evidence is too weak for any grid cell to be occupied '
                         '(coarser cells or lower thresholds)')
    noise = np.where(cells.observed, noise, params.unobserved_variance_m2)
    train_mask = ~unknown
    sdf_object = occ_bin | ~train_mask  # what the GPIS's SDF treats as object (pipeline.publishable_grids)
    noise = noise + _propagation_variance(sdf_object, uncertain & ~(body | behind), train_mask, geometry, params)
    noise = noise + prism_variance(sdf_object, body, cells.body_alternatives, train_mask, geometry, params)
    noise = np.where(train_mask, noise, np.maximum(noise, params.disagreement_variance_m2))  # unused by the GP
    return NoiseMap(noise, train_mask, uncertain)
