"""Analytic RGB-D renderer for tests: boxes and lying cylinders on a table plane seen by a tilted pinhole camera.

Independent of the package's simulator: every pixel's ray is intersected exactly with the table
plane and with each box (slab method) in the *true* table frame built here. The camera is
pitched by ``tilt_deg`` about its x axis, so the table's upward normal in the camera frame is
n = (0, -sin t, -cos t) and the plane is n . p + d = 0 (d = camera height above the table, m).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gpis_grasp_ros.core.noise_model import SensorModel
from gpis_grasp_ros.core.sensing import CameraIntrinsics

TABLE_RGB = np.array([150.0, 140.0, 120.0])


@dataclass
class Box:
    """Box on the table: centre (x, y) and half sizes in the true table frame (m), height (m), turned by
    ``yaw_deg`` about the table normal (0: edges along the table frame's axes)."""

    x: float
    y: float
    half_x: float
    half_y: float
    height: float
    rgb: tuple[float, float, float] = (40.0, 90.0, 200.0)
    yaw_deg: float = 0.0

    def local_xy(self, xy: np.ndarray) -> np.ndarray:
        """True table points (x, y) (relative to the optical axis' foot) in the box's own frame: centre at 0,
        axes along its edges (m)."""
        c, s = np.cos(np.radians(self.yaw_deg)), np.sin(np.radians(self.yaw_deg))
        dx, dy = xy[..., 0] - self.x, xy[..., 1] - self.y
        return np.stack([c * dx + s * dy, -s * dx + c * dy], axis=-1)


@dataclass
class Cylinder:
    """Cylinder lying on the table, its axis along the true table frame's x from ``x0`` to ``x1`` at ``y``, at
    height ``radius`` (m)."""

    x0: float
    x1: float
    y: float
    radius: float
    rgb: tuple[float, float, float] = (60.0, 60.0, 60.0)


@dataclass
class TiltedScene:
    tilt_deg: float
    distance_m: float = 0.8  # along the optical axis to the table
    boxes: list[Box] = field(default_factory=list)
    cylinders: list[Cylinder] = field(default_factory=list)  # labelled after the boxes
    width: int = 640
    height: int = 480
    focal_px: float = 570.0  # VGA, like the Carmine
    shadows: list[tuple[float, float, float, float, float]] = field(default_factory=list)  # (x0, y0, x1, y1, gain)
    prints: list[tuple[float, float, float, float, tuple[float, float, float]]] = field(default_factory=list)
    #       flat marks on the table: (x0, y0, x1, y1, rgb)

    @property
    def normal(self) -> np.ndarray:
        t = np.radians(self.tilt_deg)
        return np.array([0.0, -np.sin(t), -np.cos(t)])

    @property
    def offset(self) -> float:
        """d of n . p + d = 0: the optical axis meets the table at ``distance_m``."""
        return float(-self.normal @ np.array([0.0, 0.0, self.distance_m]))

    @property
    def frame(self) -> np.ndarray:
        """True table frame: columns x (= camera x), y, z = -n; table point (x, y) at depth d along z."""
        z = -self.normal
        x = np.array([1.0, 0.0, 0.0])
        return np.stack([x, np.cross(z, x), z], axis=1)

    @property
    def origin_xy(self) -> np.ndarray:
        """Table (x, y) of the point where the optical axis meets the table (boxes are placed around it)."""
        return (np.array([0.0, 0.0, self.distance_m]) @ self.frame)[:2]

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return CameraIntrinsics(self.focal_px, self.focal_px, (self.width - 1) / 2, (self.height - 1) / 2,
                                self.width, self.height)

    def to_camera(self, xy: np.ndarray, h: float = 0.0) -> np.ndarray:
        """True table (x, y) relative to the optical axis' foot, at height h → camera frame."""
        xy = np.asarray(xy, dtype=np.float64) + self.origin_xy
        local = np.concatenate([xy, np.full(xy.shape[:-1] + (1,), self.offset - h)], axis=-1)
        return local @ self.frame.T

    def table_xy(self, points: np.ndarray) -> np.ndarray:
        """Camera points → true table (x, y) relative to the optical axis' foot."""
        return (np.asarray(points) @ self.frame)[..., :2] - self.origin_xy

    def render(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Noise-free (depth (H, W) m, NaN = no hit; rgb (H, W, 3) float; label (H, W): 0 table, k = box k)."""
        intr = self.intrinsics
        u, v = np.meshgrid(np.arange(self.width), np.arange(self.height))
        rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(u.shape)], axis=-1)
        local = rays @ self.frame  # ray directions in the table frame
        d = self.offset
        with np.errstate(divide='ignore', invalid='ignore'):
            t_best = np.where(local[..., 2] > 1e-9, d / local[..., 2], np.inf)
        label = np.zeros(u.shape, dtype=np.int64)
        ox, oy = self.origin_xy
        for k, b in enumerate(self.boxes, start=1):
            centre = np.array([ox + b.x, oy + b.y, 0.0])
            c, s = np.cos(np.radians(b.yaw_deg)), np.sin(np.radians(b.yaw_deg))
            rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # box frame -> table frame
            start = centre - centre @ rot  # the camera (table-frame origin) in the box's frame: R^T (0 - c) + c
            direction = local @ rot
            lo = np.array([ox + b.x - b.half_x, oy + b.y - b.half_y, d - b.height])
            hi = np.array([ox + b.x + b.half_x, oy + b.y + b.half_y, d])
            with np.errstate(divide='ignore', invalid='ignore'):
                t1 = (lo - start) / direction
                t2 = (hi - start) / direction
            t_near = np.nanmax(np.minimum(t1, t2), axis=-1)
            t_far = np.nanmin(np.maximum(t1, t2), axis=-1)
            hit = (t_near <= t_far) & (t_near > 0) & (t_near < t_best)
            t_best = np.where(hit, t_near, t_best)
            label = np.where(hit, k, label)
        for k, cyl in enumerate(self.cylinders, start=len(self.boxes) + 1):
            t_hit = self._cylinder_hit(local, cyl)
            hit = t_hit < t_best
            t_best = np.where(hit, t_hit, t_best)
            label = np.where(hit, k, label)
        depth = np.where(np.isfinite(t_best), t_best, np.nan)  # rays have z = 1: t is the depth
        rgb = np.broadcast_to(TABLE_RGB, u.shape + (3,)).copy()
        table_xy = self.table_xy(rays * depth[..., None])
        for x0, y0, x1, y1, gain in self.shadows:
            sh = (label == 0) & (table_xy[..., 0] >= x0) & (table_xy[..., 0] <= x1) & (table_xy[..., 1] >= y0) \
                & (table_xy[..., 1] <= y1)
            rgb[sh] *= gain
        for x0, y0, x1, y1, colour in self.prints:
            mark = (label == 0) & (table_xy[..., 0] >= x0) & (table_xy[..., 0] <= x1) & (table_xy[..., 1] >= y0) \
                & (table_xy[..., 1] <= y1)
            rgb[mark] = colour
        for k, b in enumerate(self.boxes + self.cylinders, start=1):
            rgb[label == k] = b.rgb
        return depth, rgb, label

    def _cylinder_hit(self, local: np.ndarray, cyl: Cylinder) -> np.ndarray:
        """Ray parameter (= depth) of the first hit of rays ``local`` (table frame) on ``cyl``'s side or end caps."""
        ox, oy = self.origin_xy
        yc, zc = oy + cyl.y, self.offset - cyl.radius  # the axis, in the table frame (the camera at its origin)
        lx, ly, lz = local[..., 0], local[..., 1], local[..., 2]
        a, b, c = ly ** 2 + lz ** 2, ly * yc + lz * zc, yc ** 2 + zc ** 2 - cyl.radius ** 2
        with np.errstate(divide='ignore', invalid='ignore'):
            t_side = (b - np.sqrt(b ** 2 - a * c)) / a
            x = t_side * lx
            t = np.where(np.isfinite(t_side) & (t_side > 0) & (x >= ox + cyl.x0) & (x <= ox + cyl.x1), t_side, np.inf)
            for x_cap in (ox + cyl.x0, ox + cyl.x1):
                t_cap = x_cap / lx
                inside = (t_cap * ly - yc) ** 2 + (t_cap * lz - zc) ** 2 <= cyl.radius ** 2
                t = np.where(np.isfinite(t_cap) & (t_cap > 0) & inside & (t_cap < t), t_cap, t)
        return t

    def frames(self, n: int = 10, seed: int = 0, model: SensorModel | None = None,
               rgb_noise: float = 2.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``n`` noisy frames (rgb uint8 (n, H, W, 3), depth (n, H, W) m) and the label image."""
        model = model or SensorModel()
        rng = np.random.default_rng(seed)
        depth, rgb, label = self.render()
        sigma = model.sigma(np.nan_to_num(depth, nan=1.0))
        d = depth[None] + sigma[None] * rng.standard_normal((n,) + depth.shape)
        c = np.clip(np.round(rgb[None] + rgb_noise * rng.standard_normal((n,) + rgb.shape)), 0, 255).astype(np.uint8)
        return c, d, label


def tilt_table(tilts: tuple[float, ...] = (0.0, 30.0, 50.0, 60.0)) -> list[str]:
    """README rows: fitted-plane and footprint errors of a 6 x 4 x 4 cm box at each tilt (10 Carmine frames)."""
    from gpis_grasp_ros.core.sensing import segment_frames

    box = Box(0.0, 0.0, 0.03, 0.02, 0.04)
    rows = []
    for tilt in tilts:
        scene = TiltedScene(tilt, boxes=[box])
        rgb, depth, _ = scene.frames(10, seed=int(tilt))
        r = segment_frames(rgb, depth, scene.intrinsics)
        angle = np.degrees(np.arccos(np.clip(r.table.n @ scene.normal, -1, 1)))
        g = r.geometry
        x0, y0, (sx, sy) = g.origin_x, g.origin_y, g.size_m
        corners = np.array([[x0, y0], [x0 + sx, y0], [x0, y0 + sy], [x0 + sx, y0 + sy]])
        off_plane = np.abs(g.to_sensor(corners) @ scene.normal + scene.offset).max()
        xy = scene.table_xy(g.to_sensor(g.cell_centers()))
        inside = (np.abs(xy[..., 0] - box.x) < box.half_x) & (np.abs(xy[..., 1] - box.y) < box.half_y)
        occ = r.occupancy >= 0.5
        rows.append(f'| {tilt:.0f} | {angle:.3f} | {abs(r.table.offset_m - scene.offset) * 1000:.2f} | '
                    f'{off_plane * 1000:.2f} | {(inside & occ).sum() / (inside | occ).sum():.2f} |')
    return rows


if __name__ == '__main__':
    print('\n'.join(tilt_table()))
