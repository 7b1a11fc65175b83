"""Objects on the table: evidence components in the table plane, split where objects touch, joined across small
holes, kept when they hold enough solid evidence; the target picked among them and refused when it is cut by the
border or too wide for the gripper."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import cv2
import numpy as np
from scipy.ndimage import find_objects
from scipy.special import ndtri

from gpis_grasp_ros.core.sensing.camera import CameraIntrinsics
from gpis_grasp_ros.core.sensing.evidence import (
    Evidence,
    _bounded_extension,
    chromatic_extension,
)
from gpis_grasp_ros.core.sensing.morphology import _filled, _flood, _nearest_label, _reconstruct, grid_components
from gpis_grasp_ros.core.sensing.params import (
    CHROMA_CLEAR_FRACTION,
    FLAT_JUMP_M,
    FLAT_MIN_AREA_M2,
    FLAT_STEP_M,
    MISSING_ATTACH_M,
    MISSING_BRIDGE_M,
    OBJECT_HEIGHT_PERCENTILE,
    SOLID_FALSE_ALARM,
    SPLIT_NECK_M,
    SensingParams,
)
from gpis_grasp_ros.core.sensing.pixel_kernels import (
    all_finite,
    distinct_cells_per_label,
    feet_box,
    has_label,
    mask_bounds,
    nan_to_num,
    raster_cells,
)
from gpis_grasp_ros.core.sensing.steps import cell_heights, split_height_steps
from gpis_grasp_ros.core.sensing.table import Measurement, TableFit, noise_ratio

#: Cells of the table raster kept around the pixels' feet: beyond any operation's reach from the evidence
RASTER_PAD_CELLS = 8


@dataclass
class _Raster:
    """Table-plane raster of the evidence: the part of the lattice from ``origin`` whose first cell is ``first``
    (column, row); cell (ix, iy) covers origin + [ix + first_x, ix + first_x + 1) x [...] x res."""

    origin: np.ndarray  # (2,) m, the lattice's origin
    res: float
    labels: np.ndarray  # (ny, nx) int32 component labels after closing (0 = none)
    first: tuple[int, int] = (0, 0)  # the lattice cell (column, row) of labels[0, 0]
    _last: tuple | None = field(default=None, repr=False)  # (xy, its cells): the frame's feet are asked again

    def cell(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(column, row, in the raster) of the cell under each table point ``xy`` (..., 2) (0, 0 outside)."""
        if self._last is not None and self._last[0] is xy:
            return self._last[1]
        self._last = (xy, raster_cells(xy, self.origin, self.res, self.labels.shape, self.first))
        return self._last[1]

    def centres(self, ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
        """(K, 2) table-frame centres (m) of the cells (``ix``, ``iy``)."""
        return self.origin + (np.stack([ix + self.first[0], iy + self.first[1]], axis=1) + 0.5) * self.res


def split_touching(labels: np.ndarray, neck_cells: float) -> tuple[np.ndarray, np.ndarray]:
    """Split touching objects in a labelled raster at the necks of their union (distance-transform watershed).

    Two objects in contact form one evidence component shaped like two blobs joined by a neck (their
    contact). The components' holes are filled first (a clear object is seen as an outline around a
    see-through interior). The distance transform (DT, cells to the nearest non-evidence cell) of the
    filled components has a maximum in each blob; the markers are the maxima whose *dynamic* (peak DT
    minus the DT of the saddle joining them to a higher peak) is at least ``neck_cells``: the h-maxima
    of the DT, i.e. both blobs are wider than the neck by at least 2 ``neck_cells`` in diameter. A
    component with two or more markers is divided by a watershed of -DT from them (cells go to the
    blob they are deepest in); an elongated object with a narrow part (a bottle's neck, a marker's
    tip) has no maximum in the narrow part and stays whole.

    Returns the new labels (split parts get fresh labels after the existing ones) and, per new label,
    the label it came from (so that the parts are not joined again by later merging steps)."""
    n = int(labels.max()) + 1
    origin = np.arange(n)
    if n <= 1 or neck_cells <= 0:
        return labels, origin
    filled = _filled(labels > 0).astype(np.uint8)
    n_f, lab_f = cv2.connectedComponents(filled, connectivity=8)
    dist = cv2.distanceTransform(np.pad(filled, 1), cv2.DIST_L2, 5)[1:-1, 1:-1]
    hmax = _reconstruct(np.maximum(dist - neck_cells, 0.0), dist)
    eps = 1e-3
    maxima = (hmax - _reconstruct(np.maximum(hmax - eps, 0.0), hmax) > eps / 2) & (filled > 0)
    n_mark, markers = cv2.connectedComponents(maxima.astype(np.uint8), connectivity=8)
    if n_mark <= 2:
        return labels, origin
    owner = np.zeros(n_mark, np.int64)
    owner[markers[maxima]] = lab_f[maxima]
    per_comp = np.bincount(owner[1:], minlength=n_f)
    out = labels.astype(np.int32).copy()
    origin = list(origin)
    for comp_id in np.nonzero(per_comp >= 2)[0]:
        if comp_id == 0:
            continue
        comp = lab_f == comp_id
        flooded = _flood(np.where(comp & (markers > 0), markers, 0), dist, comp)
        cells = comp & (labels > 0)
        parts = int(flooded.max()) + 1  # the (label, part) pairs in order, one integer key each
        keys = np.unique(labels[cells].astype(np.int64) * parts + flooded[cells])
        pairs = np.stack([keys // parts, keys % parts], axis=1)
        seen: set[int] = set()
        for lab, part in pairs:
            if int(lab) not in seen:  # the first part of each original label keeps the label
                seen.add(int(lab))
                continue
            out[cells & (labels == lab) & (flooded == part)] = len(origin)
            origin.append(int(lab))
    return out, np.asarray(origin)


def split_flat_support(labels: np.ndarray, cell_height: np.ndarray, res: float,
                       origin: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Split an object standing on or next to a flat one (a notebook, a plate, a tray) from it.

    ``cell_height`` (m, NaN = no depth-seen evidence in the cell) is the mean height of each raster
    cell's depth-seen pixels. Within a component, cells whose heights differ by at most
    ``FLAT_STEP_M`` from a 4-neighbour form *smooth* regions (the flat top of a notebook varies by
    ~1 mm from cell to cell; the feet of a box's walls and the rims of a clear object jump by
    centimetres). If the largest smooth region covers at least ``FLAT_MIN_AREA_M2`` and the rest of
    the component holds at least ``FLAT_MIN_AREA_M2`` / 4 of depth-seen cells more than ``FLAT_JUMP_M``
    *above* it (something taller standing on or next to it), the component is split:
    the flat region is one object, the rest is assigned to the flat region or to the other parts by a
    watershed of -DT (cells go to the part they are deepest in), each other part keeping its own label.
    A box's flat top is not a support: the feet of its walls lie *below* it. Nor is a smooth region whose
    heights (5th to 95th percentile) span more than ``FLAT_JUMP_M``: a support is flat to within the jump
    that tells what stands on it, while a lying cylinder's smooth crest (cell steps up to ``FLAT_STEP_M``)
    spans r (1 - 1 / sqrt(1 + (FLAT_STEP_M / res)^2)) and is kept with its taller end cap when that exceeds
    the jump. Limitations: one object made of a large flat base and a taller part (a tray with a handle) is
    split too, and so is a narrower lying cylinder with a taller end cap.

    Returns the labels and the origin of every label (see :func:`split_touching`)."""
    n = int(labels.max()) + 1
    origin = np.arange(n) if origin is None else np.asarray(origin)
    out = labels.astype(np.int32).copy()
    origin = list(origin)
    seen = np.isfinite(cell_height) & (labels > 0)
    min_cells = FLAT_MIN_AREA_M2 / res ** 2
    h = nan_to_num(cell_height)
    # 4-neighbour smoothness edges between depth-seen cells of the same component
    edges = [seen[a] & seen[b] & (labels[a] == labels[b]) & (np.abs(h[a] - h[b]) <= FLAT_STEP_M)
             for a, b in ((np.s_[:, :-1], np.s_[:, 1:]), (np.s_[:-1, :], np.s_[1:, :]))]
    smooth = np.where(seen, grid_components(*edges) + 1, 0)
    sizes = np.bincount(smooth.ravel())
    sizes[0] = 0
    big = np.nonzero(sizes >= min_cells)[0]  # smooth regions large enough to be a support, and their labels
    region_label = np.zeros(sizes.size, np.int64)
    region_label[smooth[seen]] = labels[seen]
    if big.size == 0:
        return out, np.asarray(origin)
    dist = cv2.distanceTransform(np.pad((labels > 0).astype(np.uint8), 1), cv2.DIST_L2, 5)[1:-1, 1:-1]
    for lab in np.unique(region_label[big]):
        comp = labels == lab
        regions = np.unique(smooth[comp & seen])
        if regions.size == 0:
            continue
        flat = int(regions[np.argmax(sizes[regions])])
        if sizes[flat] < min_cells:
            continue
        flat_cells = smooth == flat
        h_lo, h_flat, h_hi = np.percentile(h[flat_cells], [5.0, 50.0, 95.0])
        if h_hi - h_lo > FLAT_JUMP_M:  # not flat: what stands on a support is more than FLAT_JUMP_M above it all
            continue
        other = comp & seen & ~flat_cells & (h > h_flat + FLAT_JUMP_M)
        if other.sum() < min_cells / 4:
            continue
        n_o, lab_o = cv2.connectedComponents(other.astype(np.uint8), connectivity=8)
        markers = np.where(flat_cells, 1, np.where(lab_o > 0, lab_o + 1, 0)).astype(np.int32)
        flooded = _flood(markers, dist, comp)
        for part in range(2, n_o + 1):
            sel = comp & (flooded == part)
            if sel.any():
                out[sel] = len(origin)
                origin.append(int(origin[lab]) if lab < len(origin) else lab)
    return out, np.asarray(origin)


def _merge_across_small_holes(labels: np.ndarray, lab_miss: np.ndarray, n_miss: int, n_pos: int,
                              touching: np.ndarray, res: float, origin: np.ndarray | None = None) -> np.ndarray:
    """Objects touching the same small hole region (extent <= ``MISSING_BRIDGE_M``) are one object
    (e.g. a specular band across a marker); large hole regions (drop-outs along the table) join nothing.
    Parts of one component split at a neck (same ``origin``, :func:`split_touching`) are not joined again."""
    parent = np.arange(labels.max() + 1)
    source = np.arange(parent.size)
    if origin is not None:
        source[:min(origin.size, source.size)] = origin[:source.size]

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    grown = cv2.dilate((labels > 0).astype(np.uint8), np.ones((3, 3), np.uint8))
    boxes = find_objects(lab_miss)
    ny, nx = lab_miss.shape
    for c in np.nonzero(touching)[0]:
        if c == 0 or boxes[c - 1] is None:
            continue
        rs, cs = boxes[c - 1]
        rows, cols = np.nonzero(lab_miss[rs, cs] == c)
        if math.hypot(np.ptp(rows), np.ptp(cols)) * res > MISSING_BRIDGE_M:
            continue
        # the region's box and the cell around it that its dilation reaches
        box = np.s_[max(rs.start - 1, 0):min(rs.stop + 1, ny), max(cs.start - 1, 0):min(cs.stop + 1, nx)]
        ring = cv2.dilate((lab_miss[box] == c).astype(np.uint8), np.ones((3, 3), np.uint8)) & grown[box]
        lab_box = labels[box]
        near = np.unique(lab_box[(ring > 0) & (lab_box > 0) & (lab_box <= n_pos)])
        for other in near[1:]:
            if source[int(other)] != source[int(near[0])]:
                parent[find(int(other))] = find(int(near[0]))
    roots = np.array([find(i) for i in range(parent.size)])
    return roots[labels].astype(np.int32)


def _table_components(foot_xy: np.ndarray, evidence: np.ndarray, missing: np.ndarray, inlier_xy: np.ndarray,
                      footprint_m: float, attach_m: float, height: np.ndarray | None = None,
                      sigma: np.ndarray | None = None, min_area_m2: float = 0.0) -> tuple[_Raster, np.ndarray]:
    """Rasterise the evidence pixels' feet over the table's extent and label connected components.

    Components are built from the positive evidence (depth or colour). Holes (missing pixels) are
    grouped separately: a hole region touching an object joins it only within ``attach_m`` of its
    positive evidence (a hole is object where it is part of a seen object, e.g. a specular patch, not
    a path along the table's drop-outs to the next object), entirely if it touches only that object
    and is at most 2 ``MISSING_BRIDGE_M`` across; a small hole region (``MISSING_BRIDGE_M``) touching
    several objects joins them; a hole region touching no object is an object of its own (entirely
    specular / transparent).

    Components are split at necks (:func:`split_touching`), with ``height`` (m, NaN = not seen in depth) at flat
    supports (:func:`split_flat_support`) and, with ``sigma`` (m, each pixel's height noise), at height steps
    (:func:`~.steps.split_height_steps`, its cores at least the minimum object ``min_area_m2`` and a jaw face of
    its side wide).

    Returns the raster and the per-pixel labels (0 = not evidence or off the table)."""
    lo, hi = inlier_xy.min(axis=0), inlier_xy.max(axis=0)
    res = max(5e-4, 2.0 * footprint_m)
    while np.prod((hi - lo) / res) > 4e6:
        res *= 1.5
    nx, ny = (int(v) + 1 for v in np.ceil((hi - lo) / res))
    # the lattice over the table's extent, held where the pixels' feet are (a window's part of the table), with
    # RASTER_PAD_CELLS around them: the same cells as the whole frame's raster
    x0, y0, x1, y1 = feet_box(foot_xy)
    if not (math.isfinite(x0) and math.isfinite(y0)):
        x0, y0, x1, y1 = lo[0], lo[1], hi[0], hi[1]
    k0 = (int(np.clip(math.floor((x0 - lo[0]) / res) - RASTER_PAD_CELLS, 0, nx)),
          int(np.clip(math.floor((y0 - lo[1]) / res) - RASTER_PAD_CELLS, 0, ny)))
    k1 = (int(np.clip(math.floor((x1 - lo[0]) / res) + 1 + RASTER_PAD_CELLS, k0[0] + 1, nx)),
          int(np.clip(math.floor((y1 - lo[1]) / res) + 1 + RASTER_PAD_CELLS, k0[1] + 1, ny)))
    raster = _Raster(lo, res, np.zeros((k1[1] - k0[1], k1[0] - k0[0]), np.int32), k0)
    nx, ny = k1[0] - k0[0], k1[1] - k0[1]
    # the table's extent: convex hull of its inliers (in raster cell units)
    hull = cv2.convexHull(((inlier_xy - lo) / res).astype(np.float32))
    extent = np.zeros((ny, nx), np.uint8)
    cv2.fillConvexPoly(extent, np.round(hull).astype(np.int32) - np.array(k0, np.int32), 1)
    extent = cv2.erode(extent, np.ones((5, 5), np.uint8))  # the rounded hull's rim (2 cells) is not surely table
    ix, iy, ok = raster.cell(foot_xy)
    use = evidence & ok & (extent[iy, ix] > 0)
    close = np.ones((3, 3), np.uint8)

    def mark(sel: np.ndarray) -> np.ndarray:
        m = np.zeros((ny, nx), np.uint8)
        m[iy[sel], ix[sel]] = 1
        return cv2.morphologyEx(m, cv2.MORPH_CLOSE, close)

    n_pos, lab_pos = cv2.connectedComponents(mark(use & ~missing), connectivity=8)
    lab_pos, origin = split_touching(lab_pos, SPLIT_NECK_M / res)  # objects in contact
    if height is not None:  # an object standing on / next to a flat one (notebook, plate); touching at a step
        cells = cell_heights(iy, ix, use, height, np.zeros(height.shape) if sigma is None else sigma, missing,
                             (ny, nx))
        lab_pos, origin = split_flat_support(lab_pos, cells.mean, res, origin)
        if sigma is not None:
            lab_pos, origin = split_height_steps(lab_pos, cells, res, math.sqrt(min_area_m2), min_area_m2, origin)
    n_pos = int(lab_pos.max()) + 1
    n_miss, lab_miss = cv2.connectedComponents(mark(use & missing) & (lab_pos == 0).astype(np.uint8), connectivity=8)
    labels = lab_pos.astype(np.int32)
    if n_miss > 1:
        if n_pos > 1:
            nearest, dist = _nearest_label(lab_pos)
            touching = np.zeros(n_miss, dtype=bool)
            touching[np.unique(lab_miss[(dist <= 1.5) & (lab_miss > 0)])] = True
        else:
            nearest, dist, touching = np.zeros_like(labels), np.full(labels.shape, np.inf), np.zeros(n_miss, bool)
        attach = (lab_miss > 0) & touching[lab_miss] & (dist * res <= attach_m)
        labels[attach] = nearest[attach]
        boxes = find_objects(lab_miss)  # each hole region's bounding box
        for c in np.nonzero(touching)[0]:  # a hole region of one object only (a specular lever): all of it
            box = boxes[c - 1]
            cells = lab_miss[box] == c
            rows, cols = np.nonzero(cells)
            owners = np.unique(nearest[box][cells & (dist[box] <= 1.5)])
            if owners.size == 1 and math.hypot(np.ptp(rows), np.ptp(cols)) * res <= 2 * MISSING_BRIDGE_M:
                labels[box][cells] = owners[0]
        alone = (lab_miss > 0) & ~touching[lab_miss]
        labels[alone] = n_pos + lab_miss[alone]
        labels = _merge_across_small_holes(labels, lab_miss, n_miss, n_pos, touching, res, origin)
    raster.labels = labels
    px_labels = np.where(use, raster.labels[iy, ix], 0)
    return raster, px_labels


#: Sigmas of the table's height noise above which a depth-seen pixel is solid (one-sided, SOLID_FALSE_ALARM).
SOLID_SIGMAS = float(-ndtri(SOLID_FALSE_ALARM))


def solid_pixels(height: np.ndarray, s_h: np.ndarray, inlier: np.ndarray, h_thr: float,
                 missing: np.ndarray, ratio: float | None = None) -> np.ndarray:
    """Pixels that are surely not the table: depth-seen more than ``SOLID_SIGMAS`` sigma above it, or ``missing``.

    sigma is each pixel's height noise ``s_h`` (m, the sensor model at its depth and incidence) scaled by the
    table inliers' measured RMS height over their modelled one (``ratio``, from ``inlier`` when not given: a
    filtered depth image is less noisy than the model, a rough table or a misfitted plane more); at least the
    depth-evidence threshold ``h_thr``."""
    ratio = noise_ratio(height, s_h, inlier) if ratio is None else ratio
    thr = np.maximum(h_thr, SOLID_SIGMAS * ratio * s_h)
    return (nan_to_num(height, nan=-np.inf) > thr) | missing


def object_labels(px_labels: np.ndarray, raster: _Raster, foot_xy: np.ndarray, solid: np.ndarray,
                  params: SensingParams) -> np.ndarray:
    """Labels of the components that are objects, not sensor noise or marks on the table.

    An object covers at least ``min_object_area_px`` pixels and ``min_object_area_m2`` of the table, and as much
    table area of ``solid`` evidence (:func:`solid_pixels`; area = the raster cells holding its solid pixels'
    feet). The default 1 cm^2 is a jaw face (``GripperParams.jaw_width`` 1 cm) squared: less can neither be
    held nor stop a closing jaw. Depth noise just above the evidence threshold and flat prints seen only in
    colour are neither targets nor other objects."""
    n_lab = int(raster.labels.max()) + 1
    px_count = np.bincount(px_labels.ravel(), minlength=n_lab)
    area_m2 = np.bincount(raster.labels.ravel(), minlength=n_lab) * raster.res ** 2
    ix, iy, ok = raster.cell(foot_xy)
    sel = solid & (px_labels > 0) & ok
    n_cells = raster.labels.size  # one key per (label, cell): the distinct cells of each label
    solid_m2 = distinct_cells_per_label(px_labels[sel], iy[sel] * raster.labels.shape[1] + ix[sel], n_cells,
                                        n_lab) * raster.res ** 2
    kept = np.nonzero((px_count >= params.min_object_area_px) & (area_m2 >= params.min_object_area_m2)
                      & (solid_m2 >= params.min_object_area_m2))[0]
    return kept[kept > 0]


def clear_labels(px_labels: np.ndarray, kept: np.ndarray, p_d: np.ndarray) -> np.ndarray:
    """The clear objects among ``kept``: fewer than ``CHROMA_CLEAR_FRACTION`` of their pixels seen in depth."""
    n_lab = int(px_labels.max()) + 1
    seen = np.bincount(px_labels[p_d > 0.5], minlength=n_lab)  # the same counts as weights of 0 and 1
    size = np.bincount(px_labels.ravel(), minlength=n_lab)
    return kept[seen[kept] < CHROMA_CLEAR_FRACTION * size[kept]]


def clear_object_at(u: int, v: int, px_labels: np.ndarray, clear: np.ndarray, kept: np.ndarray, ev: Evidence,
                    meas: Measurement, fit: TableFit, missing_px: np.ndarray, chroma_z: np.ndarray,
                    params: SensingParams) -> int:
    """The clear object (one of the labels ``clear``) whose body, seen through, holds pixel (u, v); 0 if none.

    A clear object lying on the table returns the table's depth through its body, so a pixel on the body is on no
    object's evidence. The pixel selects an object when the table seen there is tinted as through a clear body
    (:func:`~.evidence.chromatic_extension` on the chromaticity z-scores ``chroma_z``, grown from the pixel: a region
    of changed chromaticity with a core, not running out of the image) and that region touches a clear object,
    whose body :func:`~.clear_body.grow_target` extends over the same kind of pixels. Of several such objects, the
    nearest to the pixel through the region."""
    is_object = has_label(px_labels, kept)
    table_level = np.isfinite(meas.height) & (ev.p_d <= 0.5) & (np.abs(nan_to_num(meas.height)) <= fit.h_thr)
    seed = np.zeros(px_labels.shape, dtype=bool)
    seed[v, u] = True
    region = _bounded_extension(seed, chromatic_extension(seed, (table_level | missing_px) & ~is_object, chroma_z,
                                                          params.chroma_z_min), params)
    if not region.any():
        return 0
    # the nearest clear object through the region: grow from the pixel one ring at a time within the region (on
    # the region's bounding box plus a pixel) until a ring meets a clear object
    v_min, v_max, u_min, u_max = mask_bounds(region | seed)
    box = (slice(max(v_min - 1, 0), v_max + 2), slice(max(u_min - 1, 0), u_max + 2))
    inside, labels = (region | seed)[box].astype(np.uint8), px_labels[box]
    is_clear = np.isin(labels, clear)
    reach, ring = seed[box].astype(np.uint8), np.ones((3, 3), np.uint8)
    while True:
        grown = cv2.dilate(reach, ring)
        hit = (grown > 0) & is_clear
        if hit.any():
            found, n = np.unique(labels[hit], return_counts=True)
            return int(found[np.argmax(n)])
        grown &= inside
        if np.array_equal(grown, reach):
            return 0
        reach = grown


def _select_target(px_labels: np.ndarray, raster: _Raster, foot_xy: np.ndarray, params: SensingParams,
                   intr: CameraIntrinsics, kept: np.ndarray) -> tuple[int, int]:
    """Label of the target among the objects ``kept`` and the number of objects seen (``target`` mode)."""
    n_lab = int(raster.labels.max()) + 1
    area_m2 = np.bincount(raster.labels.ravel(), minlength=n_lab) * raster.res ** 2
    if kept.size == 0:
        raise ValueError(f'no object found on the table: no region of at least {params.min_object_area_px} px and '
                         f'{params.min_object_area_m2 * 1e4:.1f} cm^2 stands out from the table in depth or colour '
                         'or lacks depth, with as much of it surely above the table\'s depth noise or without depth '
                         '(empty table?)')
    if params.target == 'largest':
        return int(kept[np.argmax(area_m2[kept])]), int(kept.size)
    if params.target == 'nearest_center':
        vv, uu = np.nonzero(px_labels > 0)
        lab = px_labels[vv, uu]
        n = np.bincount(lab, minlength=n_lab).astype(np.float64)
        cu = np.bincount(lab, uu, minlength=n_lab) / np.maximum(n, 1)
        cv = np.bincount(lab, vv, minlength=n_lab) / np.maximum(n, 1)
        d = np.hypot(cu[kept] - (intr.width - 1) / 2, cv[kept] - (intr.height - 1) / 2)
        return int(kept[np.argmin(d)]), int(kept.size)
    if params.target == 'pixel':
        u, v = (int(round(c)) for c in params.target_point)
        if not (0 <= u < intr.width and 0 <= v < intr.height):
            raise ValueError(f'target pixel ({u}, {v}) is outside the {intr.width} x {intr.height} image')
        point = foot_xy[v, u]
        if not np.isfinite(point).all():
            raise ValueError(f'target pixel ({u}, {v}) does not look at the table (its ray misses the plane)')
        what = f'target pixel ({u}, {v})'
    else:
        point = np.asarray(params.target_point, dtype=np.float64)
        what = f'target point ({point[0]:.3f}, {point[1]:.3f}) m in the table frame'
    iy, ix = np.nonzero(has_label(raster.labels, kept))
    centres = raster.centres(ix, iy)
    dist = np.linalg.norm(centres - point, axis=1)
    if dist.size == 0 or dist.min() > params.target_tolerance_m + raster.res:
        near = '' if dist.size == 0 else f' (nearest object {dist.min() * 1000:.0f} mm away)'
        raise ValueError(f'{what} is on no object{near}: {kept.size} object(s) seen on the table')
    return int(raster.labels[iy[np.argmin(dist)], ix[np.argmin(dist)]]), int(kept.size)


def minimum_width(xy: np.ndarray) -> float:
    """Smallest extent (m) of points ``(K, 2)`` over all directions (exact: the hull's edge directions)."""
    pts = np.asarray(xy, dtype=np.float64)
    if pts.shape[0] < 3:
        return 0.0
    hull = cv2.convexHull(pts.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    if hull.shape[0] < 3:
        return 0.0
    edges = np.roll(hull, -1, axis=0) - hull
    length = np.linalg.norm(edges, axis=1)
    edges, starts = edges[length > 0], hull[length > 0]
    normals = np.stack([-edges[:, 1], edges[:, 0]], axis=1) / np.linalg.norm(edges, axis=1)[:, None]
    extent = np.abs((hull[None, :, :] - starts[:, None, :]) @ normals[..., None])[..., 0].max(axis=1)
    return float(extent.min())


class TargetCut(ValueError):
    """The target reaches the border of the image (or of the pixel ROI): its shape is not fully seen."""


def _check_target(target_px: np.ndarray, target_xy: np.ndarray, target_raster: np.ndarray, raster_res: float,
                  params: SensingParams, intr: CameraIntrinsics) -> None:
    """Refuse a target cut by the image (or pixel ROI) border, or with no part narrow enough for the gripper.

    Too wide = the footprint's convex hull is wider than ``max_opening_m`` in every direction *and*
    its largest inscribed disc is wider too (a toy plane's wings are wide but its fuselage fits)."""
    v_min, v_max, u_min, u_max = mask_bounds(target_px)
    b = params.border_px
    u_lo, v_lo, u_hi, v_hi = (0, 0, intr.width - 1, intr.height - 1) if params.roi_px is None else \
        (max(0, params.roi_px[0]), max(0, params.roi_px[1]), min(intr.width - 1, params.roi_px[2]),
         min(intr.height - 1, params.roi_px[3]))
    if u_min < u_lo + b or v_min < v_lo + b or u_max > u_hi - b or v_max > v_hi - b:
        raise TargetCut(f'the target (pixels u {u_min}..{u_max}, v {v_min}..{v_max}) is cut by the image '
                         'border: its shape is not fully seen (move the camera or the object, or choose another '
                         'target)')
    if params.max_opening_m > 0:
        width = minimum_width(target_xy)
        if width > params.max_opening_m:
            padded = np.pad(target_raster.astype(np.uint8), 1)
            inscribed = 2.0 * float(cv2.distanceTransform(padded, cv2.DIST_L2, 5).max()) * raster_res
            if inscribed > params.max_opening_m:
                (x0, y0), (x1, y1) = target_xy.min(axis=0), target_xy.max(axis=0)
                raise ValueError(f'the target is {width * 1000:.0f} mm wide in its narrowest direction and no part of '
                                 f'it is narrower than {inscribed * 1000:.0f} mm: more than the gripper opening '
                                 f'max_opening_m = {params.max_opening_m * 1000:.0f} mm. If it is several objects '
                                 'touching with no step in height, normal or neck between them to separate them, '
                                 'select the one to grasp with roi_table (x_min, y_min, x_max, y_max, m in the table '
                                 f'frame; this target spans x {x0:.3f} .. {x1:.3f}, y {y0:.3f} .. {y1:.3f}): the '
                                 'evidence outside it is ignored')


def in_contact(raster: _Raster, px_labels: np.ndarray, foot_xy: np.ndarray, target: int) -> np.ndarray:
    """Pixels of the other objects in contact with the target: objects with a pixel whose foot falls in a raster
    cell next to (8-neighbour of) or in a cell holding a target pixel's foot - no cell between them where a
    table pixel could have been seen. The closed raster's labels are not used: closing bridges gaps of seen table.

    Where two objects touch, the line between them is where a split (:func:`split_touching`, a flat support, a
    height step) put it - an inference, not a measurement of free table. The target's grid counts such pixels
    as table the sensor did not confirm (uncertain), not as table seen (:func:`~.rasterise.rasterise`)."""
    ix, iy, ok = raster.cell(foot_xy)
    mine = np.zeros(raster.labels.shape, np.uint8)
    sel = ok & (px_labels == target)
    mine[iy[sel], ix[sel]] = 1
    near = cv2.dilate(mine, np.ones((3, 3), np.uint8)) > 0
    others = ok & (px_labels > 0) & (px_labels != target)
    touching = np.unique(px_labels[others][near[iy[others], ix[others]]])
    return has_label(px_labels, touching) if touching.size else np.zeros(px_labels.shape, dtype=bool)


def object_height(height: np.ndarray, seen: np.ndarray, percentile: float = OBJECT_HEIGHT_PERCENTILE,
                  min_pixels: int = 10) -> float:
    """Height (m) of an object above the table: the ``percentile`` of the heights (m, along the table normal)
    of its pixels ``seen`` in depth above the table; 0 (unknown) with fewer than ``min_pixels`` of them.

    A high percentile rather than the maximum: the top face (or the crest of a lying cylinder) is the
    highest part seen, and 5 % of the pixels may be depth outliers (flying pixels at edges). Parts
    without a depth return (specular, or transparent ones the sensor sees through: their depth is the
    table's) are not measured, so an object seen only through holes and colour has an unknown height,
    and one whose top is entirely specular is measured by its highest seen part (its walls)."""
    h = np.asarray(height, dtype=np.float64)[np.asarray(seen, dtype=bool)]
    h = h[np.isfinite(h)]
    if h.size < max(1, min_pixels):
        return 0.0
    return max(0.0, float(np.percentile(h, percentile)))


class Objects(NamedTuple):
    """The objects seen on the table and the target among them."""

    raster: _Raster  # table-plane raster of the evidence components
    px_labels: np.ndarray  # (H, W) int, component of each evidence pixel (0 = none)
    target: int  # the target's label
    objects_seen: int  # components kept (not specks)
    target_px: np.ndarray  # (H, W) bool, the target's evidence pixels
    kept: np.ndarray  # labels of the objects (components that are not noise, :func:`object_labels`)


def isolate_target(fit: TableFit, meas: Measurement, ev: Evidence, occ: np.ndarray,
                   missing_px: np.ndarray, foot_xy: np.ndarray, footprint: float, intrinsics: CameraIntrinsics,
                   params: SensingParams, rgb_mean: np.ndarray | None = None) -> Objects:
    """Evidence (o, p_d or p_c > 0.5, or missing) above the plane, on the table's extent and in the region of
    interest, split into objects in the table plane; the target selected and checked. With the frame's colour
    ``rgb_mean``, a target pixel on the body of a clear object seen through selects it (:func:`clear_object_at`)
    before the nearest object within ``target_tolerance_m`` would."""
    h, w = missing_px.shape
    height, inlier = meas.height, fit.inlier
    evidence = (occ > 0.5) | (ev.p_d > 0.5) | (ev.p_c > 0.5) | missing_px
    if params.morph_kernel_px > 1:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (params.morph_kernel_px, params.morph_kernel_px))
        evidence = cv2.morphologyEx(evidence.astype(np.uint8), cv2.MORPH_OPEN, kernel).astype(bool)
    h_ok = nan_to_num(height, nan=0.0)
    evidence &= (h_ok > -fit.band) & (h_ok < params.max_object_height_m) & all_finite(foot_xy)
    if params.roi_px is not None:
        u0, v0, u1, v1 = params.roi_px
        uu, vv = np.meshgrid(np.arange(w), np.arange(h))
        evidence &= (uu >= u0) & (uu <= u1) & (vv >= v0) & (vv <= v1)
    if params.roi_table is not None:
        x0, y0, x1, y1 = params.roi_table
        fx_, fy_ = foot_xy[..., 0], foot_xy[..., 1]
        evidence &= (fx_ >= x0) & (fx_ <= x1) & (fy_ >= y0) & (fy_ <= y1)
    on_plane = inlier & (np.abs(nan_to_num(height, nan=np.inf)) <= fit.band)  # not moved by the see-through test
    ratio = fit.noise_ratio  # the frame's table
    raster, px_labels = _table_components(foot_xy, evidence, missing_px, fit.rim_xy, footprint, MISSING_ATTACH_M,
                                          np.where(ev.p_d > 0.5, height, np.nan), max(ratio, 1.0) * meas.s_h,
                                          params.min_object_area_m2)
    solid = solid_pixels(height, meas.s_h, on_plane, fit.h_thr, missing_px & evidence, ratio)
    kept = object_labels(px_labels, raster, foot_xy, solid, params)
    target, objects_seen = 0, int(kept.size)
    if params.target == 'pixel' and rgb_mean is not None and params.chroma_z_min > 0:
        u, v = (int(round(c)) for c in params.target_point)
        if 0 <= u < w and 0 <= v < h and px_labels[v, u] not in kept:  # not on an object's evidence
            clear = clear_labels(px_labels, kept, ev.p_d)
            if clear.size:
                target = clear_object_at(u, v, px_labels, clear, kept, ev, meas, fit, missing_px, fit.chroma_z(),
                                         params)
    if not target:  # on an object's evidence, or the nearest object within target_tolerance_m
        target, objects_seen = _select_target(px_labels, raster, foot_xy, params, intrinsics, kept)
    target_px = px_labels == target
    _check_target(target_px, foot_xy[target_px], raster.labels == target, raster.res, params, intrinsics)
    return Objects(raster, px_labels, target, objects_seen, target_px, kept)
