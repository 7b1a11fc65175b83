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

    def __post_init__(self) -> None:
        if not (np.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(f'grid resolution must be a positive number of metres, got {self.resolution}')
        if self.width < 1 or self.height < 1:
            raise ValueError(f'grid must have at least one cell, got {self.height} x {self.width}')
        if not (np.isfinite(self.origin_x) and np.isfinite(self.origin_y) and np.isfinite(self.z)):
            raise ValueError('grid origin must be finite')

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
        return GridGeometry(self.origin_x, self.origin_y, res, width, height, self.z, self.frame_id)
