"""The segmentation's data flow, one stage after another (see the package docstring)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.sensing.camera import AveragedFrames, CameraIntrinsics, average_frames, validate_frames
from gpis_grasp_ros.core.sensing.clear_body import Target, grow_target
from gpis_grasp_ros.core.sensing.evidence import Evidence, combine, soft_evidence
from gpis_grasp_ros.core.sensing.noise_map import noise_map
from gpis_grasp_ros.core.sensing.objects import Objects, TargetCut, isolate_target, object_height
from gpis_grasp_ros.core.sensing.occlusion import Feet, move_seen_through, place_feet, sensor_shadow
from gpis_grasp_ros.core.sensing.params import SUPPORT_RADIUS_M, SensingParams, SensingResult
from gpis_grasp_ros.core.sensing.pixel_kernels import has_label, mask_bounds
from gpis_grasp_ros.core.sensing.rasterise import grid_around, rasterise
from gpis_grasp_ros.core.sensing.table import Measurement, TableFit, fit_table, pixel_footprint
from gpis_grasp_ros.core.sensing.window import crop, grown, square, target_point, uncrop, window

#: Half-side (m) of the table square around a target point whose window is segmented first (window.py): the
#: table around the target
WINDOW_HALF_SIDE_M = SUPPORT_RADIUS_M


def segment_frames(rgb_frames: np.ndarray | Sequence[np.ndarray], depth_frames: np.ndarray | Sequence[np.ndarray],
                   intrinsics: CameraIntrinsics, params: SensingParams = SensingParams(),
                   frame_id: str = '') -> SensingResult:
    """Segment the target object from N RGBD frames into an M x M occupancy grid and SDF noise map (III-B).

    Args:
        rgb_frames: ``(N, H, W, 3)`` uint8 RGB images (or one ``(H, W, 3)`` image).
        depth_frames: ``(N, H, W)`` float depth in metres, NaN (or <= 0) = no return.
        intrinsics: pinhole intrinsics of the (registered) images, pixels.
        params: thresholds, table, target and grid settings (see :class:`SensingParams`).
        frame_id: sensor frame stored in the returned geometry.

    Returns:
        :class:`SensingResult`. The grid lies in the table plane (``geometry.rotation`` = table frame). For a
        target point (``target`` ``pixel`` or ``table``) only the target's window of the frame is segmented
        (:mod:`.window`); the pixel maps are empty outside it.

    Raises:
        ValueError: wrong dtype or shape, no valid depth, no table plane (or seen edge-on), no object
            on the table, target point on no object, target cut by the image border or too wide.
    """
    frames = average_frames(*validate_frames(rgb_frames, depth_frames, intrinsics), params)
    fit, meas = fit_table(frames, intrinsics, params)
    point = target_point(fit, intrinsics, params) if WINDOW_HALF_SIDE_M > 0 else None
    region, box = None if point is None else square(point, WINDOW_HALF_SIDE_M), None
    while region is not None:  # a target point: segment its window, grown until it holds the target and its grid
        win = window(fit, meas, region, params)
        if win is None or win[:4] == box:  # the whole image, or all of it the region can reach
            break
        box = win[:4]
        try:
            found = find_target(*crop(win, frames, fit, meas, intrinsics, params))
        except TargetCut:  # by the window's edge (the whole image's edges are checked at the end)
            region = square(point, region[2] - region[0])
            continue
        region = grown(win, found.target.target_px, found.target.contact_px, found.grid, intrinsics, params)
        if region is None:
            return uncrop(grid_of(found, frame_id), win, frames, meas, intrinsics)
    return grid_of(find_target(frames, fit, meas, intrinsics, params), frame_id)


class Found(NamedTuple):
    """The segmentation up to the target: the frames and evidence after the occlusion tests, the objects, the
    target and the extent of its grid."""

    frames: AveragedFrames
    fit: TableFit
    meas: Measurement
    intrinsics: CameraIntrinsics
    params: SensingParams
    ev: Evidence
    rho: np.ndarray
    through_px: np.ndarray
    shadow_px: np.ndarray
    missing_px: np.ndarray
    feet: Feet
    objects: Objects
    target: Target
    grid_footprint: float  # m, a pixel's extent on the table under the target
    grid: GridGeometry


def find_target(frames: AveragedFrames, fit: TableFit, meas: Measurement, intrinsics: CameraIntrinsics,
                params: SensingParams) -> Found:
    """The stages after the table up to the target and its grid's extent (III-B)."""
    ev = soft_evidence(frames, fit, meas, params)
    frames, meas, ev, through_px = move_seen_through(frames, fit, meas, ev, intrinsics, params)
    footprint = fit.footprint
    shadow_px = sensor_shadow(frames, fit, meas, ev, intrinsics, params, footprint)
    missing_px = frames.missing & ~shadow_px  # the sensor's shadow is table it did not measure, not missing
    occ, rho = combine(ev, missing_px, params)  # missing = object
    feet = place_feet(frames, fit, meas, missing_px, shadow_px, intrinsics, footprint)
    objects = isolate_target(fit, meas, ev, occ, missing_px, feet.foot_xy, footprint, intrinsics, params,
                             frames.rgb_mean)
    target = grow_target(objects, frames, fit, meas, ev, occ, missing_px, feet, intrinsics, params)
    # the grid is sized by the footprint of a pixel on the table under the target (a crop does not change it)
    grid_footprint = pixel_footprint(feet.hit_points[..., 2], fit, intrinsics, target.target_px)
    grid = grid_around(target.target_xy, fit.table, params, '', grid_footprint)
    return Found(frames, fit, meas, intrinsics, params, ev, rho, through_px, shadow_px, missing_px, feet, objects,
                 target, grid_footprint, grid)


def grid_of(found: Found, frame_id: str) -> SensingResult:
    """The target's grid: its cells rasterised, their SDF noise, and the pixel maps (III-B)."""
    frames, fit, meas, params, ev, target, missing_px = (found.frames, found.fit, found.meas, found.params, found.ev,
                                                         found.target, found.missing_px)
    objects, rho, feet = found.objects, found.rho, found.feet
    cells = rasterise(target, missing_px, frames, fit, meas, ev.p_d, feet, found.grid_footprint, found.intrinsics,
                      params, dataclasses.replace(found.grid, frame_id=frame_id))
    noise = noise_map(cells, missing_px, target.target_px, feet.off_hull, params)

    valid, target_px, colour = frames.valid, target.target_px, ev.colour
    noise_px = np.where(missing_px, np.nan, meas.var_z + params.disagreement_variance_m2 * rho)
    v_min, v_max, u_min, u_max = mask_bounds(target_px)
    return SensingResult(
        occupancy=cells.occupancy, noise_variance=noise.noise, missing=cells.missing, geometry=cells.geometry,
        table_depth=fit.table.offset_m, train_mask=noise.train_mask, observed=cells.observed,
        occluded=cells.occluded, uncertain=noise.uncertain, disagreement=cells.disagreement, table=fit.table,
        table_color=colour.table_rgb, color_threshold=colour.threshold, height_threshold=fit.h_thr,
        effective_frames=frames.n_eff, objects_seen=objects.objects_seen, mean_depth=frames.z_mean,
        valid_count=frames.count.astype(np.int64), height=meas.height, depth_mask=ev.p_d > 0.5,
        rgb_mask=ev.p_c > 0.5, missing_mask=missing_px, object_mask=target_px,
        labels_px=np.where(has_label(objects.px_labels, objects.kept) | target_px, objects.px_labels, 0),
        occupancy_px=target.occ, noise_px=noise_px,
        disagreement_px=rho, bbox_px=(u_min, v_min, u_max, v_max),
        intrinsics=found.intrinsics, object_height=object_height(meas.height, target_px & valid & (ev.p_d > 0.5)),
        seen_through_px=found.through_px, shadow_px=found.shadow_px, clear_body=cells.body, seen_behind=cells.behind,
        obstacles=cells.obstacle)
