"""The target's window: the part of the image a target point's grid depends on.

A grid around a target point (``target`` ``pixel`` or ``table``) depends on what stands on the table near that
point and on what hides that table from the camera: the pixels whose ray meets the table in a rectangle of the
table plane around the point, and those whose point's column - from its foot on the table to where its ray meets
the table, the stretch of table it hides - crosses the rectangle. Their bounding box is the window. The stages after
the table run on the window with everything the table fit took of the whole frame (:class:`~.table.TableFit`: plane,
thresholds, colour support, noise, footprint, extent, chromaticity), so the window's grid is the whole frame's up to
a few cells. The rectangle starts as the square of half-side :data:`~.params.SUPPORT_RADIUS_M` around the point (the
table around the target whose colour the objects stand out from) and grows until neither the target nor an object
in contact with it is cut by the window and the target's grid lies in the rectangle
(:func:`~.segment.segment_frames`). The work follows the window, not the frame.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np
from numba import njit

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.sensing.camera import AveragedFrames, CameraIntrinsics
from gpis_grasp_ros.core.sensing.params import SensingParams, SensingResult
from gpis_grasp_ros.core.sensing.pixel_kernels import mask_bounds
from gpis_grasp_ros.core.sensing.table import Measurement, TableFit


class Window(NamedTuple):
    """A pixel box (inclusive) and the table-frame rectangle it was made for."""

    u0: int
    v0: int
    u1: int
    v1: int
    region: tuple[float, float, float, float]  # (x_min, y_min, x_max, y_max), table frame (m)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.v1 - self.v0 + 1, self.u1 - self.u0 + 1)

    @property
    def slices(self) -> tuple[slice, slice]:
        return (slice(self.v0, self.v1 + 1), slice(self.u0, self.u1 + 1))


def target_point(fit: TableFit, intrinsics: CameraIntrinsics, params: SensingParams) -> np.ndarray | None:
    """Table-frame (x, y) of the target point (``pixel``: where its ray meets the plane; ``table``: as given), or
    None when the target is chosen among all objects (``largest``, ``nearest_center``) or the pixel's ray misses the
    table or lies outside the image (the whole frame's segmentation gives the reason)."""
    if params.target == 'table':
        return np.asarray(params.target_point, dtype=np.float64)
    if params.target != 'pixel':
        return None
    u, v = (int(round(c)) for c in params.target_point)
    if not (0 <= u < intrinsics.width and 0 <= v < intrinsics.height):
        return None
    hit_pt, hit = fit.table.ray_intersection(fit.rays[v, u])
    if not bool(hit):
        return None
    return fit.table.to_table(hit_pt)[0]


def square(point: np.ndarray, half_m: float) -> tuple[float, float, float, float]:
    """The table-frame square of half-side ``half_m`` (m) centred on ``point``."""
    return (float(point[0]) - half_m, float(point[1]) - half_m, float(point[0]) + half_m, float(point[1]) + half_m)


def _roi_box(intrinsics_shape: tuple[int, int], params: SensingParams) -> tuple[int, int, int, int]:
    h, w = intrinsics_shape
    u_lo, v_lo, u_hi, v_hi = 0, 0, w - 1, h - 1
    if params.roi_px is not None:
        u_lo, v_lo = max(u_lo, math.ceil(params.roi_px[0])), max(v_lo, math.ceil(params.roi_px[1]))
        u_hi, v_hi = min(u_hi, math.floor(params.roi_px[2])), min(v_hi, math.floor(params.roi_px[3]))
    return u_lo, v_lo, u_hi, v_hi


def window(fit: TableFit, meas: Measurement, region: tuple[float, float, float, float],
           params: SensingParams) -> Window | None:
    """The window (module docstring) of the table-frame rectangle ``region``, within the pixel ROI; None when it is
    the whole image (or the whole ROI): nothing to gain. Points higher than ``max_object_height_m`` are not on the
    table and hide nothing the segmentation uses."""
    u_lo, v_lo, u_hi, v_hi = _roi_box(fit.inlier.shape, params)
    rot = fit.table.rotation
    box = _region_box(np.ascontiguousarray(fit.rays), np.ascontiguousarray(meas.points),
                      np.ascontiguousarray(meas.height), fit.table.n, float(fit.table.offset_m),
                      np.ascontiguousarray(rot[:, 0]), np.ascontiguousarray(rot[:, 1]), *(float(c) for c in region),
                      float(params.max_object_height_m))
    u0, v0, u1, v1 = max(box[0], u_lo), max(box[1], v_lo), min(box[2], u_hi), min(box[3], v_hi)
    if u0 > u1 or v0 > v1 or (u0, v0, u1, v1) == (u_lo, v_lo, u_hi, v_hi):
        return None
    return Window(int(u0), int(v0), int(u1), int(v1), tuple(float(c) for c in region))


@njit(cache=True, nogil=True)
def _meets(fx, fy, tx, ty, x0, y0, x1, y1):
    """Whether the segment (fx, fy) - (tx, ty) meets the rectangle [x0, x1] x [y0, y1] (Liang-Barsky clipping)."""
    lo, hi = 0.0, 1.0
    for p, q in ((fx - tx, fx - x0), (tx - fx, x1 - fx), (fy - ty, fy - y0), (ty - fy, y1 - fy)):
        if p == 0.0:
            if q < 0.0:
                return False
        else:
            t = q / p
            if p < 0.0:
                lo = max(lo, t)
            else:
                hi = min(hi, t)
            if lo > hi:
                return False
    return True


@njit(cache=True, nogil=True)
def _region_box(rays, points, height, n, offset, ax, ay, x0, y0, x1, y1, h_max):
    """Bounding box (u0, v0, u1, v1) of the pixels whose ray meets the plane in the rectangle, or whose point
    (height below ``h_max``) has its column - foot to ray hit - meet it."""
    hgt, wid = height.shape
    u0, v0, u1, v1 = wid, hgt, -1, -1
    for v in range(hgt):
        for u in range(wid):
            dn = rays[v, u, 0] * n[0] + rays[v, u, 1] * n[1] + rays[v, u, 2] * n[2]
            has_t = dn < -1e-9
            tx = ty = 0.0
            if has_t:
                s = -offset / dn
                hx, hy, hz = rays[v, u, 0] * s, rays[v, u, 1] * s, rays[v, u, 2] * s
                tx = hx * ax[0] + hy * ax[1] + hz * ax[2]
                ty = hx * ay[0] + hy * ay[1] + hz * ay[2]
            has_p = height[v, u] < h_max  # False for NaN (no return)
            fx = fy = 0.0
            if has_p:
                fx = points[v, u, 0] * ax[0] + points[v, u, 1] * ax[1] + points[v, u, 2] * ax[2]
                fy = points[v, u, 0] * ay[0] + points[v, u, 1] * ay[1] + points[v, u, 2] * ay[2]
                if not has_t:
                    tx, ty = fx, fy
            elif has_t:
                fx, fy = tx, ty
            else:
                continue
            if _meets(fx, fy, tx, ty, x0, y0, x1, y1):
                u0, v0, u1, v1 = min(u0, u), min(v0, v), max(u1, u), max(v1, v)
    return u0, v0, u1, v1


def crop(win: Window, frames: AveragedFrames, fit: TableFit, meas: Measurement, intrinsics: CameraIntrinsics,
         params: SensingParams) -> tuple[AveragedFrames, TableFit, Measurement, CameraIntrinsics, SensingParams]:
    """The frames, table fit, measurement, intrinsics (principal point shifted) and parameters (target pixel and
    pixel ROI shifted) of the window: what segmentation of a crop at the window sees, with the whole frame's table
    fit (its statistics of the frame's table) and independent frame count."""
    sl = win.slices
    frames = frames._replace(rgb_mean=frames.rgb_mean[sl], z_mean=frames.z_mean[sl], count=frames.count[sl],
                             valid=frames.valid[sl], missing=frames.missing[sl], count_eff=frames.count_eff[sl])
    whole_z = fit.chroma_z
    fit = fit._replace(rays=fit.rays[sl], ray_n=fit.ray_n[sl], band=fit.band[sl], inlier=fit.inlier[sl],
                       support=fit.support[sl], chroma_z=lambda: whole_z()[sl])
    meas = Measurement(*(a[sl] for a in meas))
    h, w = win.shape
    intr = CameraIntrinsics(intrinsics.fx, intrinsics.fy, intrinsics.cx - win.u0, intrinsics.cy - win.v0, w, h)
    changes = {}
    if params.target == 'pixel':
        changes['target_point'] = (params.target_point[0] - win.u0, params.target_point[1] - win.v0)
    if params.roi_px is not None:
        u0, v0, u1, v1 = params.roi_px
        changes['roi_px'] = (u0 - win.u0, v0 - win.v0, u1 - win.u0, v1 - win.v0)
    return frames, fit, meas, intr, dataclasses.replace(params, **changes) if changes else params


def grown(win: Window, target_px: np.ndarray, contact_px: np.ndarray, grid: GridGeometry,
          intrinsics: CameraIntrinsics, params: SensingParams) -> tuple[float, float, float, float] | None:
    """The larger region a window needs, given the target's pixels, the pixels of the objects in contact with it
    (window image) and its grid found in it (``intrinsics`` and ``params`` of the whole image), or None when it holds
    what the whole frame's segmentation would see: the target and the objects it touches (where they were split from
    it is decided on both) ``border_px`` clear of the window's edges that are not the image's (else the region
    doubled about its centre) and the grid, a cell around, within the region (else the region extended over it)."""
    x0, y0, x1, y1 = win.region
    v_min, v_max, u_min, u_max = mask_bounds(target_px | contact_px)
    if touches_edge(win, (u_min, v_min, u_max, v_max), intrinsics, params):
        cx, cy, hx, hy = (x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0
        return (cx - hx, cy - hy, cx + hx, cy + hy)
    gx0, gy0 = grid.origin_x - grid.resolution, grid.origin_y - grid.resolution
    gx1, gy1 = grid.origin_x + grid.size_m[0] + grid.resolution, grid.origin_y + grid.size_m[1] + grid.resolution
    if gx0 >= x0 and gy0 >= y0 and gx1 <= x1 and gy1 <= y1:
        return None
    return (min(x0, gx0), min(y0, gy0), max(x1, gx1), max(y1, gy1))


def touches_edge(win: Window, bbox: tuple[int, int, int, int], intrinsics: CameraIntrinsics,
                 params: SensingParams) -> bool:
    """Whether the box ``bbox`` (u0, v0, u1, v1, window pixels; ``intrinsics`` and ``params`` the image's) comes
    within ``border_px`` of an edge of the window that is not an edge of the image (or of the pixel ROI)."""
    h, w = win.shape
    b = params.border_px
    u_lo, v_lo, u_hi, v_hi = _roi_box((intrinsics.height, intrinsics.width), params)
    return bool((win.u0 > u_lo and bbox[0] < b) or (win.v0 > v_lo and bbox[1] < b)
                or (win.u1 < u_hi and bbox[2] > w - 1 - b) or (win.v1 < v_hi and bbox[3] > h - 1 - b))


def uncrop(result: SensingResult, win: Window, frames: AveragedFrames, meas: Measurement,
           intrinsics: CameraIntrinsics) -> SensingResult:
    """``result`` of the window with its pixel maps placed in the whole image: the averaged depth, returns and
    heights of the whole frame outside the window (as moved by the see-through test inside it), the frame's no-return
    pixels as missing outside it, no evidence, labels or target there (NaN for the per-pixel noise)."""
    sl = win.slices
    shape = frames.valid.shape

    def place(a: np.ndarray, outside: np.ndarray | float | bool) -> np.ndarray:
        out = np.array(outside, dtype=a.dtype, copy=True) if isinstance(outside, np.ndarray) else \
            np.full(shape + a.shape[2:], outside, dtype=a.dtype)
        out[sl] = a
        return out

    u0, v0, u1, v1 = result.bbox_px
    opt = {}
    for name in ('seen_through_px', 'shadow_px'):
        if getattr(result, name) is not None:
            opt[name] = place(getattr(result, name), False)
    return dataclasses.replace(
        result, mean_depth=place(result.mean_depth, frames.z_mean), valid_count=place(result.valid_count,
                                                                                       frames.count.astype(np.int64)),
        height=place(result.height, meas.height), depth_mask=place(result.depth_mask, False),
        rgb_mask=place(result.rgb_mask, False), missing_mask=place(result.missing_mask, frames.missing),
        object_mask=place(result.object_mask, False), labels_px=place(result.labels_px, 0),
        occupancy_px=place(result.occupancy_px, 0.0), noise_px=place(result.noise_px, np.nan),
        disagreement_px=place(result.disagreement_px, 0.0),
        bbox_px=(u0 + win.u0, v0 + win.v0, u1 + win.u0, v1 + win.v0), intrinsics=intrinsics,
        window_px=(win.u0, win.v0, win.u1, win.v1), **opt)
