"""Metric geometry of the M x M grids used throughout the package (paper section III).

Conventions (shared by every module, every message and every test):

* Arrays are indexed ``[row, col]``; rows run along +y and columns along +x of the sensor
  frame (for a camera looking down at the table, the optical frame: x right, y down), so the
  grid's frame of reference is at the top-left corner, as in the paper's Fig. 3.
* ``origin_x, origin_y`` (metres) is the outer corner of cell (0, 0), exactly like
  ``nav_msgs/MapMetaData.origin``; the centre of cell (row, col) is at
  ``(origin_x + (col + 0.5) * resolution, origin_y + (row + 0.5) * resolution)``.
* ``resolution`` is metres per cell. Points handed between modules are metric ``(x, y)``;
  *cell coordinates* ``(u, v) = (col, row)`` are fractional and place cell centres on integers.
* ``z`` is the table plane's depth in the sensor frame (m); grids lie in that plane.

**Grid pose (tilted cameras).** A grid lies in the table plane but need not be fronto-parallel.
``rotation`` (row-major 3 x 3, default identity) holds the grid frame's axes as columns in the
sensor frame: x and y in the table plane, z = **−table normal** (pointing into the table, away
from the camera, like the optical axis of a top-down camera and like a gripper's approach). A grid
point ``(x, y)`` at height ``h`` above the table (along the normal, towards the camera) is the
sensor-frame point ``R @ (x, y, z − h)``: ``z`` is the distance of the plane from the camera along
the grid's z axis. The identity rotation gives exactly the top-down convention above. The metric
core works in grid coordinates ``(x, y)`` and never needs ``R``; only the sensor-facing code
(segmentation, messages, poses) does. ``MapMetaData.origin`` carries the full pose
(:meth:`GridGeometry.corner_pose` / :meth:`GridGeometry.from_corner_pose`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GridGeometry:
    """Placement of a ``height x width`` grid in the sensor frame (all lengths in metres)."""

    origin_x: float
    origin_y: float
    resolution: float
    width: int
    height: int
    z: float = 0.0
    frame_id: str = ''
    #: Grid axes (columns) in the sensor frame, row-major 3 x 3; z axis = −table normal.
    rotation: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(f'grid resolution must be a positive number of metres, got {self.resolution}')
        if self.width < 1 or self.height < 1:
            raise ValueError(f'grid must have at least one cell, got {self.height} x {self.width}')
        if not (np.isfinite(self.origin_x) and np.isfinite(self.origin_y) and np.isfinite(self.z)):
            raise ValueError('grid origin must be finite')
        r = np.asarray(self.rotation, dtype=np.float64)
        if r.shape != (9,) or not np.isfinite(r).all():
            raise ValueError(f'grid rotation must be 9 finite numbers (row-major 3 x 3), got {self.rotation!r}')
        r = r.reshape(3, 3)
        if not (np.allclose(r.T @ r, np.eye(3), atol=1e-6) and np.linalg.det(r) > 0):
            raise ValueError('grid rotation must be a proper rotation matrix (orthonormal, det +1)')
        object.__setattr__(self, 'rotation', tuple(float(v) for v in r.ravel()))

    @property
    def rotation_matrix(self) -> np.ndarray:
        """``R`` (3 x 3): grid axes as columns in the sensor frame (z = −table normal)."""
        return np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)

    @property
    def table_normal(self) -> np.ndarray:
        """Unit table normal in the sensor frame, pointing to the camera side (= −R[:, 2])."""
        return -self.rotation_matrix[:, 2]

    def to_sensor(self, xy: np.ndarray, height: float | np.ndarray = 0.0) -> np.ndarray:
        """Grid-frame points ``(..., 2)`` (m) at ``height`` (m) above the table → sensor frame ``(..., 3)``."""
        xy = np.asarray(xy, dtype=np.float64)
        h = np.broadcast_to(np.asarray(height, dtype=np.float64), xy.shape[:-1])
        local = np.concatenate([xy, (self.z - h)[..., None]], axis=-1)
        return local @ self.rotation_matrix.T

    def from_sensor(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sensor-frame points ``(..., 3)`` → (grid-frame ``(x, y)`` (..., 2), height above the table (...))."""
        local = np.asarray(points, dtype=np.float64) @ self.rotation_matrix
        return local[..., :2], self.z - local[..., 2]

    def corner_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Pose of the grid for ``MapMetaData.origin``: (position of the outer corner of cell (0, 0) in
        the sensor frame, orientation quaternion ``(x, y, z, w)`` of ``R``)."""
        return self.to_sensor(np.array([self.origin_x, self.origin_y])), rotation_to_quaternion(self.rotation_matrix)

    @classmethod
    def from_corner_pose(cls, position: np.ndarray, quaternion: np.ndarray, resolution: float, width: int,
                         height: int, frame_id: str = '') -> GridGeometry:
        """Inverse of :meth:`corner_pose` (the grid's (x, y) origin and ``z`` are recovered from the pose)."""
        r = quaternion_to_rotation(quaternion)
        local = r.T @ np.asarray(position, dtype=np.float64)
        return cls(float(local[0]), float(local[1]), float(resolution), int(width), int(height), float(local[2]),
                   frame_id, tuple(float(v) for v in r.ravel()))

    @property
    def shape(self) -> tuple[int, int]:
        """Array shape ``(rows, cols)``."""
        return (self.height, self.width)

    @property
    def size_m(self) -> tuple[float, float]:
        """Extent ``(x, y)`` of the grid in metres."""
        return (self.width * self.resolution, self.height * self.resolution)

    def cell_centers(self) -> np.ndarray:
        """Metric centres of all cells, shape ``(height, width, 2)`` holding ``(x, y)`` in m."""
        cols = self.origin_x + (np.arange(self.width) + 0.5) * self.resolution
        rows = self.origin_y + (np.arange(self.height) + 0.5) * self.resolution
        xx, yy = np.meshgrid(cols, rows)
        return np.stack([xx, yy], axis=-1)

    def to_cell(self, xy: np.ndarray) -> np.ndarray:
        """Metric ``(..., 2)`` points (m) → fractional cell coordinates ``(col, row)``."""
        xy = np.asarray(xy, dtype=np.float64)
        origin = np.array([self.origin_x, self.origin_y])
        return (xy - origin) / self.resolution - 0.5

    def to_metric(self, uv: np.ndarray) -> np.ndarray:
        """Fractional cell coordinates ``(..., 2)`` as ``(col, row)`` → metric ``(x, y)`` in m."""
        uv = np.asarray(uv, dtype=np.float64)
        origin = np.array([self.origin_x, self.origin_y])
        return origin + (uv + 0.5) * self.resolution

    def with_shape(self, width: int, height: int) -> GridGeometry:
        """Same metric extent resampled to ``width x height`` cells (square cells, x extent kept)."""
        res = self.size_m[0] / width
        return GridGeometry(self.origin_x, self.origin_y, res, width, height, self.z, self.frame_id, self.rotation)


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` → 3 x 3 rotation matrix (normalised first; zero or non-finite → ValueError)."""
    q = np.asarray(q, dtype=np.float64).ravel()
    n = float(np.linalg.norm(q)) if q.shape == (4,) and np.isfinite(q).all() else 0.0
    if not 0.5 < n < 2.0:
        raise ValueError(f'orientation must be a unit quaternion (x, y, z, w), got {q.tolist()}')
    x, y, z, w = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def rotation_to_quaternion(r: np.ndarray) -> np.ndarray:
    """3 x 3 rotation matrix → unit quaternion ``(x, y, z, w)`` with w ≥ 0 (Shepperd's method)."""
    r = np.asarray(r, dtype=np.float64)
    tr = np.trace(r)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q
