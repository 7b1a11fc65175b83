"""Rasterise stage (core.sensing.rasterise): a known footprint's cells, the grid around the target."""

from __future__ import annotations

import numpy as np
import pytest

from gpis_grasp_ros.core.sensing import SensingParams, segment_frames
from gpis_grasp_ros.core.sensing.rasterise import _table_area_weights, grid_around
from gpis_grasp_ros.core.table_frame import TableFrame
from support.tilted_scene import Box, TiltedScene


@pytest.mark.parametrize('tilt', [0.0, 40.0])
def test_a_box_footprint_occupies_its_cells(tilt):
    """A 6 x 4 cm box: grid cells whose centres lie half a cell inside its footprint are occupied, cells a cell
    outside it are free (all of them from straight above; at 40 degrees, where the walls and the hidden strip
    behind the box blur the edges, 90 % and 98 %)."""
    box = Box(0.0, 0.0, 0.03, 0.02, 0.03)
    scene = TiltedScene(tilt, boxes=[box], width=320, height=240, focal_px=285.0)
    rgb, depth, _ = scene.frames(3, seed=0)
    result = segment_frames(rgb, depth, scene.intrinsics, SensingParams())
    g = result.geometry
    xy = scene.table_xy(g.to_sensor(g.cell_centers()))
    r = g.resolution
    dx, dy = np.abs(xy[..., 0] - box.x), np.abs(xy[..., 1] - box.y)
    inside = (dx < box.half_x - r / 2) & (dy < box.half_y - r / 2)
    outside = (dx > box.half_x + r) | (dy > box.half_y + r)
    occupied = result.occupancy >= 0.5
    assert inside.sum() > 100
    assert occupied[inside].mean() >= (1.0 if tilt == 0 else 0.9)
    assert occupied[outside].mean() <= (0.0 if tilt == 0 else 0.02)
    if tilt == 0:
        assert result.observed[inside].all()


def test_grid_around_a_footprint():
    table = TableFrame.from_plane(0.0, 0.0, -1.0, 0.7)
    xy = np.array([[0.0, 0.0], [0.06, 0.0], [0.06, 0.04], [0.0, 0.04]])
    g = grid_around(xy, table, SensingParams(grid_size=20, margin=0.25), 'cam')
    assert g.shape == (20, 20) and g.frame_id == 'cam'
    assert g.resolution == pytest.approx(0.06 * 1.5 / 20)
    assert (g.origin_x, g.origin_y) == pytest.approx((0.03 - 0.045, 0.02 - 0.045))


def test_area_weights_of_a_flat_table_and_of_a_window():
    """Feet on the table itself cover a table pixel's area each (weight 1); a window with 2 pixels around it
    gives its inner pixels the weights of the whole image (the median filter and the differences read no
    farther)."""
    yy, xx = np.mgrid[:12, :15].astype(np.float64)
    feet = np.stack([0.002 * xx + 0.0005 * yy, 0.003 * yy], axis=-1)
    w = _table_area_weights(feet, feet, np.ones((12, 15), bool))
    assert np.allclose(w[2:-2, 2:-2], 1.0, atol=1e-4)  # the median filter's border aside
    bumpy = feet + np.random.default_rng(0).normal(0.0, 5e-4, feet.shape)
    valid = np.random.default_rng(1).random((12, 15)) > 0.2
    whole = _table_area_weights(bumpy, feet, valid)
    for box in (np.s_[3:9, 4:12], np.s_[0:7, 0:9], np.s_[5:12, 8:15]):
        part = _table_area_weights(bumpy[box], feet[box], valid[box])
        inner = tuple(slice(b.start + (2 if b.start else 0), b.stop - (2 if b.stop < n else 0))
                      for b, n in zip(box, (12, 15), strict=True))
        rel = tuple(slice(i.start - b.start, i.stop - b.start) for i, b in zip(inner, box, strict=True))
        assert np.array_equal(part[rel], whole[inner])
