"""Signed distance of occupancy grids against analytic distances (gpis_grasp_ros.core.sdf)."""

from __future__ import annotations

import numpy as np
import pytest

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.sdf import signed_distance


def _grid(m: int = 40, size: float = 0.12) -> GridGeometry:
    return GridGeometry(-size / 2, -size / 2, size / m, m, m)


def test_disc_matches_analytic_distance_within_one_cell():
    g = _grid()
    c = g.cell_centers()
    radius = 0.035
    true = np.hypot(c[..., 0] - 0.004, c[..., 1] + 0.003) - radius
    sdf = signed_distance(true < 0, g.resolution)
    assert sdf.dtype == np.float64 and sdf.shape == g.shape
    assert np.max(np.abs(sdf - true)) <= g.resolution
    assert np.all(np.sign(sdf[np.abs(true) > g.resolution]) == np.sign(true[np.abs(true) > g.resolution]))


def test_rectangle_matches_analytic_box_distance_within_one_cell():
    g = _grid(50)
    c = g.cell_centers()
    half = np.array([0.03, 0.015])
    q = np.abs(c - np.array([0.005, -0.004])) - half
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    inside = np.minimum(np.max(q, axis=-1), 0.0)
    true = outside + inside
    sdf = signed_distance(true < 0, g.resolution)
    assert np.max(np.abs(sdf - true)) <= g.resolution
    # axis-aligned faces: the half-cell convention is exact along the axes
    row = g.height // 2
    assert np.allclose(sdf[row][np.abs(true[row]) < 0.01], true[row][np.abs(true[row]) < 0.01],
                       atol=0.51 * g.resolution)


def test_half_cell_convention_on_boundary():
    occ = np.zeros((5, 7), dtype=bool)
    occ[1:4, 2:5] = True
    res = 0.01
    sdf = signed_distance(occ, res)
    # edge-adjacent cells of opposite state read +-res/2: the zero level set is on the shared edge
    assert sdf[2, 1] == pytest.approx(0.5 * res)
    assert sdf[2, 2] == pytest.approx(-0.5 * res)
    assert sdf[2, 3] == pytest.approx(-1.5 * res)
    assert np.min(np.abs(sdf)) == pytest.approx(0.5 * res)
    assert np.all((sdf < 0) == occ)


def test_float_occupancy_is_thresholded_at_half():
    occ = np.zeros((6, 6))
    occ[2:4, 2:4] = 0.7
    occ[1, 1] = 0.49
    occ[4, 4] = 0.5
    sdf = signed_distance(occ, 0.005)
    assert np.all((sdf < 0) == (occ >= 0.5))


def test_outside_the_grid_is_free_space():
    sdf = signed_distance(np.ones((4, 4), dtype=bool), 0.01)
    # every cell is inside; the surface is the grid border
    assert np.all(sdf < 0)
    assert sdf[0, 0] == pytest.approx(-0.005)
    assert sdf[1, 1] == pytest.approx(-0.015)


@pytest.mark.parametrize('bad, res, match', [
    (np.zeros((4, 4), dtype=bool), 0.01, 'no object'),
    (np.ones((2, 2, 2), dtype=bool), 0.01, '2-D'),
    (np.ones((3, 3), dtype=bool), 0.0, 'resolution'),
    (np.full((3, 3), np.nan), 0.01, 'non-finite'),
])
def test_invalid_input_raises(bad, res, match):
    with pytest.raises(ValueError, match=match):
        signed_distance(bad, res)


def test_sdf_gradient_central_differences_and_validity():
    from gpis_grasp_ros.core.sdf import sdf_gradient

    g = _grid(12, 0.06)
    c = g.cell_centers()
    plane = 0.6 * c[..., 0] - 0.8 * c[..., 1] + 0.01  # a linear field: central differences are exact
    valid = np.ones(g.shape, bool)
    valid[4, 7] = False
    grad, defined = sdf_gradient(plane, g.resolution, valid)
    assert grad.shape == (12, 12, 2) and defined.shape == (12, 12, 2)
    np.testing.assert_allclose(grad[defined[..., 0], 0], 0.6, atol=1e-12)
    np.testing.assert_allclose(grad[defined[..., 1], 1], -0.8, atol=1e-12)
    # x needs both column neighbours, y both row neighbours, inside the grid and valid
    assert not defined[:, 0, 0].any() and not defined[:, -1, 0].any()
    assert not defined[0, :, 1].any() and not defined[-1, :, 1].any()
    assert not defined[4, 6, 0] and not defined[4, 8, 0] and not defined[4, 7, 0] and defined[4, 5, 0]
    assert not defined[3, 7, 1] and not defined[5, 7, 1] and not defined[4, 7, 1] and defined[6, 7, 1]
    assert np.all(grad[~defined] == 0.0)
    with pytest.raises(ValueError, match='valid mask'):
        sdf_gradient(plane, g.resolution, valid[:-1])
