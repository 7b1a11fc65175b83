"""Clear targets: the table seen through them joins the target (an enclosed interior, a change of the table's
chromaticity), and a clear body's footprint is the prism under its silhouette."""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.sensing.camera import AveragedFrames, CameraIntrinsics
from gpis_grasp_ros.core.sensing.evidence import (
    Evidence,
    _bounded_extension,
    chromatic_extension,
)
from gpis_grasp_ros.core.sensing.morphology import _filled
from gpis_grasp_ros.core.sensing.objects import Objects, _Raster, clear_labels, in_contact, minimum_width
from gpis_grasp_ros.core.sensing.occlusion import Feet
from gpis_grasp_ros.core.sensing.params import (
    CHROMA_CLEAR_FRACTION,
    CHROMA_CORE_PX,
    CLEAR_BODY_FRACTION,
    CLEAR_BODY_HEIGHT_FACTOR,
    PRISM_RASTER_M,
    PRISM_STEP_M,
    SensingParams,
)
from gpis_grasp_ros.core.sensing.pixel_kernels import all_finite, has_label, nan_to_num
from gpis_grasp_ros.core.sensing.ray_kernels import camera_vector, coarse_to_fine, under_prism
from gpis_grasp_ros.core.sensing.table import Measurement, TableFit
from gpis_grasp_ros.core.table_frame import TableFrame


def seen_through(raster: _Raster, target: int, foot_xy: np.ndarray, px_labels: np.ndarray, table_level: np.ndarray,
                 close_m: float) -> np.ndarray:
    """Pixels that see the table *through* the target: its enclosed interior (a transparent object's outline).

    A clear object lying on the table is seen as an outline - specular edges, depth holes at its ends,
    colour along its rims - around an interior where the sensor returns the table behind it (the paper's
    "invalid measurements", section VI). In the table raster the target's component is dilated with a
    disc of radius ``close_m`` (gaps in the outline up to ~2 ``close_m`` close), its holes are filled and it
    is eroded back with the same disc. The pixels returned are table-level pixels (``table_level``: valid
    depth, no depth evidence) not given to another object whose foot lies in a cell of the filled interior
    that is not in the component. The caller makes them object in the occupancy map with colour/hole evidence
    only (p_c = 1 against the table-level depth: the masks disagree, the cells are uncertain), never
    observed-depth table. An opaque object's interior is seen in depth (no such pixels)."""
    comp = (raster.labels == target).astype(np.uint8)
    r = max(1, int(round(close_m / raster.res)))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    grown = cv2.dilate(np.pad(comp, r + 1), disc)  # gaps in a thin outline up to 2 r close
    filled = np.zeros_like(grown)
    contours, _ = cv2.findContours(grown, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(filled, contours, -1, 1, thickness=cv2.FILLED)
    filled = cv2.erode(filled, disc)[r + 1:-r - 1, r + 1:-r - 1] | comp  # back to the outline's extent
    interior = (filled > 0) & (comp == 0)
    ix, iy, ok = raster.cell(foot_xy)
    free = (px_labels == 0) | (px_labels == target)
    return ok & free & table_level & interior[iy, ix]


def prism_footprint(cells_xy: np.ndarray, silhouette: np.ndarray, table: TableFrame, intrinsics: CameraIntrinsics,
                    height_m: float, step_m: float = PRISM_STEP_M) -> np.ndarray:
    """Table points (``cells_xy`` (..., 2), table frame, m) under a prism of height ``height_m`` whose image is
    ``silhouette`` (H x W bool): the single-view visual hull of a prism standing on the table.

    A point x is under it when the vertical segment from x up to ``height_m`` projects onto silhouette pixels
    at every ``step_m`` of height (the silhouette dilated by one pixel for the rounding). Seen by a camera
    tilted by theta, the silhouette's table points are the footprint swept H tan(theta) away from the camera;
    this undoes the sweep. ``height_m`` = 0 gives the silhouette's own table points."""
    return _prism_test(cells_xy, silhouette, table, intrinsics)(height_m, step_m)


def _prism_test(cells_xy: np.ndarray, silhouette: np.ndarray, table: TableFrame, intrinsics: CameraIntrinsics):
    """:func:`prism_footprint` of these cells and silhouette as a function of the height (and step), the
    dilated silhouette and the cells' camera points made once for all the heights tried."""
    sil = cv2.dilate(np.asarray(silhouette, dtype=np.uint8), np.ones((3, 3), np.uint8)) > 0
    base = table.to_camera(np.asarray(cells_xy, dtype=np.float64))  # camera frame, on the table
    flat = np.ascontiguousarray(base.reshape(-1, 3))
    cam = camera_vector(intrinsics)

    def under(height_m: float, step_m: float = PRISM_STEP_M) -> np.ndarray:
        heights = np.linspace(0.0, max(height_m, 0.0), max(2, int(math.ceil(height_m / step_m)) + 1))
        heights = heights[np.r_[0, heights.size - 1, 1 + coarse_to_fine(heights.size - 2)]]  # the same test, sooner off
        # h above the table, towards the camera
        return under_prism(flat, table.n, heights, cam, sil).reshape(base.shape[:-1])

    return under


def clear_body_height(silhouette: np.ndarray, table: TableFrame, intrinsics: CameraIntrinsics,
                      res_m: float = PRISM_RASTER_M, iterations: int = 12,
                      known_height_m: float = 0.0) -> tuple[float, np.ndarray]:
    """Height (m) of a clear body seen only as a silhouette (no depth on it), and the footprint under it.

    Without depth, a single view fixes the footprint only given H (the silhouette's table points are the
    footprint swept H tan(theta) away from the camera; :func:`prism_footprint` undoes the sweep). Two priors
    each fix H:

    * **lying** - a bottle on its side, a box on its face - is about as high as its footprint's smallest
      width: the prism height at which the footprint is as narrow as it is high;
    * **round** - an upright can, a knob, a glass - has a footprint as deep (along the camera's view, in the
      table plane) as it is wide (across it): the height at which the footprint's two extents are equal. A
      silhouette whose table points are already shallower than wide (a body lying across the view) has no
      such height.

    The lower of the two is taken: the one that leaves more of the footprint (a lower H sweeps less away).
    A squat round body (a 7 cm knob, 3.5 cm high) gets the round H, a lying bar the lying one whatever its
    direction (lying along the view its round H is far too high), and a body higher than wide (an upright
    bottle) the lying H, too small - its footprint then reaches too far away from the camera: more object,
    never a missing part. Both heights are found by bisection on a ``res_m`` raster. Returns H and the
    footprint's raster cell centres (K, 2) in the table frame (m); (0, the silhouette's table points) when
    it has fewer than 3 of them. ``known_height_m`` > 0 (the body's height known, e.g. from a catalogue of the
    objects): no prior, the footprint under a prism of that height.

    The priors assume vertical walls. A round body lying on the table (a bottle) leaves the silhouette of a
    box lower by a factor cos a + sin a (a: the rays' angle from the vertical across its axis; 1.4 at 45-52
    deg), so the lying prior puts it that much too low and its footprint H tan(a) / 2 too far from the
    camera. One view of a clear body does not tell the two apart."""
    vs, us = np.nonzero(silhouette)  # the silhouette's rays (CameraIntrinsics.rays at its pixels)
    rays = np.stack([(us.astype(np.float64) - intrinsics.cx) / intrinsics.fx,
                     (vs.astype(np.float64) - intrinsics.cy) / intrinsics.fy, np.ones(us.size)], axis=-1)
    hit, ok = table.ray_intersection(rays)
    if ok.sum() < 3:
        return 0.0, table.to_table(hit[ok])[0]
    xy = table.to_table(hit[ok])[0]
    lo, hi = xy.min(axis=0) - res_m, xy.max(axis=0) + res_m
    nx, ny = (int(math.ceil(c)) for c in (hi - lo) / res_m)
    gx, gy = np.meshgrid(lo[0] + (np.arange(nx) + 0.5) * res_m, lo[1] + (np.arange(ny) + 0.5) * res_m)
    cells = np.stack([gx, gy], axis=-1)
    view = xy.mean(axis=0) - table.to_table(np.zeros((1, 3)))[0][0]  # camera's foot -> body, in the table plane
    view = view / max(float(np.linalg.norm(view)), 1e-12)
    across = np.array([-view[1], view[0]])

    under_at = _prism_test(cells, silhouette, table, intrinsics)

    def footprint(h: float) -> np.ndarray:
        return cells[under_at(h)]

    def narrow_minus_height(h: float) -> float:
        under = footprint(h)
        return (minimum_width(under) if under.shape[0] >= 3 else 0.0) - h

    def deep_minus_wide(h: float) -> float:
        under = footprint(h)
        return float(np.ptp(under @ view) - np.ptp(under @ across)) if under.shape[0] >= 3 else -1.0

    def bisect(f, high: float) -> float:  # the largest h in [0, high] with f(h) >= 0 (f decreasing)
        low = 0.0
        for _ in range(iterations):
            mid = 0.5 * (low + high)
            low, high = (mid, high) if f(mid) >= 0.0 else (low, mid)
        return low

    if known_height_m > 0:
        return float(known_height_m), footprint(float(known_height_m))
    top = narrow_minus_height(0.0)  # the silhouette's own smallest width bounds both heights
    height = bisect(narrow_minus_height, top)
    if deep_minus_wide(0.0) > 0.0:
        height = min(height, bisect(deep_minus_wide, top))
    return height, footprint(height)


def _touching_clear_parts(target_px: np.ndarray, missing: np.ndarray, depth_seen: np.ndarray, px_labels: np.ndarray,
                          target: int) -> np.ndarray:
    """Pixels of the other parts of a clear target: no-return regions and evidence components touching its
    pixels in the image (8-connected) that are themselves clear - fewer than ``CHROMA_CLEAR_FRACTION`` of
    their pixels seen in depth. A clear body falls apart into a specular ridge, holes at its ends and a
    seen-through interior; an object seen in depth next to it is not taken."""
    touch = cv2.dilate(target_px.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    out = np.zeros_like(target_px)
    for lab in np.unique(px_labels[touch & (px_labels > 0) & ~target_px]):
        if lab == target:
            continue
        part = px_labels == lab
        if np.mean(depth_seen[part]) < CHROMA_CLEAR_FRACTION:
            out |= part
    n, holes = cv2.connectedComponents((missing & (px_labels == 0)).astype(np.uint8), connectivity=8)
    ids = np.unique(holes[cv2.dilate((target_px | out).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0])
    return out | (has_label(holes, ids[ids > 0]) & missing)


def _clear_body_cells(under: np.ndarray, depth_seen: np.ndarray, observed: np.ndarray, occupancy: np.ndarray,
                      missing: np.ndarray, miss_c: np.ndarray, disagreement: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A clear target's cells from its prism footprint ``under`` (:func:`prism_footprint`, M x M).

    Observed cells inside the footprint not mostly seen in depth (``depth_seen``) are the **body**: object
    with colour/hole evidence only (occupancy 1, disagreement 1). Cells outside it that the target reached
    only through its body or its holes are the table **behind** it, seen through the plastic: table
    (occupancy 0, not missing) but with disagreement 1 - they are free only if the prism's height, a prior,
    is right (a lower body would cover part of them). The caller trains both with the disagreement variance
    rather than leaving them unknown (unknown cells count as object). Returns new (occupancy, missing,
    miss_c, disagreement) and the body and behind masks."""
    behind = observed & ~under & ~depth_seen & ((occupancy > 0) | missing)
    body = observed & under & ~depth_seen & ~missing
    occupancy = np.where(behind, 0.0, np.where(body, np.maximum(occupancy, 1.0), occupancy))
    disagreement = np.where(behind | body, 1.0, disagreement)
    return occupancy, missing & ~behind, np.where(behind, 0.0, miss_c), disagreement, body, behind


def prism_alternatives(geometry: GridGeometry, silhouette: np.ndarray, table: TableFrame, intrinsics: CameraIntrinsics,
                       height_m: float, depth_seen: np.ndarray, observed: np.ndarray, missing: np.ndarray,
                       factor: float = CLEAR_BODY_HEIGHT_FACTOR) -> tuple[np.ndarray, np.ndarray]:
    """A clear body's prism cells (as :func:`_clear_body_cells` makes them) under the heights ``height_m`` /
    ``factor`` and ``height_m`` x ``factor``: the footprint its height prior allows (the noise map's
    variance of the body, :func:`~gpis_grasp_ros.core.sensing.noise_map.prism_variance`)."""
    under_at = _prism_test(geometry.cell_centers(), silhouette, table, intrinsics)
    return tuple(observed & ~depth_seen & ~missing & under_at(h) for h in (height_m / factor, height_m * factor))


class Target(NamedTuple):
    """The target with what was seen through it."""

    target_px: np.ndarray  # (H, W) bool, its pixels (a clear body: its silhouette)
    target_xy: np.ndarray  # (K, 2) table-frame points (m) the grid must span
    occ: np.ndarray  # (H, W) per-pixel occupancy, seen-through pixels object
    p_c: np.ndarray  # (H, W) colour evidence, seen-through pixels 1
    body_height: float  # m, a clear body's prism height (0 = not a clear body)
    clear_target: bool  # the target is a clear body: its footprint is its prism's
    contact_px: np.ndarray  # (H, W) bool, other objects' pixels in contact with it (:func:`~.objects.in_contact`)
    others_px: np.ndarray  # (H, W) bool, the other objects' pixels seen in depth above the table (kept objects)


def _clear_fragments(target_px: np.ndarray, through: np.ndarray, objects: Objects, frames: AveragedFrames,
                     fit: TableFit, ev: Evidence, table_level: np.ndarray, foot_xy: np.ndarray,
                     params: SensingParams) -> tuple[np.ndarray, np.ndarray]:
    """The other clear fragments of a clear target's body and the body seen through (``through`` with the
    chromatic extension), grown together.

    A clear body falls apart into fragments (a specular ridge, holes at its ends, its cap) joined only by the table
    seen through it: each fragment's extension stops at the others' pixels (they are not candidates), so grown
    from one fragment the body would depend on which one the target pixel fell on. The extension is grown again
    from every clear fragment it touches (fewer than ``CHROMA_CLEAR_FRACTION`` of its pixels seen in depth) until
    it reaches no new one; objects seen in depth stop it as before. The fragments join the target's clear parts
    (:func:`_touching_clear_parts`), not its pixels."""
    raster, px_labels = objects.raster, objects.px_labels
    chroma_z = fit.chroma_z()  # the whole frame's, computed once
    n_lab = int(px_labels.max()) + 1
    clear = np.zeros(n_lab, dtype=bool)
    clear[clear_labels(px_labels, objects.kept, ev.p_d)] = True
    rx, ry, r_ok = raster.cell(foot_xy)  # not over another object's cells in the table plane either
    under = np.where(r_ok, raster.labels[ry, rx], 0)
    members = np.zeros(n_lab, dtype=bool)
    members[objects.target] = True
    members[0] = True  # unlabelled pixels are candidates
    ring = np.ones((3, 3), np.uint8)
    grown = np.zeros_like(target_px), through
    while True:
        mine = members[px_labels] & (px_labels > 0)
        ext = _bounded_extension(target_px, chromatic_extension(
            target_px | mine | through, table_level & members[px_labels] & members[under] & r_ok, chroma_z,
            params.chroma_z_min), params)
        if mine.sum() > target_px.sum() and not ext.any():  # the fragments' extension runs out of the image
            return grown
        grown = mine & ~target_px, through | ext
        reached = (cv2.dilate((ext | through).astype(np.uint8), ring) > 0) & (px_labels > 0)
        new = np.unique(px_labels[reached])
        new = new[clear[new] & ~members[new]]
        if new.size == 0:
            return grown
        members[new] = True


def grow_target(objects: Objects, frames: AveragedFrames, fit: TableFit, meas: Measurement, ev: Evidence,
                occ: np.ndarray, missing_px: np.ndarray, feet: Feet, intrinsics: CameraIntrinsics,
                params: SensingParams) -> Target:
    """The target's pixels with the table seen through it (colour/hole evidence only: object in the occupancy,
    p_c = 1); a clear body's silhouette and prism height; otherwise the holes off its visual hull removed."""
    raster, px_labels, target, target_px = objects.raster, objects.px_labels, objects.target, objects.target_px
    valid, p_d, p_c, foot_xy = frames.valid, ev.p_d, ev.p_c, feet.foot_xy
    table_level = valid & (p_d <= 0.5) & (np.abs(nan_to_num(meas.height)) <= fit.h_thr)
    through = seen_through(raster, target, foot_xy, px_labels, table_level, params.transparent_close_m)
    depth_fraction = float(np.mean(p_d[target_px] > 0.5))
    fragments = np.zeros_like(target_px)
    if params.chroma_z_min > 0 and depth_fraction < CHROMA_CLEAR_FRACTION:  # a clear target's body
        fragments, through = _clear_fragments(target_px, through, objects, frames, fit, ev, table_level, foot_xy,
                                              params)
    target_px, occ, p_c = target_px | through, np.where(through, 1.0, occ), np.where(through, 1.0, p_c)
    target_xy = foot_xy[target_px]
    body_height, clear_target = 0.0, False
    if params.clear_body_prism and depth_fraction < CHROMA_CLEAR_FRACTION:
        # a clear body: with its clear parts, less than CLEAR_BODY_FRACTION of it seen in depth (a partly clear
        # object - the paper's Object A - keeps its clear part uncertain)
        whole = target_px | fragments | _touching_clear_parts(target_px, missing_px, p_d > 0.5, px_labels, target)
        clear_target = bool(np.mean(p_d[whole] > 0.5) < CLEAR_BODY_FRACTION)
    if clear_target:
        # the body's silhouette: its parts closed over gaps narrower than a body's core disc, holes filled
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (CHROMA_CORE_PX, CHROMA_CORE_PX))
        target_px = _filled(cv2.morphologyEx(whole.astype(np.uint8), cv2.MORPH_CLOSE, disc)) & (valid | missing_px) \
            & all_finite(foot_xy)
        body_height, body_xy = clear_body_height(target_px, fit.table, intrinsics,
                                                 known_height_m=params.clear_body_height_m)
        if body_xy.shape[0] >= 3:  # the grid spans the body's footprint, not the table seen through it
            target_xy = body_xy
    elif feet.off_hull.any():
        # no-return pixels next to the target whose ray meets no part of its visual hull (_missing_height: a
        # projector shadow or drop-out on the table beside it) are table the sensor did not measure, not
        # the target: they neither vote object in the cells they fall in nor stretch the grid
        target_px = target_px & ~feet.off_hull
        target_xy = foot_xy[target_px]
    contact_px = in_contact(objects.raster, px_labels, foot_xy, target) & ~target_px
    # the other objects as obstacles: where the sensor measured their surface (a deterministic solid; their
    # colour-only or no-return parts - a clear neighbour's, or the target's own detached specular fringe - are
    # not measured solids and stay what the target's grid makes of them)
    others_px = has_label(px_labels, objects.kept) & (px_labels != target) & ~target_px & valid & (p_d > 0.5)
    return Target(target_px, target_xy, occ, p_c, body_height, clear_target, contact_px, others_px)
