"""Camera stage (core.sensing.camera): clouds to frames, frame validation, per-pixel averaging."""

from __future__ import annotations

import numpy as np
import pytest

from gpis_grasp_ros.core.sensing import CameraIntrinsics, SensingParams, frames_from_clouds
from gpis_grasp_ros.core.sensing.camera import average_frames, validate_frames

INTR = CameraIntrinsics(fx=110.0, fy=105.0, cx=31.5, cy=23.0, width=64, height=48)


def _organized_cloud(n: int = 2, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n organized clouds of a slanted plane seen by INTR, a few points invalid; and their depths."""
    rng = np.random.default_rng(seed)
    rays = INTR.rays()
    depth = 0.6 + 0.2 * rays[..., 0] + 0.1 * rays[..., 1]
    depth = np.broadcast_to(depth, (n,) + depth.shape).copy()
    depth[rng.random(depth.shape) < 0.05] = np.nan
    xyz = (rays[None] * depth[..., None]).astype(np.float32)
    rgb = rng.integers(0, 256, xyz.shape, dtype=np.uint8)
    return xyz, rgb, depth


def test_frames_from_clouds_round_trip():
    """The pinhole intrinsics and the depth (z) of a synthetic organized cloud are recovered."""
    xyz, rgb, depth = _organized_cloud()
    col, z, intr = frames_from_clouds(xyz, rgb)
    assert (intr.width, intr.height) == (INTR.width, INTR.height)
    assert np.allclose([intr.fx, intr.fy, intr.cx, intr.cy], [INTR.fx, INTR.fy, INTR.cx, INTR.cy], atol=1e-3)
    assert np.array_equal(np.isnan(z), np.isnan(depth))
    assert np.allclose(z[np.isfinite(z)], depth[np.isfinite(depth)], atol=1e-6)
    assert np.array_equal(col, rgb)
    # the recovered intrinsics project the points back onto their own pixels
    v, u = np.nonzero(np.isfinite(z[0]))
    uv = intr.project(xyz[0][v, u].astype(np.float64))
    assert np.allclose(uv, np.stack([u, v], axis=1), atol=1e-2)


def test_frames_from_clouds_refuses_bad_input():
    xyz, rgb, _ = _organized_cloud()
    with pytest.raises(ValueError, match='uint8'):
        frames_from_clouds(xyz, rgb.astype(np.float32))
    with pytest.raises(ValueError, match='fewer than 3'):
        frames_from_clouds(np.full_like(xyz, np.nan), rgb)


def test_validate_frames_checks_shapes_and_types():
    rgb = np.zeros((2, 48, 64, 3), np.uint8)
    depth = np.ones((2, 48, 64))
    r, d = validate_frames(rgb[0], depth[0], INTR)  # one frame without N
    assert r.shape == (1, 48, 64, 3) and d.shape == (1, 48, 64)
    with pytest.raises(ValueError, match='intrinsics'):
        validate_frames(rgb[:, :40], depth[:, :40], INTR)
    with pytest.raises(ValueError, match='differ'):
        validate_frames(rgb, depth[:1], INTR)
    with pytest.raises(ValueError, match='floating point'):
        validate_frames(rgb, depth.astype(np.uint16), INTR)


def test_average_over_valid_returns():
    """Depth is the mean of the valid returns, colour of all frames; a pixel without any return is missing;
    identical repeated frames are worth one."""
    depth = np.full((3, 4, 5), 0.5)
    depth[0, 0, 0], depth[1, 0, 0] = np.nan, 0.0  # one valid return of three
    depth[2, 0, 0] = 0.8
    depth[:, 1, 1] = np.nan  # none
    rgb = np.zeros((3, 4, 5, 3), np.uint8)
    rgb[0] = 30
    frames = average_frames(rgb, depth, SensingParams())
    assert frames.count[0, 0] == 1 and frames.z_mean[0, 0] == 0.8
    assert frames.missing[1, 1] and not frames.valid[1, 1] and np.isnan(frames.z_mean[1, 1])
    assert frames.missing.sum() == 1
    assert np.all(frames.rgb_mean == 10.0)
    assert np.allclose(frames.count_eff, frames.count * frames.n_eff / 3)
    assert average_frames(rgb, np.full((3, 4, 5), 0.5), SensingParams()).n_eff == pytest.approx(1.0)
    with pytest.raises(ValueError, match='no valid return'):
        average_frames(rgb, np.full((3, 4, 5), np.nan), SensingParams())
