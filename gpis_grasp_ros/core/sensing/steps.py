"""Touching objects split where their surfaces are discontinuous in height (a step no continuous surface makes).

Two neighbouring raster cells lie on one continuous surface when their mean heights above the table differ by
no more than the sensor's noise can explain (``STEP_SIGMAS`` x the noise of the difference) plus the rise of a
surface of slope ``STEP_SLOPE_DEG`` over one cell; a cell no higher than that above the table is continuous with
the table itself. Cells above that, joined by such edges, form *patches*; a patch that holds a square jaw face
(``min_width_m``, the side of the minimum object) and the minimum object area is a *core*. A component with two
or more cores is split where two of them meet only through a step with the lower one flat (a box beside a taller
box), or only down at the table (a valley: two objects lying side by side), and not through slivers (walls,
steep flanks, noise) narrower than a jaw face: every cell goes to the core it is deepest in
(:func:`split_height_steps`)."""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np
from numba import njit
from scipy.special import ndtri

from gpis_grasp_ros.core.sensing.morphology import _flood, _nearest_label, grid_components
from gpis_grasp_ros.core.sensing.params import CHROMA_CLEAR_FRACTION, FLAT_JUMP_M, STEP_FALSE_ALARM, STEP_SLOPE_DEG
from gpis_grasp_ros.core.sensing.pixel_kernels import nan_to_num

#: Sigmas of the noise of a height difference that one continuous surface exceeds with STEP_FALSE_ALARM (two-sided).
STEP_SIGMAS = float(-ndtri(STEP_FALSE_ALARM / 2))


class CellHeights(NamedTuple):
    """What the pixels in each table-raster cell say about its height (NaN where no pixel is seen in depth)."""

    mean: np.ndarray  # m, mean height of its depth-seen pixels
    sigma: np.ndarray  # m, RMS of their height noise (the sensor model)
    spread: np.ndarray  # m, max - min of their heights
    depth_px: np.ndarray  # its evidence pixels seen in depth
    evidence_px: np.ndarray  # all its evidence pixels
    blind: np.ndarray  # bool, holds pixels without a return and none seen in depth


def cell_heights(iy: np.ndarray, ix: np.ndarray, evidence: np.ndarray, height: np.ndarray, sigma: np.ndarray,
                 missing: np.ndarray, shape: tuple[int, int]) -> CellHeights:
    """:class:`CellHeights` of the ``evidence`` pixels whose cell is (``iy``, ``ix``); a pixel is seen in depth
    where ``height`` is finite, ``missing`` where it has no return."""
    ny, nx = shape
    size = nx * ny
    count, total, total_s2, hi, lo, n_evidence, blind_any = _cell_sums(
        np.ascontiguousarray(iy, dtype=np.int64).ravel(), np.ascontiguousarray(ix, dtype=np.int64).ravel(),
        np.ascontiguousarray(evidence, dtype=bool).ravel(), np.ascontiguousarray(height, dtype=np.float64).ravel(),
        np.ascontiguousarray(sigma, dtype=np.float64).ravel(), np.ascontiguousarray(missing, dtype=bool).ravel(),
        nx, size)
    with np.errstate(invalid='ignore', divide='ignore'):
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
        rms = np.sqrt(np.where(count > 0, total_s2 / np.maximum(count, 1), np.nan))
    blind = blind_any & (count == 0)
    return CellHeights(mean.reshape(shape), rms.reshape(shape), np.where(count > 0, hi - lo, np.nan).reshape(shape),
                       count.reshape(shape), n_evidence.reshape(shape), blind.reshape(shape))


@njit(cache=True, nogil=True)
def _cell_sums(iy, ix, evidence, height, sigma, missing, nx, size):
    """Per cell, in pixel order (``np.bincount``'s sums, ``np.maximum.at`` / ``np.minimum.at``): the evidence
    pixels seen in depth (finite height, not missing), the sums of their heights and squared sigmas, their
    largest and smallest height; all the evidence pixels, and whether any of them is missing."""
    count = np.zeros(size, np.int64)
    total = np.zeros(size)
    total_s2 = np.zeros(size)
    hi = np.full(size, -np.inf)
    lo = np.full(size, np.inf)
    n_evidence = np.zeros(size, np.int64)
    blind_any = np.zeros(size, np.bool_)
    for p in range(evidence.size):
        if not evidence[p]:
            continue
        k = iy[p] * nx + ix[p]
        n_evidence[k] += 1
        if missing[p]:
            blind_any[k] = True
            continue
        h = height[p]
        if not np.isfinite(h):
            continue
        count[k] += 1
        total[k] += h
        total_s2[k] += sigma[p] * sigma[p]
        if h > hi[k]:  # np.maximum keeps the value it has on a tie (and signed zeros)
            hi[k] = h
        if h < lo[k]:
            lo[k] = h
    return count, total, total_s2, hi, lo, n_evidence, blind_any


def step_limit(sigma_a: np.ndarray, sigma_b: np.ndarray, res: float) -> np.ndarray:
    """Largest height difference (m) of two neighbouring cells ``res`` apart on one continuous surface: the noise
    of the difference of their heights (sigmas ``sigma_a``, ``sigma_b``, m) times ``STEP_SIGMAS``, plus the rise of
    a ``STEP_SLOPE_DEG`` slope over one cell."""
    return STEP_SIGMAS * np.hypot(sigma_a, sigma_b) + res * math.tan(math.radians(STEP_SLOPE_DEG))


def surface_patches(labels: np.ndarray, cells: CellHeights, res: float) -> np.ndarray:
    """Patch id (1..) of every *coherent* depth-seen cell of a component (0 elsewhere): cells whose pixels' heights
    span at most :func:`step_limit` (one surface sampled; a cell across a wall, a flying pixel or a clear body's
    blend of surface and table seen through is not), joined through 4-neighbours of the same label whose heights
    differ by at most :func:`step_limit`."""
    s = nan_to_num(cells.sigma)
    h = nan_to_num(cells.mean)
    limit = step_limit(s, s, res)
    seen = np.isfinite(cells.mean) & (labels > 0) & (nan_to_num(cells.spread, nan=np.inf) <= limit) & (h > limit)
    edges = [seen[a] & seen[b] & (labels[a] == labels[b]) & (np.abs(h[a] - h[b]) <= step_limit(s[a], s[b], res))
             for a, b in ((np.s_[:, :-1], np.s_[:, 1:]), (np.s_[:-1, :], np.s_[1:, :]))]
    return np.where(seen, grid_components(*edges) + 1, 0)


def split_height_steps(labels: np.ndarray, cells: CellHeights, res: float, min_width_m: float, min_area_m2: float,
                       origin: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Split the components of ``labels`` whose cores meet only through a valley or a step (module docstring).

    A core is measured surface standing on the table: a patch (:func:`surface_patches`: cells a step above the
    table; its cells without a coherent height - unseen, or spanning a step - added from the nearest coherent
    cell of the same component) that holds a disc of diameter ``min_width_m``, has ``min_area_m2`` of coherent
    cells, is mostly seen in depth (at least half of its cells coherent, ``CHROMA_CLEAR_FRACTION`` of its pixels:
    a clear body's scattered returns and its table seen through are no surface to tell it by) and whose median
    height is a step above the table (:func:`step_limit`). The cells are flooded from the cores
    (:func:`~.morphology._flood`); two parts stay one unless their common boundary is mostly measured and either
    a valley or a step with the lower part flat (:func:`_join_parts`). The first part of a component keeps its
    label, the others get fresh labels; returns the labels and the origin of every label (parts of one component
    are not joined again through holes, see :func:`~.objects.split_touching`)."""
    n = int(labels.max()) + 1
    origin = np.arange(n) if origin is None else np.asarray(origin)
    out = labels.astype(np.int32).copy()
    patch = surface_patches(labels, cells, res) if n > 1 else np.zeros(labels.shape, np.int64)
    if not patch.any():
        return out, origin
    origin = list(origin)
    near, _ = _nearest_label(patch)  # the patch of each cell's nearest coherent cell
    n_patch = int(patch.max()) + 1
    patch_label = np.zeros(n_patch, np.int64)
    patch_label[patch.ravel()] = labels.ravel()
    filled = np.where((labels > 0) & (patch_label[near] == labels), near, 0)  # ... if it is of the same component
    pad = np.pad(filled, 1)
    edge = np.zeros(filled.shape, bool)
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        edge |= pad[1 + dy:pad.shape[0] - 1 + dy, 1 + dx:pad.shape[1] - 1 + dx] != filled
    inner = cv2.distanceTransform(np.pad((~edge & (filled > 0)).astype(np.uint8), 1), cv2.DIST_L2, 5)[1:-1, 1:-1]
    # a disc of diameter min_width_m: its centre at least its radius from the boundary cells (which are at 0)
    depth = _group_max(filled.ravel(), inner.ravel(), n_patch)
    n_cells = np.bincount(filled.ravel(), minlength=n_patch)
    measured = np.bincount(patch.ravel(), minlength=n_patch)
    depth_px = np.bincount(filled.ravel(), weights=cells.depth_px.ravel(), minlength=n_patch)
    evidence_px = np.bincount(filled.ravel(), weights=cells.evidence_px.ravel(), minlength=n_patch)
    height = np.zeros(n_patch)
    sigma = np.zeros(n_patch)
    span = np.zeros(n_patch)
    coherent = patch > 0
    order = np.argsort(patch[coherent], kind='stable')
    ids_sorted, h_sorted = patch[coherent][order], cells.mean[coherent][order]
    s_sorted = cells.sigma[coherent][order]
    bounds = np.searchsorted(ids_sorted, np.arange(n_patch + 1))
    core = (depth >= max(0.5 * min_width_m / res - 0.5, 0.5)) & (measured * res ** 2 >= min_area_m2) \
        & (2 * measured >= n_cells) & (depth_px >= CHROMA_CLEAR_FRACTION * evidence_px)
    for i in np.nonzero(core[1:] & (measured[1:] > 0))[0] + 1:  # the heights of the patches that may be cores
        lo, height[i], hi = np.percentile(h_sorted[bounds[i]:bounds[i + 1]], [5.0, 50.0, 95.0])
        span[i] = hi - lo
        sigma[i] = np.median(s_sorted[bounds[i]:bounds[i + 1]])
    core &= height > step_limit(sigma, sigma, res)
    core[0] = False
    cores_of = np.bincount(patch_label[core], minlength=n)
    dist = cv2.distanceTransform(np.pad((labels > 0).astype(np.uint8), 1), cv2.DIST_L2, 5)[1:-1, 1:-1]
    s = nan_to_num(cells.sigma)
    limit = step_limit(s, s, res)
    ground = np.isfinite(cells.mean) & (cells.mean <= limit)  # continuous with the table
    for lab in np.nonzero(cores_of >= 2)[0]:
        comp = labels == lab
        ids = np.nonzero(core & (patch_label == lab))[0]
        rank = np.zeros(n_patch, np.int32)
        rank[ids] = np.arange(1, ids.size + 1)
        parts = _join_parts(_flood(np.where(comp, rank[filled], 0).astype(np.int32), dist, comp), patch,
                            np.isfinite(cells.mean), ground, cells.blind, height[ids], span[ids] <= FLAT_JUMP_M,
                            nan_to_num(cells.mean) + limit)
        for part in np.unique(parts[comp & (parts > 0)])[1:]:
            out[comp & (parts == part)] = len(origin)
            origin.append(int(origin[lab]))
    return out, np.asarray(origin)


@njit(cache=True, nogil=True)
def _group_max(keys: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Largest of ``values`` per key 0..n-1 (0 for a key without a value): ``np.maximum.at`` on zeros."""
    out = np.zeros(n)
    for k in range(keys.size):
        if values[k] > out[keys[k]]:
            out[keys[k]] = values[k]
    return out


def _join_parts(parts: np.ndarray, patch: np.ndarray, seen: np.ndarray, ground: np.ndarray, blind: np.ndarray,
                height: np.ndarray, flat: np.ndarray, step_up: np.ndarray) -> np.ndarray:
    """``parts`` (1..n, 0 = none; core ``k`` of median ``height[k - 1]``, ``flat`` or not) with neighbouring parts
    joined unless their common boundary is mostly measured and either a valley or a step with the lower part flat.

    Of the 4-neighbour cell pairs across the boundary: a *valley* pair holds a cell continuous with the table
    (``ground``) that both parts stand a step above (``step_up``, the cell's height plus :func:`step_limit`); a
    *step* pair holds depth-seen cells in different patches above the table (a step, or a cell whose pixels span
    one); an *open* pair holds a cell without a return (a clear body's parts are separated by its no-return cells)
    or a ground cell not a step below both parts (a surface at the table's noise level). Measured: valley + step
    pairs at least the open ones. Flat lower part (5th to 95th percentile of its heights within ``FLAT_JUMP_M``, as
    a flat support in :func:`~.objects.split_flat_support`): a box's top beside a taller box is another object,
    while a lying cylinder's crest beside its taller end cap (a flashlight's head) is not flat and stays with it."""
    n_parts = height.size
    step = np.zeros((n_parts + 1, n_parts + 1))
    unseen = np.zeros((n_parts + 1, n_parts + 1))
    valley = np.zeros((n_parts + 1, n_parts + 1))
    for a, b in ((np.s_[:, :-1], np.s_[:, 1:]), (np.s_[:-1, :], np.s_[1:, :])):
        pa, pb = parts[a], parts[b]
        cross = (pa > 0) & (pb > 0) & (pa != pb)
        both = seen[a] & seen[b]
        low = cross & (ground[a] | ground[b])
        # a valley: a cell continuous with the table, both parts a step higher than it
        deep = np.minimum(height[np.maximum(pa, 1) - 1], height[np.maximum(pb, 1) - 1]) \
            > np.where(ground[a], step_up[a], -np.inf).clip(min=np.where(ground[b], step_up[b], -np.inf))
        is_valley = low & deep
        is_step = cross & both & ~low & ((patch[a] != patch[b]) | (patch[a] == 0))
        is_blind = cross & ((blind[a] | blind[b]) | (low & ~deep))
        np.add.at(step, (pa[is_step], pb[is_step]), 1.0)
        np.add.at(valley, (pa[is_valley], pb[is_valley]), 1.0)
        np.add.at(unseen, (pa[is_blind], pb[is_blind]), 1.0)
    step, valley, unseen = step + step.T, valley + valley.T, unseen + unseen.T
    root = np.arange(n_parts + 1)

    def find(i: int) -> int:
        while root[i] != i:
            root[i] = root[root[i]]
            i = root[i]
        return i

    for i, j in zip(*np.nonzero(np.triu((step + valley + unseen) > 0, 1)), strict=True):
        lower = i if height[i - 1] <= height[j - 1] else j
        measured = step[i, j] + valley[i, j] >= max(unseen[i, j], 1.0)
        if not measured or not (valley[i, j] >= step[i, j] or flat[lower - 1]):
            root[find(int(j))] = find(int(i))
    return np.array([find(i) for i in range(n_parts + 1)])[parts]
