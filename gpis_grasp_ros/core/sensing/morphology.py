"""Image and raster morphology shared by the stages: nearest pixels, hole filling, reconstruction, flooding, and the
components of a raster's 4-neighbour graph."""

from __future__ import annotations

import cv2
import numpy as np
from numba import njit

from gpis_grasp_ros.core.sensing.pixel_kernels import mask_bounds


def nearest_pixel(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel (or raster cell) of ``mask`` (H x W bool, at least one True): the distance to the nearest
    True pixel (float32, pixels; 0 on them) and that pixel's (row, column) (H x W x 2 int)."""
    dist, nearest_at = nearest_pixel_lookup(mask)
    return dist, nearest_at(...)


def box_max_at(image: np.ndarray, rows: np.ndarray, cols: np.ndarray, k: int) -> np.ndarray:
    """The maximum of ``image`` (H x W, float32) over the k x k window (odd ``k``) around each pixel (``rows``,
    ``cols``): ``cv2.dilate`` with a k x k rectangle read at those pixels, the dilation computed on the box that holds
    their windows only (the image beyond it is in none of them; at the image's edge the dilation's border applies
    as on the whole image)."""
    if rows.size == 0:
        return np.zeros(0, dtype=image.dtype)
    r0, r1 = max(int(rows.min()) - k // 2, 0), min(int(rows.max()) + k // 2 + 1, image.shape[0])
    c0, c1 = max(int(cols.min()) - k // 2, 0), min(int(cols.max()) + k // 2 + 1, image.shape[1])
    box = cv2.dilate(np.ascontiguousarray(image[r0:r1, c0:c1]), cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
    return box[rows - r0, cols - c0]


def nearest_pixel_lookup(mask: np.ndarray):
    """:func:`nearest_pixel`'s distances, and a function giving the (row, column) of the nearest True pixel at the
    pixels an index selects (``nearest_at((vs, us))`` = ``nearest[vs, us]``) without the whole H x W x 2 array."""
    m = np.asarray(mask, dtype=bool)
    dist, nearest = cv2.distanceTransformWithLabels((~m).astype(np.uint8), cv2.DIST_L2, 5,
                                                    labelType=cv2.DIST_LABEL_PIXEL)
    seen = np.flatnonzero(m)  # in the (row-major) order of OpenCV's pixel labels

    def nearest_at(index) -> np.ndarray:
        flat = seen[np.clip(nearest[index] - 1, 0, len(seen) - 1)]
        return np.stack(np.divmod(flat, m.shape[1]), axis=-1)  # np.argwhere's rows

    return dist, nearest_at


def _nearest_label(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For every raster cell: the label of the nearest labelled cell and the distance to it (cells)."""
    dist, near = nearest_pixel(labels > 0)
    return labels[near[..., 0], near[..., 1]], dist


def _reconstruct(marker: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Grey-level morphological reconstruction by dilation of ``marker`` under ``mask`` (8-connected), float32.

    The fixed point of ``min(dilate(out, 3 x 3), mask)`` from ``min(marker, mask)``, reached by a forward and a
    backward raster scan and a queue of the cells still to raise (Vincent 1993); the values are copies of the
    marker's and the mask's, so this is the same array as iterating the dilations."""
    out = np.minimum(marker, mask).astype(np.float32)
    _reconstruct_kernel(out, np.ascontiguousarray(mask, dtype=np.float32))
    return out


@njit(cache=True, nogil=True)
def _reconstruct_kernel(out: np.ndarray, mask: np.ndarray) -> None:
    rows, cols = out.shape
    for r in range(rows):  # forward scan: the neighbours already visited
        for c in range(cols):
            v = out[r, c]
            for dr, dc in ((-1, -1), (-1, 0), (-1, 1), (0, -1)):
                rr, cc = r + dr, c + dc
                if 0 <= rr < rows and 0 <= cc < cols and out[rr, cc] > v:
                    v = out[rr, cc]
            out[r, c] = min(v, mask[r, c])
    queue = np.empty(rows * cols + 1, np.int64)
    head = tail = 0
    for r in range(rows - 1, -1, -1):  # backward scan; cells that may raise a neighbour are queued
        for c in range(cols - 1, -1, -1):
            v = out[r, c]
            for dr, dc in ((1, 1), (1, 0), (1, -1), (0, 1)):
                rr, cc = r + dr, c + dc
                if 0 <= rr < rows and 0 <= cc < cols and out[rr, cc] > v:
                    v = out[rr, cc]
            v = min(v, mask[r, c])
            out[r, c] = v
            for dr, dc in ((1, 1), (1, 0), (1, -1), (0, 1)):
                rr, cc = r + dr, c + dc
                if 0 <= rr < rows and 0 <= cc < cols and out[rr, cc] < v and out[rr, cc] < mask[rr, cc]:
                    queue[tail] = r * cols + c
                    tail += 1
                    break
    while head < tail:
        p = queue[head]
        head += 1
        r, c = p // cols, p % cols
        v = out[r, c]
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                rr, cc = r + dr, c + dc
                if (dr or dc) and 0 <= rr < rows and 0 <= cc < cols and out[rr, cc] < v \
                        and out[rr, cc] != mask[rr, cc]:
                    out[rr, cc] = min(v, mask[rr, cc])
                    if tail == queue.size:  # the queue is full: drop its done head, grow it if still full
                        pending = queue[head:tail].copy()
                        if pending.size * 2 > queue.size:
                            queue = np.empty(2 * queue.size, np.int64)
                        queue[:pending.size] = pending
                        tail, head = pending.size, 0
                    queue[tail] = rr * cols + cc
                    tail += 1


def _flood(markers: np.ndarray, dist: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Watershed of -``dist`` from ``markers`` inside ``mask`` by flooding: level by level from the highest
    distance down (half-cell steps), the labelled regions grow (8-neighbour dilations) into the unlabelled
    mask cells at or above the level, so each cell joins the blob it is deepest in. Only the mask's bounding box
    is flooded: nothing grows outside the mask. Each dilation step is done at the cells next to those the
    previous one labelled (:func:`_flood_kernel`), the same steps as dilating the whole box."""
    result = np.zeros(mask.shape, np.int32)
    if not mask.any():
        return result
    r0, r1, c0, c1 = mask_bounds(mask)
    box = np.s_[max(r0 - 1, 0):r1 + 2, max(c0 - 1, 0):c1 + 2]
    markers, dist, mask = markers[box], dist[box], mask[box]
    out = np.where(mask, markers, 0).astype(np.float32)
    free = np.flatnonzero(mask & (markers == 0))  # the cells to flood, by the level from which they may be
    cell_level = np.floor(dist.ravel()[free] * 2.0) / 2.0
    levels = np.unique(cell_level)
    rank = levels.size - 1 - np.searchsorted(levels, cell_level)  # index in the levels from the highest down
    order = np.argsort(rank, kind='stable')
    starts = np.searchsorted(rank[order], np.arange(levels.size + 1))
    _flood_kernel(out, np.ascontiguousarray(dist), np.ascontiguousarray(mask), np.ascontiguousarray(levels[::-1]),
                  free[order], starts)
    result[box] = out.astype(np.int32)
    return result


@njit(cache=True, nogil=True, inline='always')
def _neighbour_max(out, r, c):
    rows, cols = out.shape
    g = np.float32(0.0)
    for rr in range(max(r - 1, 0), min(r + 2, rows)):
        for cc in range(max(c - 1, 0), min(c + 2, cols)):
            if out[rr, cc] > g:
                g = out[rr, cc]
    return g


@njit(cache=True, nogil=True)
def _flood_kernel(out, dist, mask, levels, cells, starts) -> None:
    """The flooding of :func:`_flood` in place on ``out`` (float32 labels, 0 = none): at every level, steps in
    which each free allowed cell (in ``mask``, ``dist`` >= level, unlabelled) with a labelled 8-neighbour takes
    the largest label around it, all from the labels before the step, until none changes.

    A level's first step looks only at the cells it allows first (``cells[starts[i]:starts[i + 1]]``, flat
    indices, for ``levels[i]``): after the previous level no allowed free cell was left next to a label."""
    rows, cols = out.shape
    cand = np.empty(rows * cols, np.int64)
    nxt = np.empty(rows * cols, np.int64)
    vals = np.empty(rows * cols, np.float32)
    stamp = np.full(rows * cols, -1, np.int64)
    step = 0
    for li in range(levels.size):
        level = levels[li]
        n = 0
        for j in range(starts[li], starts[li + 1]):
            r, c = cells[j] // cols, cells[j] % cols
            if mask[r, c] and dist[r, c] >= level and out[r, c] == 0:
                g = _neighbour_max(out, r, c)
                if g > 0:
                    cand[n] = r * cols + c
                    vals[n] = g
                    n += 1
        while n > 0:
            for k in range(n):
                out[cand[k] // cols, cand[k] % cols] = vals[k]
            step += 1
            m = 0
            for k in range(n):
                r, c = cand[k] // cols, cand[k] % cols
                for rr in range(max(r - 1, 0), min(r + 2, rows)):
                    for cc in range(max(c - 1, 0), min(c + 2, cols)):
                        q = rr * cols + cc
                        if stamp[q] != step and mask[rr, cc] and dist[rr, cc] >= level and out[rr, cc] == 0:
                            stamp[q] = step
                            nxt[m] = q
                            m += 1
            for k in range(m):
                vals[k] = _neighbour_max(out, nxt[k] // cols, nxt[k] % cols)
            cand, nxt = nxt, cand
            n = m


def _filled(mask: np.ndarray) -> np.ndarray:
    """``mask`` (H x W) with every hole of its 8-connected regions filled (bool)."""
    out = np.zeros(mask.shape, np.uint8)
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, 1, thickness=cv2.FILLED)
    return out > 0


def grid_components(right: np.ndarray, down: np.ndarray) -> np.ndarray:
    """Component of every cell of an (ny, nx) raster whose 4-neighbour edges are ``right`` (ny, nx - 1: cell (r, c)
    joined to (r, c + 1)) and ``down`` (ny - 1, nx: to (r + 1, c)), as ``scipy.sparse.csgraph.connected_components``
    numbers them on that graph (undirected; components in the order of their first cell, row-major): (ny, nx)
    int32 labels from 0, every cell without an edge a component of its own."""
    ny, nx = right.shape[0], down.shape[1]
    labels = np.empty(ny * nx, np.int32)
    _grid_components(np.ascontiguousarray(right, dtype=bool), np.ascontiguousarray(down, dtype=bool), labels)
    return labels.reshape(ny, nx)


@njit(cache=True, nogil=True, inline='always')
def _root(parent, a):
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@njit(cache=True, nogil=True)
def _grid_components(right, down, labels):
    ny, nx = down.shape[0] + 1, right.shape[1] + 1
    parent = np.arange(ny * nx)
    for r in range(ny):
        for c in range(nx):
            for ok, q in ((c + 1 < nx and right[r, c], r * nx + c + 1), (r + 1 < ny and down[r, c], (r + 1) * nx + c)):
                if ok:
                    a, b = _root(parent, r * nx + c), _root(parent, q)
                    if a != b:  # the smaller index is the root: a component's root is its first cell
                        parent[max(a, b)] = min(a, b)
    found = np.full(ny * nx, -1, np.int32)
    n = 0
    for p in range(ny * nx):
        root = _root(parent, p)
        if found[root] < 0:
            found[root] = n
            n += 1
        labels[p] = found[root]
