"""The table plane: given or robustly fitted to the whole cloud, heights above it and its inlier pixels."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import cv2
import numpy as np

from gpis_grasp_ros.core.median import median
from gpis_grasp_ros.core.noise_model import SensorModel
from gpis_grasp_ros.core.sensing.camera import AveragedFrames, CameraIntrinsics
from gpis_grasp_ros.core.sensing.chroma import frame_chromaticity
from gpis_grasp_ros.core.sensing.params import SUPPORT_MIN_PX, SUPPORT_RADIUS_M, SensingParams
from gpis_grasp_ros.core.sensing.pixel_kernels import masked_rows, nan_to_num, norm_of
from gpis_grasp_ros.core.table_frame import TableFrame, fit_table_plane


class TableFit(NamedTuple):
    """The table plane and what segmentation derives from it once."""

    table: TableFrame  # camera frame, normal n towards the camera
    rays: np.ndarray  # (H, W, 3) camera rays of the pixels
    ray_n: np.ndarray  # (H, W) |ray . n|: height error per unit depth error along the ray
    band: np.ndarray  # (H, W) m, plane inlier band
    inlier: np.ndarray  # (H, W) bool, pixels on the plane
    h_thr: float  # m, depth-evidence height threshold
    support: np.ndarray  # (H, W) bool, the inliers of the table around the target (colour model)
    chroma_z: Callable[[], np.ndarray]  # (H, W) the chromaticity z-scores against the inliers (chroma.py), lazily
    noise_ratio: float  # the inliers' measured RMS height over the sensor model's (1 without inliers)
    footprint: float  # m, a pixel's extent on the table at the inliers' median depth (pixel_footprint)
    rim_xy: np.ndarray  # (K, 2) table frame (m), the feet of the inlier region's rim: the table's extent is their hull


class Measurement(NamedTuple):
    """Per-pixel geometry of the averaged depths."""

    points: np.ndarray  # (H, W, 3) camera-frame points (m), NaN where no return
    height: np.ndarray  # (H, W) m above the plane along its normal, NaN where no return
    z_safe: np.ndarray  # (H, W) m, depth, the plane's offset where no return
    var_z: np.ndarray  # (H, W) m^2, variance of the averaged depth
    s_h: np.ndarray  # (H, W) m, its noise projected on the normal


def _table_frame(points: np.ndarray, valid: np.ndarray, params: SensingParams) -> TableFrame:
    """Given (``table_plane``, ``table_depth_m``) or fitted (MSAC over the whole cloud) table plane."""
    if params.table_plane is not None:
        frame = TableFrame.from_plane(*params.table_plane)
    elif params.table_depth_m is not None:
        if not (math.isfinite(params.table_depth_m) and params.table_depth_m > 0):
            raise ValueError(f'table_depth_m must be positive metres, got {params.table_depth_m}')
        frame = TableFrame.from_plane(0.0, 0.0, -1.0, float(params.table_depth_m))
    else:
        return fit_table_plane(points, params.sensor, band_sigmas=params.plane_band_sigmas,
                               band_floor_m=params.plane_band_floor_m, min_inlier_fraction=params.min_plane_fraction,
                               max_tilt_deg=params.max_tilt_deg, mask=valid)
    if frame.tilt_deg > params.max_tilt_deg:
        raise ValueError(f'the given table plane is seen at {frame.tilt_deg:.0f} degrees (more than '
                         f'{params.max_tilt_deg:.0f}): edge-on')
    return frame


def measure(z: np.ndarray, frames: AveragedFrames, table: TableFrame, rays: np.ndarray, ray_n: np.ndarray,
            sensor: SensorModel, points: np.ndarray | None = None) -> Measurement:
    """Camera points, heights above the plane (NaN where no return), depths with the plane's offset where
    none, their averaged variance and the height noise s_h of depths ``z`` (m) - for the frames' returns,
    and again after the see-through test moved some. ``points``: the camera points of ``z``, when known."""
    valid = frames.valid
    pts = rays * np.where(valid, z, np.nan)[..., None] if points is None else points
    z_ok = np.where(valid, z, table.offset_m)
    var = sensor.variance(z_ok) / np.maximum(frames.count_eff, 1.0)
    return Measurement(pts, np.where(valid, pts @ table.n + table.offset_m, np.nan), z_ok, var,
                       np.sqrt(var) * np.maximum(ray_n, 1e-3))


def measure_again(meas: Measurement, z: np.ndarray, changed: np.ndarray, frames: AveragedFrames, table: TableFrame,
                  rays: np.ndarray, ray_n: np.ndarray, sensor: SensorModel) -> Measurement:
    """:func:`measure` of depths ``z`` that differ from those ``meas`` was taken of only at the pixels ``changed``:
    the noise there computed again (the same per-pixel operations), the points and heights of the whole frame."""
    valid = frames.valid
    pts = rays * np.where(valid, z, np.nan)[..., None]
    z_ok = np.where(valid, z, table.offset_m)
    var, s_h = meas.var_z.copy(), meas.s_h.copy()
    var[changed] = sensor.variance(z_ok[changed]) / np.maximum(frames.count_eff[changed], 1.0)
    s_h[changed] = np.sqrt(var[changed]) * np.maximum(ray_n[changed], 1e-3)
    return Measurement(pts, np.where(valid, pts @ table.n + table.offset_m, np.nan), z_ok, var, s_h)


def fit_table(frames: AveragedFrames, intrinsics: CameraIntrinsics,
              params: SensingParams) -> tuple[TableFit, Measurement]:
    """The table plane from the whole valid cloud (or as given), its inliers, the depth-evidence threshold
    max(``height_threshold``, 2 x the inliers' RMS), the inliers' noise against the sensor model and a pixel's
    footprint there (statistics of the frame's table, the same for any window of it), and the pixels' heights."""
    valid = frames.valid
    rays = intrinsics.rays()
    points = rays * np.where(valid, frames.z_mean, np.nan)[..., None]
    table = _table_frame(points, valid, params)
    ray_n = np.abs(rays @ table.n)  # height error per unit depth error along the ray
    meas = measure(frames.z_mean, frames, table, rays, ray_n, params.sensor, points)
    band = np.maximum(params.plane_band_floor_m, params.plane_band_sigmas * params.sensor.sigma(meas.z_safe))
    inlier = valid & (np.abs(nan_to_num(meas.height, nan=1.0)) <= band)
    if inlier.sum() < 20:
        raise ValueError(f'only {int(inlier.sum())} pixels lie on the table plane: cannot estimate the table '
                         '(check table_plane / table_depth_m, or the depth image)')
    rms = float(np.sqrt(np.mean(meas.height[inlier] ** 2)))
    h_thr = max(params.height_threshold, 2.0 * rms)
    support = target_support(inlier, points, table, rays, params, intrinsics, float(np.max(band)))
    fit = TableFit(table, rays, ray_n, band, inlier, h_thr, support, frame_chromaticity(frames.rgb_mean, inlier),
                   noise_ratio(meas.height, meas.s_h, inlier), 0.0, rim_feet(inlier, meas, table))
    return fit._replace(footprint=pixel_footprint(frames.z_mean, fit, intrinsics)), meas


def rim_feet(inlier: np.ndarray, meas: Measurement, table: TableFrame) -> np.ndarray:
    """Table-frame feet (m) of the rim of the inlier region: the feet of plane points are a projective image of the
    pixels, so interior pixels are never vertices of their convex hull, the table's extent."""
    rim = inlier & ~cv2.erode(inlier.astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT,
                              borderValue=0).astype(bool)
    foot = meas.points[rim] - nan_to_num(meas.height[rim])[:, None] * table.n  # p - h n, as place_feet's feet
    return table.to_table(foot)[0]


def noise_ratio(height: np.ndarray, s_h: np.ndarray, inlier: np.ndarray) -> float:
    """The table inliers' measured RMS height over their modelled one ``s_h`` (1 without inliers): a filtered depth
    image is less noisy than the sensor model, a rough table or a misfitted plane more."""
    res_h = height[inlier]
    model = s_h[inlier]
    return math.sqrt(float(np.mean(res_h ** 2)) / max(float(np.mean(model ** 2)), 1e-18)) if res_h.size else 1.0


def target_support(inlier: np.ndarray, points: np.ndarray, table: TableFrame, rays: np.ndarray,
                   params: SensingParams, intrinsics: CameraIntrinsics, band_m: float) -> np.ndarray:
    """The plane's inliers of the table that supports the target: those within ``SUPPORT_RADIUS_M`` of the
    target point in the table plane (``target`` ``pixel``: where its ray meets the plane; ``table``: the
    point), all inliers for the other targets or when fewer than ``SUPPORT_MIN_PX`` lie that close.

    The plane may hold several surfaces - a board on a table, a sheet on a cloth, the world beyond the
    table's edge flattened into the plane by a depth filter - and the colour the objects stand out from is
    that of the surface under them; a crop of the frame around the target must not change it. Only the pixels
    that can hold such an inlier are looked at (:func:`_support_box`; ``band_m``: the largest inlier band, m)."""
    if params.target not in ('pixel', 'table') or SUPPORT_RADIUS_M <= 0:
        return inlier
    if params.target == 'pixel':
        h, w = inlier.shape
        u = int(np.clip(round(params.target_point[0]), 0, w - 1))
        v = int(np.clip(round(params.target_point[1]), 0, h - 1))
        hit_pt, hit = table.ray_intersection(rays[v, u])
        if not bool(hit):
            return inlier
        point = table.to_table(hit_pt)[0]
    else:
        point = np.asarray(params.target_point, dtype=np.float64)
        hit_pt = table.to_camera(point)
    rows, cols = _support_box(hit_pt, SUPPORT_RADIUS_M + band_m, intrinsics)
    near_inlier = inlier[rows, cols]
    xy = table.to_table(masked_rows(points[rows, cols], near_inlier))[0]
    near = norm_of([xy[:, 0] - point[0], xy[:, 1] - point[1]]) <= SUPPORT_RADIUS_M
    if near.sum() < SUPPORT_MIN_PX:
        return inlier
    out = np.zeros_like(inlier)
    box = out[rows, cols]
    box[near_inlier] = near
    return out


def _support_box(centre: np.ndarray, reach_m: float, intrinsics: CameraIntrinsics) -> tuple[slice, slice]:
    """(rows, columns) of the image holding every pixel whose point lies within ``reach_m`` of the camera-frame point
    ``centre``: the box of the projected corners of the cube around it (the image of the ball lies in the image of
    the cube, the convex hull of its corners' images, when the cube is in front of the camera), one pixel wider;
    the whole image when the cube reaches behind the camera."""
    corners = np.asarray(centre, dtype=np.float64) + reach_m * np.array(
        [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    if not (np.all(np.isfinite(corners)) and corners[:, 2].min() > 1e-6):
        return slice(0, intrinsics.height), slice(0, intrinsics.width)
    uv = intrinsics.project(corners)
    u0 = int(np.clip(math.floor(uv[:, 0].min()) - 1, 0, intrinsics.width))
    u1 = int(np.clip(math.ceil(uv[:, 0].max()) + 2, 0, intrinsics.width))
    v0 = int(np.clip(math.floor(uv[:, 1].min()) - 1, 0, intrinsics.height))
    v1 = int(np.clip(math.ceil(uv[:, 1].max()) + 2, 0, intrinsics.height))
    return slice(v0, v1), slice(u0, u1)


def pixel_footprint(z_mean: np.ndarray, fit: TableFit, intrinsics: CameraIntrinsics,
                    where: np.ndarray | None = None) -> float:
    """A pixel's extent on the table (m), at the median depth of ``z_mean`` over ``where`` (default: the
    table's inliers). On a tilted table it grows with the distance, so the footprint a grid is sized by is
    taken where that grid lies (the table under the target), not over whatever part of the table the
    image happens to show."""
    sel = fit.inlier if where is None else where
    z = z_mean[sel]
    z = z[np.isfinite(z)]
    if z.size == 0:
        raise ValueError('no depth to measure a pixel footprint at')
    return float(median(z)) / min(intrinsics.fx, intrinsics.fy) / max(
        math.cos(math.radians(fit.table.tilt_deg)), 0.3)
