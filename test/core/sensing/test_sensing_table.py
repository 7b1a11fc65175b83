"""Table stage (core.sensing.table): the robust plane under outliers, heights along its normal."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpis_grasp_ros.core.sensing import SensingParams
from gpis_grasp_ros.core.sensing.camera import average_frames
from gpis_grasp_ros.core.sensing.table import fit_table, pixel_footprint
from support.tilted_scene import TABLE_RGB, Box, TiltedScene


@pytest.mark.parametrize('tilt', [0.0, 35.0, 55.0])
def test_a_tilted_plane_with_outliers_is_recovered(tilt):
    """A table seen at ``tilt`` with a fifth of its pixels replaced by points 2-20 cm above it (clutter):
    the normal is found within 0.5 degrees, the offset within 2 mm, and the outliers are not inliers."""
    scene = TiltedScene(tilt, width=160, height=120, focal_px=140.0)
    rgb, depth, _ = scene.frames(3, seed=1)
    rng = np.random.default_rng(2)
    out = rng.random(depth.shape[1:]) < 0.2
    lift = rng.uniform(0.02, 0.2, depth.shape[1:])
    ray_n = scene.intrinsics.rays() @ scene.normal  # < 0: rays go away from the camera-facing normal
    depth[:, out] = depth[:, out] + (lift / ray_n)[out]  # h above the table along its normal
    frames = average_frames(rgb, depth, SensingParams())
    fit, meas = fit_table(frames, scene.intrinsics, SensingParams())
    angle = math.degrees(math.acos(min(1.0, abs(float(fit.table.n @ scene.normal)))))
    assert angle < 0.5
    assert abs(fit.table.offset_m - scene.offset) < 0.002
    assert fit.table.tilt_deg == pytest.approx(tilt, abs=0.5)
    assert not fit.inlier[out].any() and fit.inlier[~out].mean() > 0.95
    assert np.allclose(meas.height[out], lift[out], atol=0.01)
    assert fit.h_thr >= SensingParams().height_threshold


def test_pixel_footprint_on_a_tilted_table():
    """A pixel's extent on the table is the depth over the focal length, stretched by 1 / cos(tilt)."""
    scene = TiltedScene(40.0, width=160, height=120, focal_px=140.0, boxes=[Box(0.0, 0.0, 0.02, 0.02, 0.03)])
    rgb, depth, _ = scene.frames(2, seed=0)
    frames = average_frames(rgb, depth, SensingParams())
    fit, _ = fit_table(frames, scene.intrinsics, SensingParams())
    expect = float(np.median(frames.z_mean[fit.inlier])) / 140.0 / math.cos(math.radians(40.0))
    assert pixel_footprint(frames.z_mean, fit, scene.intrinsics) == pytest.approx(expect, rel=0.02)


def test_too_few_plane_pixels_are_refused():
    scene = TiltedScene(0.0, width=60, height=40, focal_px=60.0)
    rgb, depth, _ = scene.frames(1)
    params = SensingParams(table_depth_m=0.3)  # a given plane far from the depth seen
    with pytest.raises(ValueError, match='lie on the table plane'):
        fit_table(average_frames(rgb, depth, params), scene.intrinsics, params)


def _board_scene(tilt: float) -> TiltedScene:
    """A board (the table's colour, 48 x 40 cm) in one plane with a surround of other colours beyond its edge
    (bins, cloth, a depth filter's flattened world), a 6 x 4 x 3 cm box at its centre: the board is about a
    quarter of the plane's pixels."""
    hx, hy, far = 0.24, 0.20, 2.0
    colours = [(230.0, 230.0, 235.0), (200.0, 60.0, 150.0), (40.0, 40.0, 50.0), (60.0, 120.0, 230.0)]
    strips = [(-far, -far, far, -hy), (-far, hy, far, far), (-far, -hy, -hx, hy), (hx, -hy, far, hy)]
    prints = [(x0, y0, x1, y1, colours[k]) for k, (x0, y0, x1, y1) in enumerate(strips)]
    return TiltedScene(tilt, boxes=[Box(0.0, 0.0, 0.03, 0.02, 0.03, rgb=(150.0, 60.0, 40.0))], prints=prints)


@pytest.mark.parametrize('tilt', [0.0, 30.0, 50.0])
def test_the_colour_model_is_the_table_under_the_target_whole_frame_or_cropped(tilt):
    """The plane holds the board and, beyond its edge, three times its area of other colours: the colour
    model is learnt on the inliers around the target point (SUPPORT_RADIUS_M), so the whole frame gives the
    target, the table colour and the threshold of the frame cropped to the board, and the box's footprint."""
    from gpis_grasp_ros.core.sensing import segment_frames
    from gpis_grasp_ros.core.sensing.camera import CameraIntrinsics

    scene = _board_scene(tilt)
    rgb, depth, label = scene.frames(3, seed=4)
    corners = scene.to_camera(np.array([[-0.24, -0.2], [0.24, -0.2], [0.24, 0.2], [-0.24, 0.2]]))
    intr = scene.intrinsics
    u = intr.fx * corners[:, 0] / corners[:, 2] + intr.cx
    v = intr.fy * corners[:, 1] / corners[:, 2] + intr.cy
    u0, v0 = max(0, int(u.min()) + 2), max(0, int(v.min()) + 2)
    u1, v1 = min(intr.width, int(u.max()) - 2), min(intr.height, int(v.max()) - 2)
    vv, uu = np.nonzero(label == 1)
    target = (float(np.median(uu)), float(np.median(vv)))
    whole = segment_frames(rgb, depth, intr, SensingParams(target='pixel', target_point=target))
    crop_intr = CameraIntrinsics(intr.fx, intr.fy, intr.cx - u0, intr.cy - v0, u1 - u0, v1 - v0)
    crop = segment_frames(rgb[:, v0:v1, u0:u1], depth[:, v0:v1, u0:u1], crop_intr,
                          SensingParams(target='pixel', target_point=(target[0] - u0, target[1] - v0)))
    assert np.allclose(whole.table_color, crop.table_color, atol=3.0)
    assert whole.color_threshold == pytest.approx(crop.color_threshold, rel=0.1)
    assert np.abs(whole.table_color - TABLE_RGB).max() < 5.0
    assert whole.object_mask[label == 1].mean() > 0.9 and crop.object_mask[label[v0:v1, u0:u1] == 1].mean() > 0.9
    assert whole.object_mask.sum() == pytest.approx(crop.object_mask.sum(), rel=0.05)
    assert abs(int(whole.train_mask.sum()) - int(crop.train_mask.sum())) <= 3
    # the same target pixels seen in the whole frame as in the crop
    assert (whole.object_mask[v0:v1, u0:u1] ^ crop.object_mask).sum() <= 0.03 * crop.object_mask.sum()


def test_without_a_target_point_the_colour_model_uses_the_whole_plane():
    """``largest`` has no point to centre the support on: every inlier trains the colour model."""
    scene = _board_scene(30.0)
    rgb, depth, _ = scene.frames(2, seed=1)
    params = SensingParams()
    frames = average_frames(rgb, depth, params)
    fit, _ = fit_table(frames, scene.intrinsics, params)
    assert np.array_equal(fit.support, fit.inlier)


@pytest.mark.parametrize('y', [-0.25, 0.25])
def test_the_grid_is_sized_by_the_pixel_footprint_under_the_target_whole_frame_or_cropped(y):
    """At 45 degrees the table's pixel footprint changes by ~2x over the frame. A box off the image centre
    (nearer the camera, or farther) gets cells of two pixel footprints *at the box*, the same in the whole
    frame as in a crop around it; the median footprint over the whole table would be the wrong size."""
    from gpis_grasp_ros.core.sensing import segment_frames
    from gpis_grasp_ros.core.sensing.camera import CameraIntrinsics

    scene = TiltedScene(45.0, focal_px=300.0, boxes=[Box(0.0, y, 0.03, 0.02, 0.03)])
    rgb, depth, label = scene.frames(2, seed=3)
    intr = scene.intrinsics
    vv, uu = np.nonzero(label == 1)
    target = (float(np.median(uu)), float(np.median(vv)))
    u0, v0 = max(0, int(uu.min()) - 60), max(0, int(vv.min()) - 60)
    u1, v1 = min(intr.width, int(uu.max()) + 60), min(intr.height, int(vv.max()) + 60)
    params = SensingParams(target='pixel', target_point=target, cell_size_m=0.001, min_grid_cells=5)
    whole = segment_frames(rgb, depth, intr, params)
    crop_intr = CameraIntrinsics(intr.fx, intr.fy, intr.cx - u0, intr.cy - v0, u1 - u0, v1 - v0)
    crop = segment_frames(rgb[:, v0:v1, u0:u1], depth[:, v0:v1, u0:u1], crop_intr,
                          SensingParams(target='pixel', target_point=(target[0] - u0, target[1] - v0),
                                        cell_size_m=0.001, min_grid_cells=5))
    z_box = float(scene.to_camera(np.array([0.0, y]))[2])
    expect = 2.0 * z_box / 300.0 / math.cos(math.radians(45.0))
    frames = average_frames(rgb, depth, params)
    fit, _ = fit_table(frames, intr, params)
    median_table = 2.0 * pixel_footprint(frames.z_mean, fit, intr)
    assert abs(median_table / expect - 1.0) > 0.15  # the whole frame's median footprint is not the box's
    for r in (whole, crop):  # M = ceil(side / cell): the cell shrinks by up to one part in M
        m = r.geometry.shape[0]
        assert expect * (1.0 - 1.0 / m) * 0.97 <= r.geometry.resolution <= expect * 1.03
    assert whole.geometry.resolution == pytest.approx(crop.geometry.resolution, rel=0.02)


def test_measure_again_equals_measure():
    from gpis_grasp_ros.core.noise_model import SensorModel
    from gpis_grasp_ros.core.sensing.camera import AveragedFrames, CameraIntrinsics
    from gpis_grasp_ros.core.sensing.table import measure, measure_again
    from gpis_grasp_ros.core.table_frame import TableFrame

    rng = np.random.default_rng(13)
    intr = CameraIntrinsics(300.0, 310.0, 40.2, 29.7, 80, 60)
    table = TableFrame.from_plane(0.05, -0.4, -0.91, 0.8)
    rays = intr.rays()
    ray_n = np.abs(rays @ table.n)
    z = rng.uniform(0.5, 1.0, (60, 80))
    valid = rng.random((60, 80)) < 0.8
    count = rng.integers(0, 5, (60, 80))
    frames = AveragedFrames(None, np.where(valid, z, np.nan), count, valid, ~valid, 3.0, count * 0.7)
    sensor = SensorModel.named('realsense_d400')
    before = measure(frames.z_mean, frames, table, rays, ray_n, sensor)
    changed = rng.random((60, 80)) < 0.1
    z2 = np.where(changed, z + 0.05, frames.z_mean)
    want = measure(z2, frames, table, rays, ray_n, sensor)
    got = measure_again(before, z2, changed, frames, table, rays, ray_n, sensor)
    for g, w in zip(got, want, strict=True):
        assert np.array_equal(g, w, equal_nan=True)
