"""Grid geometry and its pose in the sensor frame (tilted table planes)."""

from __future__ import annotations

import numpy as np
import pytest

from gpis_grasp_ros.core.grid import GridGeometry, quaternion_to_rotation, rotation_to_quaternion


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q @ np.diag(np.sign(np.diag(r)))
    return q if np.linalg.det(q) > 0 else -q


def test_identity_pose_is_the_top_down_convention():
    g = GridGeometry(-0.1, 0.02, 0.005, 20, 10, 0.7, 'cam')
    xy = g.cell_centers()
    p = g.to_sensor(xy)
    np.testing.assert_array_equal(p[..., :2], xy)
    np.testing.assert_array_equal(p[..., 2], 0.7)
    # above the table = nearer the camera
    np.testing.assert_allclose(g.to_sensor(xy, height=0.02)[..., 2], 0.68, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(g.table_normal, [0.0, 0.0, -1.0])


def test_sensor_round_trip_and_plane_membership_for_random_poses():
    rng = np.random.default_rng(3)
    for _ in range(200):
        rot = _random_rotation(rng)
        g = GridGeometry(*rng.uniform(-0.2, 0.2, 2), 0.004, 25, 25, rng.uniform(0.3, 1.5), 'cam', tuple(rot.ravel()))
        xy = rng.uniform(-0.3, 0.3, (50, 2))
        h = rng.uniform(0.0, 0.1, 50)
        p = g.to_sensor(xy, h)
        xy2, h2 = g.from_sensor(p)
        np.testing.assert_allclose(xy2, xy, atol=1e-12)
        np.testing.assert_allclose(h2, h, atol=1e-12)
        # signed distance from the plane n.p + d = 0 with n the normal towards the camera, d = g.z
        np.testing.assert_allclose(p @ g.table_normal + g.z, h, atol=1e-12)
        pos, quat = g.corner_pose()
        g2 = GridGeometry.from_corner_pose(pos, quat, g.resolution, g.width, g.height, 'cam')
        np.testing.assert_allclose(g2.rotation, g.rotation, atol=1e-12)
        np.testing.assert_allclose([g2.origin_x, g2.origin_y, g2.z], [g.origin_x, g.origin_y, g.z], atol=1e-12)


def test_quaternion_conversions_invert_each_other():
    rng = np.random.default_rng(4)
    for _ in range(500):
        rot = _random_rotation(rng)
        q = rotation_to_quaternion(rot)
        assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(quaternion_to_rotation(q), rot, atol=1e-12)
    # 90° about z maps x onto y
    c = np.sqrt(0.5)
    np.testing.assert_allclose(quaternion_to_rotation([0, 0, c, c]) @ [1, 0, 0], [0, 1, 0], atol=1e-12)


@pytest.mark.parametrize('rotation', [(1.0, 0, 0, 0, 1, 0, 0, 0, -1), (2.0, 0, 0, 0, 1, 0, 0, 0, 1), (1.0,) * 3,
                                      (float('nan'),) + (0.0,) * 8])
def test_improper_rotations_are_rejected(rotation):
    with pytest.raises(ValueError, match='rotation'):
        GridGeometry(0.0, 0.0, 0.01, 4, 4, 0.5, 'cam', rotation)
