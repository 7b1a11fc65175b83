"""Incoming-message checks (ros/validation.py): rejected before allocation, the field named."""

from __future__ import annotations

import math

import numpy as np
import pytest
from nav_msgs.msg import OccupancyGrid
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField

from gpis_grasp_interfaces.msg import FloatGrid
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.ros import conversions, validation
from gpis_grasp_ros.ros.nodes.gpis_node import grid_mismatch

F = conversions.RclpyFactory()
LIM = validation.Limits()


def _info(fx: float = 525.0, fy: float = 525.0, cx: float = 320.0, width: int = 640) -> CameraInfo:
    return messages.intrinsics_to_camera_info(F, 525.0, 525.0, cx, 240.0, width, 480, messages.header(F, 0, 'c')) \
        if fx == 525.0 and fy == 525.0 else _raw_info(fx, fy, cx, width)


def _raw_info(fx, fy, cx, width) -> CameraInfo:
    m = CameraInfo()
    m.width, m.height = width, 480
    m.k = [fx, 0.0, cx, 0.0, fy, 240.0, 0.0, 0.0, 1.0]
    return m


@pytest.mark.parametrize('fx, fy, cx, width, field', [
    (1e-300, 525.0, 320.0, 640, r'k\[0\] \(fx\)'),
    (525.0, math.nan, 320.0, 640, r'k\[4\] \(fy\)'),
    (-525.0, 525.0, 320.0, 640, r'k\[0\] \(fx\)'),
    (525.0, 525.0, 1e9, 640, r'k\[2\] \(cx\)'),
    (525.0, 525.0, 320.0, 10 ** 7, 'CameraInfo.width'),
])
def test_camera_info_limits(fx, fy, cx, width, field):
    assert validation.check_camera_info(_info(), LIM) == (525.0, 525.0, 320.0, 240.0, 640, 480)
    with pytest.raises(ValueError, match=field):
        validation.check_camera_info(_raw_info(fx, fy, cx, width), LIM)


def test_image_claiming_huge_size_is_rejected_before_reading_data():
    good = messages.numpy_to_image(F, np.zeros((4, 5), np.float32), '32FC1', messages.header(F, 0, 'c'))
    validation.check_image(good, LIM)
    huge = Image(height=100000, width=100000, encoding='32FC1', step=400000, data=bytes(10))
    with pytest.raises(ValueError, match='max_image_pixels'):
        validation.check_image(huge, LIM)
    short = Image(height=4, width=5, encoding='32FC1', step=20, data=bytes(10))
    with pytest.raises(ValueError, match='data has 10 bytes'):
        validation.check_image(short, LIM)
    with pytest.raises(ValueError, match='encoding'):
        validation.check_image(Image(height=4, width=5, encoding='yuv', step=20, data=bytes(80)), LIM)


def test_cloud_claiming_huge_size_is_rejected():
    m = PointCloud2(height=100000, width=100000, point_step=16, row_step=1600000, data=bytes(10),
                    fields=[PointField(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate('xyz')])
    with pytest.raises(ValueError, match='max_image_pixels'):
        validation.check_pointcloud(m, LIM)
    m.height, m.width, m.row_step = 2, 2, 32
    with pytest.raises(ValueError, match='PointCloud2.data'):
        validation.check_pointcloud(m, LIM)


@pytest.mark.parametrize('change, field', [
    ({'resolution': 1e-30}, 'info.resolution'),
    ({'resolution': 1e30}, 'info.resolution'),
    ({'width': 10 ** 6}, 'info.width'),
    ({'qw': math.nan}, 'info.origin.orientation'),
    ({'qw': 2.0}, 'info.origin.orientation'),
    ({'x': math.inf}, 'info.origin.position.x'),
])
def test_grid_limits_name_the_field(change, field):
    g = GridGeometry(-0.05, -0.05, 0.004, 25, 25, 0.7, 'c')
    msg = messages.numpy_to_float_grid(F, np.zeros((25, 25), np.float32), g, None, 'm^2')
    validation.check_float_grid(msg, LIM, 'FloatGrid', allow_nan=True, low=0.0, high=1.0)
    msg.info.resolution = change.get('resolution', msg.info.resolution)
    msg.info.width = change.get('width', msg.info.width)
    msg.info.origin.orientation.w = change.get('qw', msg.info.origin.orientation.w)
    msg.info.origin.position.x = change.get('x', msg.info.origin.position.x)
    with pytest.raises(ValueError, match=field.replace('.', r'\.')):
        validation.check_float_grid(msg, LIM, 'FloatGrid', allow_nan=True, low=0.0, high=1.0)


def test_grid_values():
    g = GridGeometry(0.0, 0.0, 0.004, 4, 4, 0.7, 'c')
    occ = messages.numpy_to_occupancy_grid(F, np.zeros((4, 4), np.int8), g)
    validation.check_occupancy_grid(occ, LIM)
    bad = OccupancyGrid(header=occ.header, info=occ.info, data=[0] * 15 + [-7])
    with pytest.raises(ValueError, match=r'\[-1, 100\]'):
        validation.check_occupancy_grid(bad, LIM)
    noise = FloatGrid(header=occ.header, info=occ.info, unit='m^2', data=[math.nan] * 16)
    with pytest.raises(ValueError, match='all NaN'):
        validation.check_float_grid(noise, LIM, 'noise', allow_nan=True, low=0.0, high=1.0)
    noise.data = [0.0, 5.0] + [0.0] * 14
    with pytest.raises(ValueError, match='outside'):
        validation.check_float_grid(noise, LIM, 'noise', allow_nan=True, low=0.0, high=1.0)
    noise.data = [0.0, -math.inf] + [0.0] * 14
    with pytest.raises(ValueError, match='non-finite'):
        validation.check_float_grid(noise, LIM, 'noise', allow_nan=True, low=0.0, high=1.0)


def test_mismatched_grids_name_the_differing_field():
    a = GridGeometry(0.0, 0.0, 0.004, 25, 25, 0.7, 'c')
    assert grid_mismatch(a, a) is None
    assert 'info.resolution' in grid_mismatch(a, GridGeometry(0.0, 0.0, 0.005, 25, 25, 0.7, 'c'))
    assert 'info.width' in grid_mismatch(a, a.with_shape(24, 25))
    assert 'info.origin.position.y' in grid_mismatch(a, GridGeometry(0.0, 0.01, 0.004, 25, 25, 0.7, 'c'))
