"""Occlusion stage (core.sensing.occlusion): feet on a bare table, no shadow without its test."""

from __future__ import annotations

import numpy as np

from gpis_grasp_ros.core.sensing import SensingParams
from gpis_grasp_ros.core.sensing.camera import average_frames
from gpis_grasp_ros.core.sensing.evidence import soft_evidence
from gpis_grasp_ros.core.sensing.occlusion import _missing_height, place_feet, sensor_shadow
from gpis_grasp_ros.core.sensing.table import fit_table, pixel_footprint
from support.tilted_scene import TiltedScene


def test_feet_of_a_bare_tilted_table_are_its_points():
    """With nothing on the table every foot is the pixel's own table point and no hole is placed."""
    scene = TiltedScene(45.0, width=120, height=90, focal_px=110.0)
    rgb, depth, _ = scene.frames(1, seed=0)
    depth[0, 40:44, 50:56] = np.nan  # a drop-out on the bare table
    params = SensingParams()
    frames = average_frames(rgb, depth, params)
    fit, meas = fit_table(frames, scene.intrinsics, params)
    ev = soft_evidence(frames, fit, meas, params)
    footprint = pixel_footprint(frames.z_mean, fit, scene.intrinsics)
    shadow = sensor_shadow(frames, fit, meas, ev, scene.intrinsics, params, footprint)
    feet = place_feet(frames, fit, meas, frames.missing & ~shadow, shadow, scene.intrinsics, footprint)
    assert not feet.h_missing.any() and not feet.off_hull.any()
    truth = fit.table.to_table(feet.hit_points)[0]
    assert np.isfinite(feet.foot_xy).all()
    assert np.allclose(feet.foot_xy[frames.missing], truth[frames.missing], atol=1e-9)  # holes: where rays meet it
    seen = frames.valid
    err = np.linalg.norm(feet.foot_xy[seen] - truth[seen], axis=-1)  # seen: within the depth noise
    assert np.median(err) < 0.002 and err.max() < 0.02
    assert np.all((feet.ray_cos > 0) & (feet.ray_cos <= 1))


def test_no_shadow_without_its_test_or_a_second_viewpoint():
    scene = TiltedScene(0.0, width=60, height=40, focal_px=60.0)
    rgb, depth, _ = scene.frames(1)
    params = SensingParams(shadow_test=False)
    frames = average_frames(rgb, depth, params)
    fit, meas = fit_table(frames, scene.intrinsics, params)
    ev = soft_evidence(frames, fit, meas, params)
    assert not sensor_shadow(frames, fit, meas, ev, scene.intrinsics, params, 0.01).any()


def test_holes_away_from_any_object_stay_on_the_table():
    h = np.zeros((10, 10))
    missing = np.zeros((10, 10), bool)
    missing[3:5, 3:5] = True
    scene = TiltedScene(30.0, width=10, height=10, focal_px=10.0)
    from gpis_grasp_ros.core.table_frame import TableFrame
    table = TableFrame.from_plane(*scene.normal, scene.offset)
    out, tested = _missing_height(h, np.zeros((10, 10), bool), missing, scene.intrinsics.rays(), table,
                                  scene.intrinsics, 0.01, return_tested=True)
    assert not out.any() and not tested.any()
