"""What the camera did not measure: returns seen through a clear part, the sensor's shadow, and where a pixel
without a return is placed on its ray (the single-view visual hull of the objects next to it)."""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np
from scipy.special import ndtr

from gpis_grasp_ros.core.noise_model import SensorModel
from gpis_grasp_ros.core.sensing.camera import AveragedFrames, CameraIntrinsics
from gpis_grasp_ros.core.sensing.evidence import Evidence
from gpis_grasp_ros.core.sensing.morphology import _filled, box_max_at, nearest_pixel_lookup
from gpis_grasp_ros.core.sensing.params import (
    MISSING_BRIDGE_M,
    MISSING_HEIGHT_WINDOW_M,
    SHADOW_HULL_SPAN_PX,
    SensingParams,
)
from gpis_grasp_ros.core.sensing.pixel_kernels import (
    all_finite,
    masked_rows,
    nan_to_num,
    pixel_feet,
    ray_cosine,
    vector_norm,
)
from gpis_grasp_ros.core.sensing.ray_kernels import camera_vector, coarse_to_fine, draw_columns, prism_heights
from gpis_grasp_ros.core.sensing.table import Measurement, TableFit, measure_again
from gpis_grasp_ros.core.table_frame import TableFrame


def _missing_height(height: np.ndarray, above: np.ndarray, missing: np.ndarray, rays: np.ndarray, table: TableFrame,
                    intrinsics: CameraIntrinsics, footprint_m: float, window_m: float = MISSING_HEIGHT_WINDOW_M,
                    reach_m: float = MISSING_BRIDGE_M, samples: int = 24,
                    return_tested: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Height (m) above the table at which each pixel without a depth return is placed on its ray (0 = where
    the ray meets the table, also for every pixel with depth).

    What a no-return pixel sees (a specular part, or the table in a projector shadow) lies on its ray
    between the table and the top of the object next to it; seen by a camera tilted by theta, that ray
    segment projects orthographically onto a segment of length H tan(theta) on the table, its foot moving
    *away* from the camera as the height drops. Placing every hole where its ray meets the table would put
    the holes on an object's top up to H tan(theta) behind the object. So:

    1. **Local top H.** A hole region (8-connected in the image) touching pixels seen above the table
       (``above``) belongs next to that object: each of its pixels within ``reach_m`` (on the table) of
       the nearest seen-above pixel takes that pixel's *local top*, the highest height seen within
       ``window_m`` around it. Other holes (drop-outs on the bare table, holes away from any seen
       object) stay on the table.
    2. **Where the ray enters the object's prism.** The object is taken as a prism of height H whose
       image is the object's pixels (seen above the table, or holes): a table point x is under it when
       the vertical segment from x up to H projects onto object pixels (checked at every pixel it
       spans; a single-view visual hull). The pixel
       is placed at the highest point of its ray segment (H down to the table, ``samples`` heights)
       whose foot is under the prism - the first surface of the prism the ray meets: the top face for
       a hole in the top, the wall for a specular wall facing the camera (not in front of the object),
       and on the table (height 0) when the ray meets no such prism (a projector shadow or drop-out
       beside the object). The object's pixels are taken as they are, not dilated: with one pixel of slack
       (for the rounding of the projections) the points of a ray up to a pixel's footprint in front of a
       specular wall passed as under the prism, and so did a projector shadow next to the object's silhouette
       (seen by a tilted camera its pixels lie next to the wall's): the wall's holes were placed a footprint
       in front of the wall, the shadow's on the object. On the head bags (``scripts/bag_iou.py --holes``)
       the median placement error of the specular wall pixels fell from 2-5 mm to 0.5-2.2 mm and that of the
       projector shadows from 17-36 mm to 0-11 mm.

    Heights are along the table normal (m); ``footprint_m`` is a pixel's extent on the table (m).
    ``return_tested``: also return the pixels placed by the prism test (a tested pixel at height 0 is on
    the table beside the object: its ray meets no part of it)."""
    out = np.zeros(height.shape)
    tested = np.zeros(height.shape, dtype=bool)
    if not missing.any() or not above.any():
        return (out, tested) if return_tested else out
    k = max(3, 2 * int(round(0.5 * window_m / max(footprint_m, 1e-6))) + 1)
    dist_px, nearest_at = nearest_pixel_lookup(above)
    n_reg, region = cv2.connectedComponents(missing.astype(np.uint8), connectivity=8)
    touching = np.zeros(n_reg, dtype=bool)
    touching[np.unique(region[missing & (dist_px <= 1.5)])] = True
    touching[0] = False
    vs, us = np.nonzero(missing & touching[region] & (dist_px * footprint_m <= reach_m))
    if vs.size == 0:
        return (out, tested) if return_tested else out
    near = nearest_at((vs, us))
    top_h = box_max_at(np.where(above, nan_to_num(height), 0.0).astype(np.float32), near[:, 0], near[:, 1],
                       k).astype(np.float64)
    ray = rays[vs, us]
    ray_n = ray @ table.n
    ok = (ray_n < -1e-9) & (top_h > 0)
    vs, us, top_h, ray, ray_n = vs[ok], us[ok], top_h[ok], ray[ok], ray_n[ok]
    tested[vs, us] = True
    if vs.size == 0:
        return (out, tested) if return_tested else out
    # the object's pixels, not dilated: a point projecting onto the pixel next to the silhouette is not on it
    obj = above | missing
    # from the top down, the first sample whose foot has its whole vertical segment 0..H seen as object, checked
    # at every image pixel it spans (the object mask as it is, not dilated)
    lift = top_h[:, None] * table.n
    top_foot = ray * ((top_h - table.offset_m) / ray_n)[:, None] - lift
    span = vector_norm(intrinsics.project(top_foot + lift) - intrinsics.project(top_foot))
    inner = np.linspace(0.0, 1.0, int(np.clip(np.ceil(np.nanmax(span, initial=1.0)) + 1, 2, 64)))[1:-1]
    fractions = np.linspace(1.0, 0.0, samples)[:-1]  # the last sample is the table itself (height 0)
    inner = inner[coarse_to_fine(inner.size)]  # the same test, sooner off the object
    placed = prism_heights(np.ascontiguousarray(ray), ray_n, top_h, table.n, float(table.offset_m), fractions, inner,
                           camera_vector(intrinsics), obj)
    out[vs, us] = placed
    return (out, tested) if return_tested else out


def see_through_pixels(points: np.ndarray, height: np.ndarray, solid: np.ndarray, depth: np.ndarray,
                       table: TableFrame, intrinsics: CameraIntrinsics, sensor: SensorModel,
                       slack_m: float = 0.005, max_samples: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Pixels whose return lies behind the solid under a point seen above the table, and where their rays
    enter that solid.

    Objects on a table are height fields: under a point seen at height h the column from its foot up to it
    is solid. The image of that column covers the pixels between the point's and its foot's; a pixel there
    whose return is farther from the camera (optical-axis depth) than the columns over its whole 3 x 3
    neighbourhood, by more than ``3 sqrt(2) sigma_z + slack_m``, saw *through* the object - a clear part and
    what lies behind it (the table, or a blend of both in a stereo sensor) - not its surface. Equivalently,
    along a ray's epipolar line the feet of a height field's visible points move away from the camera
    monotonically; a return whose foot lies behind the foot of a point seen farther up the image breaks
    that order. For a top-down camera a column projects onto its own pixel and nothing is flagged.

    Args:
        points: (H, W, 3) camera-frame points (m); height: (H, W) m along the table normal (NaN = none).
        solid: (H, W) bool, pixels seen above the table whose columns are solid.
        depth: (H, W) m optical-axis depth of each return (NaN = none).
        slack_m: tolerance (m) on top of the noise of the two depths compared.
        max_samples: at most this many samples per column (one per pixel of its image).

    Returns:
        ``(flagged, entry_depth)``: (H, W) bool, and (H, W) m, the depth at which each pixel's ray meets the
        nearest column (inf where it meets none) - the farthest its first surface can be."""
    entry = np.full(height.shape, np.inf)
    if not solid.any():
        return np.zeros(height.shape, dtype=bool), entry
    top = masked_rows(points, solid)
    h = nan_to_num(height[solid])
    foot = top - h[:, None] * table.n
    span = vector_norm(intrinsics.project(top) - intrinsics.project(foot))
    n = np.clip(np.ceil(nan_to_num(span)).astype(np.int64) + 1, 1, max_samples)  # samples per column
    draw_columns(foot, h, n, table.n, False, camera_vector(intrinsics), entry, 0, 0, True)  # the point itself excluded
    # behind the columns of the whole 3 x 3 neighbourhood: a column rounded onto the pixel beside the
    # object's silhouette does not cover it
    behind_all = cv2.dilate(entry.astype(np.float32), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT,
                            borderValue=np.inf).astype(np.float64)
    with np.errstate(invalid='ignore'):
        tol = 3.0 * math.sqrt(2.0) * sensor.sigma(nan_to_num(depth, nan=0.0)) + slack_m
        flagged = np.isfinite(depth) & np.isfinite(behind_all) & (depth - behind_all > tol)
    return flagged, entry


def column_zbuffer(top: np.ndarray, h: np.ndarray, table: TableFrame, intrinsics: CameraIntrinsics,
                   origin: np.ndarray, bounds: tuple[int, int, int, int], max_samples: int = 64) -> np.ndarray:
    """Depth buffer of the solid columns standing under the points ``top`` (n, 3) (camera frame, m; heights
    ``h`` (n,) m along the table normal), seen by a pinhole camera with this image's focal lengths, principal
    point and orientation but centred at ``origin`` (camera frame, m), over its pixels ``bounds`` = (u0, v0, u1,
    v1) (inclusive; they may lie beyond this image's bounds: a viewpoint 5-8 cm aside).

    Returns ``zbuf`` (v1 - v0 + 1, u1 - u0 + 1): ``zbuf[v - v0, u - u0]`` is the nearest depth (m, along the
    optical axis) at which the ray of that camera's pixel (u, v) meets a column, inf where it meets none. Each
    column is sampled at about one sample per pixel of its image (at most ``max_samples``), foot to point."""
    u0, v0, u1, v1 = (int(b) for b in bounds)
    zbuf = np.full((max(v1 - v0 + 1, 1), max(u1 - u0 + 1, 1)), np.inf)
    origin = np.asarray(origin, dtype=np.float64)
    foot = np.asarray(top, dtype=np.float64) - h[:, None] * table.n - origin
    top = np.asarray(top, dtype=np.float64) - origin
    with np.errstate(invalid='ignore', divide='ignore'):
        uv_top, uv_foot = intrinsics.project(top), intrinsics.project(foot)
    ok = (all_finite(uv_top) & all_finite(uv_foot) & (foot[:, 2] > 0)
          & (top[:, 2] > 0))
    top, foot, h, uv_top, uv_foot = top[ok], foot[ok], h[ok], uv_top[ok], uv_foot[ok]
    if top.shape[0] == 0:
        return zbuf
    n = np.clip(np.ceil(vector_norm(uv_top - uv_foot)).astype(np.int64) + 1, 2, max_samples)
    draw_columns(foot, h, n, table.n, True, camera_vector(intrinsics), zbuf, u0, v0, False)
    return zbuf


def occlusion_shadow_pixels(points: np.ndarray, height: np.ndarray, solid: np.ndarray, candidates: np.ndarray,
                            table: TableFrame, intrinsics: CameraIntrinsics, sensor: SensorModel,
                            footprint_m: float, slack_m: float = 0.005,
                            min_hull_span_px: float | None = SHADOW_HULL_SPAN_PX,
                            rays: np.ndarray | None = None) -> np.ndarray:
    """No-return pixels that look at table the sensor's second viewpoint cannot see: its shadow.

    A structured-light sensor needs its projector to light a point, an active-stereo sensor its second imager
    to see it (:class:`~gpis_grasp_ros.core.noise_model.SensorModel`, ``occluder_x_m``, ``occluder_y_m``: that
    viewpoint at (x, y, 0) in the camera frame). Objects on a table are height fields, so under every point seen
    above the table the column down to its foot is solid. A candidate pixel (``candidates``: no return) is in the shadow
    when the table point on its ray

    * is hidden from the second viewpoint by those columns, by more than ``3 sqrt(2) sigma_z + slack_m``
      along that viewpoint's ray (a depth buffer of the columns seen from there, :func:`column_zbuffer`,
      eroded by one pixel so that the gaps between neighbouring columns do not let it through), and
    * does not lie under the object: outside the footprint of the columns (their feet rasterised at
      ``footprint_m``, closed by one cell and hole-filled) - the table point behind a hole in an object's
      top or a specular wall lies under the object, not beside it.

    With ``min_hull_span_px`` (default :data:`SHADOW_HULL_SPAN_PX`) only pixels where the visual hull cannot
    decide are taken: the column from the table point up to the local top of the nearest seen object (its
    highest height within ``MISSING_HEIGHT_WINDOW_M``) images shorter than that many pixels. Seen by a tilted
    camera that column images as a long segment and :func:`_missing_height` already tells a hole beside an
    object (its ray meets no part of the object's prism) from one on it; seen from straight above it images
    onto one or two pixels, a shadow band next to an object passes the prism test on its own pixels, and the
    object was grown by the band (a 3 cm box under a top-down Carmine: 18 % too much area).

    ``rays``: ``intrinsics.rays()``, when known. Returns (H, W) bool. Nothing when the sensor has no second
    viewpoint (``occluder_x_m`` = ``occluder_y_m`` = 0) or nothing is seen above the table."""
    out = np.zeros(candidates.shape, dtype=bool)
    origin = np.array([float(sensor.occluder_x_m), float(sensor.occluder_y_m), 0.0])
    if not origin.any() or not candidates.any() or not solid.any():
        return out
    hts = nan_to_num(height[solid])
    hit_pts, hit = table.ray_intersection(intrinsics.rays() if rays is None else rays)
    cand = candidates & hit
    if not cand.any():
        return out
    vs, us = np.nonzero(cand)
    p = hit_pts[vs, us]
    if min_hull_span_px is not None:
        h_img = np.where(solid, nan_to_num(height), 0.0).astype(np.float32)
        k = max(3, 2 * int(round(0.5 * MISSING_HEIGHT_WINDOW_M / max(footprint_m, 1e-6))) + 1)
        local_top = cv2.dilate(h_img, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
        near = nearest_pixel_lookup(solid)[1]((vs, us))
        top_h = local_top[near[:, 0], near[:, 1]].astype(np.float64)
        span = vector_norm(intrinsics.project(p + top_h[:, None] * table.n) - intrinsics.project(p))
        keep = span < float(min_hull_span_px)
        vs, us, p = vs[keep], us[keep], p[keep]
        if vs.size == 0:
            return out
    # the second viewpoint's depth buffer of the columns, over the pixels where the candidates' table points fall
    q = p - origin
    uv_q = np.round(intrinsics.project(q)).astype(np.int64)
    u0, v0 = uv_q.min(axis=0) - 2
    u1, v1 = uv_q.max(axis=0) + 2
    zbuf = column_zbuffer(points[solid], hts, table, intrinsics, origin, (u0, v0, u1, v1))
    big = np.float32(1e9)
    zbuf = cv2.erode(np.where(np.isfinite(zbuf), zbuf, big).astype(np.float32), np.ones((3, 3), np.uint8),
                     borderType=cv2.BORDER_CONSTANT, borderValue=float(big)).astype(np.float64)
    uv = uv_q - np.array([u0, v0])
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < zbuf.shape[1]) & (uv[:, 1] >= 0) & (uv[:, 1] < zbuf.shape[0])
    u, v = np.clip(uv[:, 0], 0, zbuf.shape[1] - 1), np.clip(uv[:, 1], 0, zbuf.shape[0] - 1)
    tol = 3.0 * math.sqrt(2.0) * sensor.sigma(q[:, 2]) + slack_m
    hidden = inside & (zbuf[v, u] < q[:, 2] - tol)
    # the footprint of the columns in the table plane (hole-filled): a table point under the object is not beside it
    feet, _ = table.to_table(points[solid] - hts[:, None] * table.n)
    res = max(float(footprint_m), 1e-4)
    lo = feet.min(axis=0) - 3.0 * res
    idx = np.floor((feet - lo) / res).astype(np.int64)
    grid = np.zeros((int(idx[:, 1].max()) + 4, int(idx[:, 0].max()) + 4), np.uint8)
    grid[idx[:, 1], idx[:, 0]] = 1
    grid = _filled(cv2.morphologyEx(grid, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)) > 0)
    j = np.floor((table.to_table(p)[0] - lo) / res).astype(np.int64)
    on = (j[:, 0] >= 0) & (j[:, 0] < grid.shape[1]) & (j[:, 1] >= 0) & (j[:, 1] < grid.shape[0])
    under = np.zeros(j.shape[0], dtype=bool)
    under[on] = grid[j[on, 1], j[on, 0]]
    out[vs, us] = hidden & ~under
    return out


def move_seen_through(frames: AveragedFrames, fit: TableFit, meas: Measurement, ev: Evidence,
                      intrinsics: CameraIntrinsics, params: SensingParams
                      ) -> tuple[AveragedFrames, Measurement, Evidence, np.ndarray]:
    """Evidence pixels whose return lies behind the solid under a point seen above the table passed through a
    clear part: their depth is moved to where the ray enters that solid (``see_through_test``), their heights
    and depth evidence measured again. Returns the frames, measurement and evidence after the move, and the
    moved pixels."""
    through_px = np.zeros(frames.valid.shape, dtype=bool)
    if params.see_through_test:
        flagged, entry = see_through_pixels(meas.points, meas.height, frames.valid & (ev.p_d > 0.5), frames.z_mean,
                                            fit.table, intrinsics, params.sensor)
        through_px = flagged & ((ev.p_d > 0.5) | (ev.p_c > 0.5))
        if through_px.any():
            frames = frames._replace(z_mean=np.where(through_px, entry, frames.z_mean))
            meas = measure_again(meas, frames.z_mean, through_px, frames, fit.table, fit.rays, fit.ray_n,
                                 params.sensor)
            p_d = ev.p_d.copy()  # measured again where moved (the same per-pixel operations, on those pixels only)
            p_d[through_px] = ndtr((nan_to_num(meas.height[through_px]) - fit.h_thr) / meas.s_h[through_px])
            ev = ev._replace(p_d=p_d)
    return frames, meas, ev, through_px


def sensor_shadow(frames: AveragedFrames, fit: TableFit, meas: Measurement, ev: Evidence,
                  intrinsics: CameraIntrinsics, params: SensingParams, footprint: float) -> np.ndarray:
    """No-return, table-coloured pixels on table the sensor's second viewpoint cannot see beside an object, where
    the visual hull cannot tell them from it (``shadow_test``): table the sensor did not measure."""
    if not params.shadow_test:
        return np.zeros(frames.valid.shape, dtype=bool)
    return occlusion_shadow_pixels(meas.points, meas.height, frames.valid & (ev.p_d > 0.5),
                                   frames.missing & (ev.p_c <= 0.5), fit.table, intrinsics, params.sensor, footprint,
                                   rays=fit.rays)


class Feet(NamedTuple):
    """Orthographic feet of the pixels on the table."""

    foot_xy: np.ndarray  # (H, W, 2) table frame (m), NaN where unknown
    h_missing: np.ndarray  # (H, W) m, height at which a no-return pixel is placed on its ray (0 = on the table)
    off_hull: np.ndarray  # (H, W) bool, no-return pixels on the table beside an object, or in its shadow
    hit_points: np.ndarray  # (H, W, 3) where the rays meet the plane (camera frame, m)
    ray_cos: np.ndarray  # (H, W) cosine of each ray to the table normal


def place_feet(frames: AveragedFrames, fit: TableFit, meas: Measurement, missing_px: np.ndarray,
               shadow_px: np.ndarray, intrinsics: CameraIntrinsics, footprint: float) -> Feet:
    """Every pixel projected orthographically onto the plane (its foot p - h n); a no-return pixel next to a seen
    object is put where its ray enters that object's prism (:func:`_missing_height`), else where it meets the
    plane."""
    table, rays, valid, height = fit.table, fit.rays, frames.valid, meas.height
    normal = table.n
    h_missing, tested = _missing_height(height, valid & (nan_to_num(height) > fit.h_thr), missing_px, rays, table,
                                        intrinsics, footprint, return_tested=True)
    off_hull = tested & (h_missing <= 0)  # next to an object, but on the table: its ray meets no part of it
    off_hull |= shadow_px  # the sensor's shadow: table it did not measure
    hit_points, hit = table.ray_intersection(rays)
    ray_dot = rays @ normal
    ray_cos = ray_cosine(rays, ray_dot)  # cosine of a ray to the normal
    # a seen pixel's foot p - h n; a no-return pixel's where its ray is h_missing above the plane, dropped onto it
    foot = pixel_feet(rays, ray_dot, meas.points, height, h_missing, valid, hit, normal, float(table.offset_m))
    foot_xy = np.ascontiguousarray(table.to_table(foot)[0])
    foot_xy[~(valid | hit)] = np.nan
    return Feet(foot_xy, h_missing, off_hull, hit_points, ray_cos)
