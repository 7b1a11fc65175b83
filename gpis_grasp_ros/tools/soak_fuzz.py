"""Malformed messages for the fuzz phase of ``gpis-grasp soak``: one maker per node input, each message
breaking a size or value limit in its own way."""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np


def malformed_makers(model: Any) -> dict[str, Any]:
    """A maker per input topic: rng → one malformed message (each breaks a size or value limit)."""
    from geometry_msgs.msg import PointStamped
    from nav_msgs.msg import OccupancyGrid
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField

    from gpis_grasp_interfaces.msg import FloatGrid
    big = [10 ** 5, 10 ** 6, 2 ** 31 - 1]

    def cloud(rng):
        m = PointCloud2()
        m.fields = [PointField(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate('xyz')] + \
            [PointField(name='rgb', offset=12, datatype=7, count=1)]
        kind = int(rng.integers(4))
        m.height, m.width, m.point_step = (int(rng.choice(big)), int(rng.choice(big)), 16) if kind == 0 else (4, 4, 16)
        m.row_step = m.width * m.point_step
        if kind == 1:
            m.data = bytes(10)  # truncated
        elif kind == 2:
            m.point_step, m.row_step = 0, 0
        elif kind == 3:  # points on a line: no camera geometry
            pts = np.zeros((16, 4), np.float32)
            pts[:, 2] = 1e30
            m.data = pts.tobytes()
        return m

    def image(rng, depth: bool):
        m = Image()
        kind = int(rng.integers(4))
        m.encoding = ('32FC1' if depth else 'rgb8') if kind != 0 else 'yuv422_weird'
        m.height, m.width = (int(rng.choice(big)), int(rng.choice(big))) if kind == 1 else (4, 4)
        m.step = m.width * (4 if depth else 3) if kind != 2 else 1
        m.data = bytes(8)
        return m

    def info(rng):
        m = CameraInfo()
        m.width, m.height = 640, 480
        kind = int(rng.integers(3))
        fx = [1e-300, math.nan, -500.0][kind]
        m.k = [fx, 0.0, 320.0, 0.0, 525.0, 240.0, 0.0, 0.0, 1.0]
        return m

    def meta(m, rng):
        kind = int(rng.integers(5))
        m.info.width, m.info.height = (int(rng.choice(big)), int(rng.choice(big))) if kind == 0 else (25, 25)
        m.info.resolution = [0.005, 1e-30, 1e30, math.nan, 0.005][kind]
        m.info.origin.orientation.w = math.nan if kind == 4 else 1.0
        return m

    def occupancy(rng):
        m = meta(OccupancyGrid(), rng)
        m.data = [0] * 7
        return m

    def float_grid(rng, unit: str):
        m = meta(FloatGrid(), rng)
        m.unit = unit
        m.data = [math.nan] * 7
        return m

    def gpis_model(rng):
        m = copy.deepcopy(model)
        kind = int(rng.integers(6))
        if kind == 0:
            m.jitter = math.nan
        elif kind == 1:
            m.train_y = [1e300] * len(m.train_y)
        elif kind == 2:
            m.train_x = [1e6] * len(m.train_x)
        elif kind == 3:
            m.info.width, m.info.height, m.mean, m.variance = 100000, 100000, [], []
        elif kind == 4:
            m.info.origin.orientation.w = math.nan
        else:
            m.resolution, m.info.resolution = 1e30, 1e30
        return m

    def com(rng):
        m = PointStamped()
        m.point.x = [math.nan, math.inf, 1e300][int(rng.integers(3))]
        return m

    makers = {'cloud': cloud, 'rgb': lambda r: image(r, False), 'depth': lambda r: image(r, True), 'info': info,
              'occupancy': occupancy, 'noise': lambda r: float_grid(r, 'm^2'), 'sdf': lambda r: float_grid(r, 'm'),
              'com': com}
    if model is not None:
        makers['model'] = gpis_model
    return makers


