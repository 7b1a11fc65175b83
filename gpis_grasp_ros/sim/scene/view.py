"""Camera pose and image window: where the camera is over the table and which pixels it records.

Frames (lengths in m):

* **Table frame** T: the object outline's (X, Y) in the table plane, z into the table (away from the
  camera side; heights above the table are -z). The default camera is top-down: camera frame = T
  shifted by ``camera_height``.
* **Camera optical frame** ``camera_rgb_optical_frame``: x right, y down, z along the optical axis.
  Camera axes in T: R_TC = Rz(azimuth) Rx(tilt); camera position C = R_TC (0, 0, -distance).
* **Ground truth in the table frame**: the grids' :class:`GridGeometry` carries ``rotation`` = R_TC^T
  (grid axes = T's axes in the camera frame) and ``z`` = the table plane's distance from the camera
  along T's z; grid (x, y) = T (X, Y) - C (X, Y).
* **Image window**: the sensor's full-frame intrinsics cropped to a window around everything in view
  (objects, distractors, the target's shadow) plus a margin; the crop shifts (cx, cy).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from gpis_grasp_ros.sim.scene.spec import SENSOR_RANGE_M, CameraModel, SceneSpec


class CameraPose:
    """Camera axes ``r_tc`` (columns, in T) and position ``c`` in T of a spec's camera (m)."""

    def __init__(self, spec: SceneSpec) -> None:
        s = spec
        self.top_down = s.top_down
        d = float(s.camera_height)
        if s.top_down:
            r = np.eye(3)
            c = np.array([0.0, 0.0, -d])
        else:
            t, a = math.radians(float(s.camera_tilt)), math.radians(float(s.camera_azimuth))
            rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(t), -math.sin(t)], [0.0, math.sin(t), math.cos(t)]])
            rz = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
            r = rz @ rx
            c = r @ np.array([0.0, 0.0, -d])
        self.r_tc, self.c = r, c
        #: distance (m) of the table plane from the camera along T's z (the ground-truth grids' ``z``)
        self.table_depth = float(s.camera_height) if s.top_down else float(-c[2])

    @property
    def grid_rotation(self) -> tuple[float, ...]:
        """Row-major ``GridGeometry.rotation`` of table-frame grids: T's axes in the camera frame (R_TC^T)."""
        return tuple(float(v) for v in self.r_tc.T.ravel())

    def table_to_camera(self, xy: np.ndarray, height: np.ndarray | float = 0.0) -> np.ndarray:
        """Table-frame points ``(..., 2)`` (m) at ``height`` (m) above the table → camera frame ``(..., 3)``."""
        xy = np.asarray(xy, dtype=np.float64)
        h = np.broadcast_to(np.asarray(height, dtype=np.float64), xy.shape[:-1])
        g = np.concatenate([xy, (-h)[..., None]], axis=-1) - self.c
        return g if self.top_down else g @ self.r_tc

    def ray_dirs(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ray slopes (..., 2) in the camera → directions in T with unit optical-axis component:
        (lateral (..., 2), along T's z (...)); the camera-frame depth of C + t d is t."""
        if self.top_down:
            return rays, np.ones(rays.shape[:-1])
        d = np.concatenate([rays, np.ones(rays.shape[:-1] + (1,))], axis=-1) @ self.r_tc.T
        return d[..., :2], d[..., 2]

    def table_points(self, rays: np.ndarray) -> np.ndarray:
        """Table-frame (X, Y) (m) where rays (..., 2) meet the table plane."""
        dxy, dz = self.ray_dirs(rays)
        t = (0.0 - self.c[2]) / dz
        return self.c[:2] + dxy * t[..., None]


class ImageWindow:
    """The cropped image: ``u0``, ``v0`` (px) of its corner in the full frame, its size and intrinsics.

    ``points`` are (table-frame outline (N, 2), height above the table) pairs that must be in view;
    ValueError when one is closer than the sensor's minimum range, outside the field of view, or when
    the view grazes the table."""

    def __init__(self, pose: CameraPose, cam: CameraModel, spec: SceneSpec,
                 points: Sequence[tuple[np.ndarray, float]]) -> None:
        margin = int(spec.crop_margin_px)
        cams = [pose.table_to_camera(xy, h) for xy, h in points]
        zs = np.concatenate([c[:, 2] for c in cams])
        lo_range = SENSOR_RANGE_M[spec.sensor][0]
        if zs.min() < lo_range:
            raise ValueError(f'object top at {zs.min():.3f} m is closer than the sensor minimum range {lo_range} m')
        us = np.concatenate([cam.cx + cam.fx * c[:, 0] / c[:, 2] for c in cams])
        vs = np.concatenate([cam.cy + cam.fy * c[:, 1] / c[:, 2] for c in cams])
        if us.min() < 0 or vs.min() < 0 or us.max() > cam.width - 1 or vs.max() > cam.height - 1:
            raise ValueError('object is outside the camera field of view: at camera height '
                             f'{spec.camera_height} m it projects to u {us.min():.0f}..{us.max():.0f}, '
                             f'v {vs.min():.0f}..{vs.max():.0f} px of a {cam.width} x {cam.height} image; '
                             'move it toward the optical axis (x = y = 0) or raise the camera')
        self.u0 = max(0, int(math.floor(us.min())) - margin)
        self.v0 = max(0, int(math.floor(vs.min())) - margin)
        u1 = min(cam.width, int(math.ceil(us.max())) + margin + 1)
        v1 = min(cam.height, int(math.ceil(vs.max())) + margin + 1)
        self.width, self.height = u1 - self.u0, v1 - self.v0
        self.fx, self.fy = cam.fx, cam.fy
        self.cx, self.cy = cam.cx - self.u0, cam.cy - self.v0
        corners = np.array([[[-0.5, -0.5], [self.width - 0.5, -0.5]],
                            [[-0.5, self.height - 0.5], [self.width - 0.5, self.height - 0.5]]])
        corner_rays = (corners - (self.cx, self.cy)) / (self.fx, self.fy)
        _, dz = pose.ray_dirs(corner_rays)
        if not (dz > 1e-3).all():
            raise ValueError('the camera view grazes the table: some pixel rays never meet the table plane; '
                             'reduce the camera tilt')

    @property
    def intrinsics(self) -> tuple[float, float, float, float, int, int]:
        """Cropped pinhole intrinsics ``(fx, fy, cx, cy, width, height)`` in px."""
        return self.fx, self.fy, self.cx, self.cy, self.width, self.height

    def pixel_rays(self, offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        """(H, W, 2) ray slopes (x/z, y/z) through the pixel centres shifted by ``offset`` px."""
        u = np.arange(self.width) + offset[0]
        v = np.arange(self.height) + offset[1]
        return np.stack(np.meshgrid((u - self.cx) / self.fx, (v - self.cy) / self.fy), axis=-1)
