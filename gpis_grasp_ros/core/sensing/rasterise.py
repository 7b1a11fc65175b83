"""From pixels to grid cells: the square grid in the table plane around the target, each cell the weighted mean of
the pixels whose feet fall in it, gaps between feet filled, cells hidden behind an object assumed table."""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.sensing.camera import AveragedFrames, CameraIntrinsics
from gpis_grasp_ros.core.sensing.clear_body import Target, _clear_body_cells, prism_alternatives, prism_footprint
from gpis_grasp_ros.core.sensing.morphology import box_max_at
from gpis_grasp_ros.core.sensing.occlusion import Feet
from gpis_grasp_ros.core.sensing.params import HIDDEN_SUBCELLS, MISSING_HEIGHT_WINDOW_M, SensingParams
from gpis_grasp_ros.core.sensing.pixel_kernels import (
    all_finite,
    max_tangent,
    nan_to_num,
    nearer_difference_area,
    vector_norm,
)
from gpis_grasp_ros.core.sensing.ray_kernels import camera_vector, under_seen_surface
from gpis_grasp_ros.core.sensing.table import Measurement, TableFit
from gpis_grasp_ros.core.table_frame import TableFrame


def _table_area_weights(foot_xy: np.ndarray, ray_xy: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Weight of each pixel in its cell: the table area its orthographic foot covers, relative to a table
    pixel's (|det| of the Jacobian of the feet over (u, v), clipped to [0, 4]).

    A wall facing the camera projects onto a line (weight ~0): it must not outweigh the top face and the
    table in the cells it borders, since the top face's feet already cover the object's footprint up to the
    wall's base and the table's feet cover the table in front of it. Two sources of a spurious wall weight are
    avoided: (1) depth noise - the feet are median-filtered (3 x 3) first, which keeps the feet of a wall on
    its base line and the step to the top face and the table sharp (a linear blur mixes them into the wall,
    and the |det| of noisy differences is biased upwards); (2) the steps - the Jacobian takes, along each
    image axis, the difference to the neighbour whose foot is nearer, i.e. the one on the same surface: a
    central difference across the top edge or the wall's base gives a wall pixel half the table area between
    the feet on both sides of the step (the gap between the wall's base and the first table foot would be
    counted as object). ``valid``: pixels whose foot is known (seen, or a no-return pixel placed on its ray:
    a specular wall placed on the wall covers no table either); the others take the nominal weight 1."""
    def plane_area(xy: np.ndarray) -> np.ndarray:  # the table's own feet: smooth, central differences
        xu, yu = np.gradient(xy[..., 0], axis=1), np.gradient(xy[..., 1], axis=1)
        xv, yv = np.gradient(xy[..., 0], axis=0), np.gradient(xy[..., 1], axis=0)
        return np.abs(xu * yv - yu * xv)

    if min(foot_xy.shape[:2]) < 3:
        return np.ones(foot_xy.shape[:2])
    feet = np.where(valid[..., None], foot_xy, ray_xy).astype(np.float32)
    feet = np.stack([cv2.medianBlur(np.ascontiguousarray(feet[..., i]), 3) for i in range(2)], axis=-1)
    with np.errstate(invalid='ignore', divide='ignore'):
        ratio = np.where(valid, nearer_difference_area(feet.astype(np.float64)), np.nan) / plane_area(ray_xy)
    return np.clip(np.where(np.isfinite(ratio), ratio, 1.0), 0.0, 4.0)


def _hidden_cells(geometry: GridGeometry, intrinsics: CameraIntrinsics, foot_xy: np.ndarray, height: np.ndarray,
                  above: np.ndarray, tol_m: float) -> np.ndarray:
    """(M, M) bool: grid cells whose table patch a tilted camera cannot see (behind an object).

    The pixel looking at the cell centre sees a surface above the table (``above``) at height h; if
    something stands on the cell, the pixel looking at the point h above the cell centre sees it there
    (its orthographic foot within ``tol_m`` of the centre). If not, the surface seen belongs to an object
    in front of the cell and the cell is hidden: the feet of the neighbouring pixels (the object's far
    edge and the table beyond the occluded strip) must not be interpolated into it."""
    centres = geometry.cell_centers()
    u0, v0, in0 = intrinsics.pixel_index(geometry.to_sensor(centres, 0.0))
    covered = in0 & above[v0, u0]
    h_seen = np.where(covered, nan_to_num(height[v0, u0]), 0.0)
    u1, v1, in1 = intrinsics.pixel_index(geometry.to_sensor(centres, h_seen))
    dist = vector_norm(foot_xy[v1, u1] - centres)
    under = in1 & np.isfinite(dist) & (dist <= tol_m)
    return covered & ~under


def _hidden_fraction(geometry: GridGeometry, intrinsics: CameraIntrinsics, foot_xy: np.ndarray, height: np.ndarray,
                     above: np.ndarray, tol_m: float, tan_max: float, cells: np.ndarray,
                     sub: int = HIDDEN_SUBCELLS, max_samples: int = 256,
                     window_m: float = MISSING_HEIGHT_WINDOW_M) -> np.ndarray:
    """(M, M) fraction of each cell's area hidden behind an object from the camera, on ``sub`` x ``sub``
    points per cell, for the ``cells`` asked (0 elsewhere).

    A table point x is under a surface the camera sees if, at some height h, the pixel looking at the point
    h above x sees a surface (``above``, at ``height``; no-return pixels placed above the table by
    :func:`_missing_height` count) whose orthographic foot is within ``tol_m`` (about a pixel's footprint) of
    x: the point is on that surface. h runs from 0 to the highest surface seen in steps whose feet move by at
    most ``tol_m`` (``tan_max``: the largest tangent of a ray's angle to the table normal). x is hidden when
    the pixel looking at it sees a surface above the table and no height puts x under a seen surface: the
    surface seen stands in front of x, not on it.

    Beyond the far edge of an object's top face (seen by a tilted camera) the table is occluded, so a cell
    crossed by that edge is seen only where the top covers it: its pixels are all object and their mean
    occupancy is 1, whatever part of the cell the top covers. Its occluded part is assumed table, as a
    wholly occluded cell is (the object is a prism whose visible top covers its footprint), so the cell's
    occupancy is the mean over its seen part times the fraction that is seen: the covered fraction. A
    top-down camera hides only a thin strip beside tall objects away from the optical axis."""
    m_y, m_x = geometry.shape
    fine = GridGeometry(geometry.origin_x, geometry.origin_y, geometry.resolution / sub, m_x * sub, m_y * sub,
                        geometry.z, geometry.frame_id, geometry.rotation)

    def pixel(pts: np.ndarray, h: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return intrinsics.pixel_index(fine.to_sensor(pts, h))

    covered = np.repeat(np.repeat(cells, sub, axis=0), sub, axis=1)  # the asked cells' points only
    rows, cols = np.nonzero(covered)  # their centres, as fine.cell_centers() gives them, without the others
    xs = fine.origin_x + (np.arange(fine.width) + 0.5) * fine.resolution
    ys = fine.origin_y + (np.arange(fine.height) + 0.5) * fine.resolution
    points = np.stack([xs[cols], ys[rows]], axis=-1)
    u, v, inside = pixel(points, 0.0)
    seen = inside & above[v, u]
    covered[covered] = seen
    if not covered.any():
        return np.zeros((m_y, m_x))
    todo = points[seen]
    top = float(np.max(height[above]))
    n_h = int(np.clip(math.ceil(top * max(tan_max, 1e-3) / max(tol_m, 1e-6)) + 1, 2, max_samples))
    under = under_seen_surface(np.ascontiguousarray(todo), np.linspace(0.0, top, n_h), fine.rotation_matrix,
                               float(fine.z), camera_vector(intrinsics),
                               np.ascontiguousarray(foot_xy, dtype=np.float64), np.ascontiguousarray(above),
                               float(tol_m))
    # a hidden point is table only if its occlusion shadow ends on the table: the ray over the local top of
    # what hides it (highest surface within window_m of the pixel looking at it) lands on the table beyond,
    # not on the object (a lower part of the object behind a taller one is object, not table)
    k = max(3, 2 * int(round(0.5 * window_m / max(tol_m, 1e-6))) + 1)
    rest = np.flatnonzero(~under)
    u, v, _ = pixel(todo[rest], 0.0)
    local_top = box_max_at(np.where(above, height, 0.0).astype(np.float32), v, u, k)
    u, v, inside = pixel(todo[rest], local_top.astype(np.float64))
    under[rest[inside & above[v, u]]] = True
    hidden = covered.copy()
    hidden[covered] = ~under
    return hidden.reshape(m_y, sub, m_x, sub).mean(axis=(1, 3))


def grid_cells(side: float, params: SensingParams, footprint: float = 0.0) -> int:
    """M for a grid of side ``side`` (m): ``grid_size`` when forced, else cells of ``cell_size_m``, or of
    ``min_pixels_per_cell`` pixel footprints (``footprint``, m) where that is larger, clamped to
    [``min_grid_cells``, ``max_grid_cells``] (the cells then shrink or grow). The cell size is physical - the
    gripper's jaw noise, and at least two depth samples across (the grid cannot hold detail the pixels do not
    sample) - so the planning problem does not depend on the object's size."""
    if params.grid_size > 0:
        return int(params.grid_size)
    cell = max(params.cell_size_m, params.min_pixels_per_cell * footprint)
    m = int(math.ceil(side / cell - 1e-9))
    return int(min(max(m, params.min_grid_cells), params.max_grid_cells))


def grid_around(target_xy: np.ndarray, table: TableFrame, params: SensingParams, frame_id: str,
                footprint: float = 0.0) -> GridGeometry:
    """The square M x M grid in the table plane: the target's footprint bounding box plus ``margin`` of its
    larger side on every side, M from :func:`grid_cells`."""
    lo, hi = target_xy.min(axis=0), target_xy.max(axis=0)
    side = float(max(hi - lo)) * (1.0 + 2.0 * params.margin)
    side = max(side, 1e-3)
    m = grid_cells(side, params, footprint)
    centre = 0.5 * (lo + hi)
    return table.grid(centre[0] - side / 2, centre[1] - side / 2, side / m, m, m, frame_id)


class Cells(NamedTuple):
    """The target's grid maps (M x M) and where the pixels fall in the grid."""

    geometry: GridGeometry
    row: np.ndarray  # (H, W) float, grid row of each pixel's foot (NaN = none)
    col: np.ndarray  # (H, W) float, grid column
    in_grid: np.ndarray  # (H, W) bool, foot inside the grid
    informative: np.ndarray  # (H, W) bool, in the grid and valid or a target hole
    observed: np.ndarray  # cells seen (the others are assumed table)
    occluded: np.ndarray  # cells in the image hidden behind something above the table
    occupancy: np.ndarray  # fraction of the cell the target covers
    missing: np.ndarray  # cells mostly the target's no-return pixels
    miss_c: np.ndarray  # fraction of the target's no-return pixels
    disagreement: np.ndarray  # rho, |mean p_d - mean p_c| over the cell's valid pixels
    depth_var: np.ndarray  # m^2, mean averaged depth variance of the cell's valid pixels
    body: np.ndarray  # a clear body's prism cells
    behind: np.ndarray  # the table seen through a clear body
    contact: np.ndarray  # cells mostly another object in contact with the target (table not seen)
    obstacle: np.ndarray  # cells mostly another object (any, in contact or not): where a jaw cannot be
    body_alternatives: tuple[np.ndarray, ...] = ()  # its prism cells under the other plausible heights


def rasterise(target: Target, missing_px: np.ndarray, frames: AveragedFrames, fit: TableFit, meas: Measurement,
              p_d: np.ndarray, feet: Feet, footprint: float, intrinsics: CameraIntrinsics, params: SensingParams,
              geometry: GridGeometry) -> Cells:
    """Every pixel averaged into the cell of ``geometry`` (:func:`grid_around`) under its foot, weighted by the table
    area its foot covers; other objects' pixels count as table (uncertain where the object touches the target).
    Cells no pixel reaches take their centre's image pixel if it sees the table
    there, else they are occluded; the part of a cell hidden behind an object counts as table."""
    valid, height, var_z, h_thr = frames.valid, meas.height, meas.var_z, fit.h_thr
    foot_xy, target_px, occ, p_c = feet.foot_xy, target.target_px, target.occ, target.p_c
    h, w = valid.shape
    m = geometry.width
    res = geometry.resolution
    col = np.floor((foot_xy[..., 0] - geometry.origin_x) / res)
    row = np.floor((foot_xy[..., 1] - geometry.origin_y) / res)
    in_grid = np.isfinite(col) & np.isfinite(row) & (col >= 0) & (col < m) & (row >= 0) & (row < m)
    miss_t = missing_px & target_px
    informative = in_grid & (valid | miss_t)

    def occ_t(i):  # other objects are not the target: table in its grid
        return np.where(target_px[i], occ[i], 0.0)

    # only the informative pixels reach a cell: the area weights are taken over their bounding box (plus the
    # 2 pixels the median filter and the differences read around it)
    vs, us = np.nonzero(informative)
    cell = (row[vs, us] * m + col[vs, us]).astype(np.int64)
    box = np.s_[max(int(vs.min()) - 2, 0):int(vs.max()) + 3, max(int(us.min()) - 2, 0):int(us.max()) + 3]
    wt_box = _table_area_weights(foot_xy[box], fit.table.to_table(feet.hit_points[box])[0],
                                 all_finite(foot_xy[box]))
    wt = wt_box[vs - box[0].start, us - box[1].start]
    contact_px, others_px = target.contact_px, target.others_px
    px = (vs, us)  # the per-pixel values at the informative pixels only
    vp = valid[px].astype(np.float64)
    seen_in_depth = target_px[px] & valid[px] & (p_d[px] > 0.5)
    sums = [np.bincount(cell, weights=wt * v, minlength=m * m)
            for v in (np.ones(vs.size), occ_t(px), p_d[px] * vp, p_c[px] * vp, vp,
                      miss_t[px].astype(np.float64), np.where(valid[px], var_z[px], 0.0),
                      seen_in_depth.astype(np.float64), contact_px[px].astype(np.float64),
                      others_px[px].astype(np.float64))]
    n_inf, s_occ, s_pd, s_pc, s_valid, s_miss, s_var, s_seen, s_contact, s_others = (s.reshape(m, m) for s in sums)
    depth_seen_cell = s_seen > 0.5 * np.maximum(n_inf, 1e-12)  # mostly the target seen in depth (before any fill)

    # cells between the feet of neighbouring pixels (a grid finer than the pixels' footprint on the
    # table): the mean of their observed 8-neighbours, if at least 3, for as many cells as a footprint spans
    stats = [s_occ, s_pd, s_pc, s_valid, s_miss, s_var, s_contact, s_others]
    kernel3 = np.ones((3, 3), np.float32)
    hidden = _hidden_cells(geometry, intrinsics, foot_xy, height, valid & (nan_to_num(height) > h_thr),
                           max(1.5 * res, 2.0 * footprint))  # behind an object: not interpolated
    # cells holding only the feet of holes on the table beside the target (off its visual hull) are not between
    # the feet of seen pixels: no measurement, not interpolated from the target's cells next to them
    off_hull = feet.off_hull
    sel = in_grid & off_hull
    unmeasured = np.bincount((row[sel] * m + col[sel]).astype(np.int64), minlength=m * m).reshape(m, m) > 0
    for _ in range(int(math.ceil(footprint / res))):
        seen = (n_inf > 0).astype(np.float32)
        n_nb = cv2.filter2D(seen, -1, kernel3, borderType=cv2.BORDER_CONSTANT)
        fill = (n_inf == 0) & (n_nb >= 3) & ~hidden & ~unmeasured
        if not fill.any():
            break
        for arr in stats:
            mean = np.where(n_inf > 0, arr / np.maximum(n_inf, 1.0), 0.0).astype(np.float32)
            arr[fill] = (cv2.filter2D(mean, -1, kernel3, borderType=cv2.BORDER_CONSTANT)[fill] / n_nb[fill])
        n_inf[fill] = 1.0

    # cells no pixel reaches: their centre's image pixel (occluded, outside the image, or a target hole)
    h_missing = feet.h_missing
    empty = n_inf == 0
    occluded = np.zeros((m, m), dtype=bool)
    if empty.any():
        rr, cc = np.nonzero(empty)
        ui, vi, inside = intrinsics.pixel_index(geometry.to_sensor(geometry.cell_centers()[rr, cc]))
        sees_table = inside & valid[vi, ui] & (nan_to_num(height[vi, ui]) <= h_thr)
        # a target hole placed on its ray above the table (_missing_height) is not at this cell: hidden, not a hole
        sees_target_hole = inside & miss_t[vi, ui] & (h_missing[vi, ui] <= 0)
        occluded[rr, cc] = inside & ~sees_table & ~sees_target_hole
        take = sees_table | sees_target_hole
        r2, c2, v2, u2 = rr[take], cc[take], vi[take], ui[take]
        n_inf[r2, c2] = 1.0
        s_occ[r2, c2] = occ_t((v2, u2))
        valid_2 = valid[v2, u2].astype(np.float64)
        s_pd[r2, c2], s_pc[r2, c2] = p_d[v2, u2] * valid_2, p_c[v2, u2] * valid_2
        s_valid[r2, c2], s_miss[r2, c2] = valid_2, miss_t[v2, u2]
        s_var[r2, c2] = np.where(valid[v2, u2], var_z[v2, u2], 0.0)
        s_contact[r2, c2] = contact_px[v2, u2]
        s_others[r2, c2] = others_px[v2, u2]
    observed = n_inf > 0
    n_safe = np.maximum(n_inf, 1.0)
    # the part of a cell hidden behind an object is table, like a wholly occluded cell (_hidden_fraction)
    ray_cos = feet.ray_cos
    hidden_part = _hidden_fraction(geometry, intrinsics, foot_xy, np.where(valid, nan_to_num(height), h_missing),
                                   (valid & (nan_to_num(height) > h_thr)) | (h_missing > 0), footprint,
                                   max_tangent(ray_cos),
                                   observed & (s_occ > 0))
    occupancy = np.clip(np.where(observed, s_occ / n_safe * (1.0 - hidden_part), 0.0), 0.0, 1.0)
    miss_c = s_miss / n_safe
    missing = observed & (miss_c > params.missing_cell_fraction)
    with np.errstate(invalid='ignore', divide='ignore'):
        rho_c = np.abs(s_pd - s_pc) / s_valid
        depth_var = np.where(s_valid > 0, s_var / s_valid, 0.0)
    disagreement = np.where(observed & (s_valid > 0), np.clip(nan_to_num(rho_c), 0.0, 1.0), 0.0)
    # another object in contact: the line between them was inferred (a split), so the table the target's grid
    # has there is a hypothesis, trained with the disagreement variance of the share it holds, never unknown
    contact_frac = np.where(observed, np.clip(s_contact / n_safe, 0.0, 1.0), 0.0)
    contact = contact_frac > params.uncertainty_threshold
    disagreement = np.maximum(disagreement, contact_frac)
    body = behind = np.zeros((m, m), dtype=bool)
    alternatives: tuple[np.ndarray, ...] = ()
    if target.clear_target:
        occupancy, missing, miss_c, disagreement, body, behind = _clear_body_cells(
            prism_footprint(geometry.cell_centers(), target_px, fit.table, intrinsics, target.body_height),
            depth_seen_cell, observed, occupancy, missing, miss_c, disagreement)
        if params.clear_body_height_m <= 0:  # the height from a prior: its footprint under the other heights
            alternatives = prism_alternatives(geometry, target_px, fit.table, intrinsics, target.body_height,
                                              depth_seen_cell, observed, missing)
    # the other objects are where no jaw can be: cells mostly their pixels and not the target (nor its body)
    obstacle = observed & (s_others / n_safe > 0.5) & (occupancy < 0.5) & ~body
    return Cells(geometry, row, col, in_grid, informative, observed, occluded, occupancy, missing, miss_c,
                 disagreement, depth_var, body, behind, contact, obstacle, alternatives)
