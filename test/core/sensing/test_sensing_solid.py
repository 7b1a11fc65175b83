"""Minimum object (core.sensing.objects.object_labels): sensor noise and flat marks are never objects.

Analytic tilted scenes (``tilted_scene``), one frame of a noisy sensor: a box, a small cube above the minimum
object, flat colour prints on the table and depth-noise specks (patches of correlated noise just above the
depth-evidence threshold but below SOLID_SIGMAS sigma) of several sizes.
"""

from __future__ import annotations

import numpy as np
import pytest

from gpis_grasp_ros.core.noise_model import SensorModel
from gpis_grasp_ros.core.sensing import SensingParams, segment_frames
from gpis_grasp_ros.core.sensing.objects import SOLID_SIGMAS
from support.tilted_scene import Box, TiltedScene

#: a noisy sensor (4 mm at every depth, no quantisation, no projector shadow): the depth-evidence threshold (2 x the
#: table's RMS) lies below SOLID_SIGMAS sigma at every tilt, so noise can be evidence without being solid
NOISY = SensorModel('custom', 0.004, 0.0, 0.4, 0.0, 0.0, 0.0, 0.0)
PRINTS = [(-0.09, -0.065, -0.08, -0.055), (-0.10, 0.05, -0.08, 0.07), (-0.025, 0.06, 0.025, 0.11)]  # 1, 2, 5 cm
SPECKS = [(0.075, -0.065, 0.085, -0.055), (0.08, 0.05, 0.10, 0.07), (-0.16, -0.02, -0.12, 0.02)]  # 1, 2, 4 cm


def _in(xy: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:
    return (xy[..., 0] >= box[0]) & (xy[..., 0] <= box[2]) & (xy[..., 1] >= box[1]) & (xy[..., 1] <= box[3])


@pytest.mark.parametrize('tilt', [0.0, 30.0, 45.0, 60.0])
def test_noise_specks_and_prints_are_never_objects(tilt):
    box = Box(0.0, 0.0, 0.03, 0.02, 0.04)
    cube = Box(0.08, 0.0, 0.0075, 0.0075, 0.015, rgb=(200.0, 60.0, 40.0))  # 2.25 cm^2: above the 1 cm^2 minimum
    scene = TiltedScene(tilt, boxes=[box, cube], prints=[(*p, (150.0, 40.0, 40.0)) for p in PRINTS])
    rgb, depth, label = scene.frames(1, seed=int(tilt), model=NOISY)
    params = SensingParams(sensor=NOISY)
    h_thr = segment_frames(rgb, depth, scene.intrinsics, params).height_threshold
    # depth specks: table pixels raised to between the evidence threshold and SOLID_SIGMAS sigma, the same in every
    # pixel's frames (correlated noise, no measurement noise on top)
    rays = scene.intrinsics.rays()
    ray_n = rays @ scene.normal
    xy = scene.table_xy(rays * np.nan_to_num(scene.render()[0])[..., None])
    speck = (label == 0) & np.any([_in(xy, s) for s in SPECKS], axis=0)
    z_table = -scene.offset / ray_n
    sigma_h = NOISY.sigma(z_table) * np.abs(ray_n)
    h = 0.5 * (h_thr + SOLID_SIGMAS * sigma_h)
    assert np.all((h[speck] > h_thr + 2e-4) & (h[speck] < SOLID_SIGMAS * sigma_h[speck] - 2e-4))
    depth[:, speck] = ((h - scene.offset) / ray_n)[speck]
    result = segment_frames(rgb, depth, scene.intrinsics, params)

    printed = (label == 0) & np.any([_in(xy, p) for p in PRINTS], axis=0)
    assert result.rgb_mask[printed].mean() > 0.8 and result.depth_mask[speck].mean() > 0.8  # evidence, both
    assert not (result.labels_px[printed | speck] > 0).any()  # but neither the target nor another object
    assert result.objects_seen == 2
    assert np.mean(label[result.object_mask] == 1) > 0.95  # the largest object is the box, not the 5 cm print
    assert (result.labels_px[label == 2] > 0).mean() > 0.5  # the small cube is an object (an obstacle)
