"""Table stage (core.sensing.table): the robust plane under outliers, heights along its normal."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpis_grasp_ros.core.sensing import SensingParams
from gpis_grasp_ros.core.sensing.camera import average_frames
from gpis_grasp_ros.core.sensing.table import fit_table, pixel_footprint
from support.tilted_scene import Box, TiltedScene


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
