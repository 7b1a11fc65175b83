"""Noise-map stage (core.sensing.noise_map): unknown cells, their variance floor, propagation."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gpis_grasp_ros.core.sdf import signed_distance
from gpis_grasp_ros.core.sensing import SensingParams
from gpis_grasp_ros.core.sensing.noise_map import (
    _extended_regions,
    _propagation_variance,
    _sdf_change_near,
    noise_map,
)
from gpis_grasp_ros.core.sensing.rasterise import Cells
from support.synthetic_shapes import make_geometry


def _cells(occupancy: np.ndarray, disagreement: np.ndarray) -> Cells:
    m = occupancy.shape[0]
    z = np.zeros((m, m), bool)
    px = np.full((2, 2), np.nan)
    return Cells(make_geometry(m, 0.005), px, px, np.zeros((2, 2), bool), np.zeros((2, 2), bool), ~z, z, occupancy,
                 z, np.zeros((m, m)), disagreement, np.full((m, m), 1e-6), z, z, z, z)


def test_certain_cells_are_all_trained_with_their_depth_variance():
    occ = np.zeros((15, 15))
    occ[5:10, 5:10] = 1.0
    params = SensingParams(grid_size=15)
    out = noise_map(_cells(occ, np.zeros((15, 15))), np.zeros((2, 2), bool), np.zeros((2, 2), bool),
                    np.zeros((2, 2), bool), params)
    assert out.train_mask.all() and not out.uncertain.any()
    assert np.allclose(out.noise, 1e-6)


def test_an_extended_disagreeing_region_is_unknown_a_band_is_not():
    occ = np.zeros((15, 15))
    occ[5:10, 5:8] = 1.0
    rho = np.zeros((15, 15))
    rho[5:10, 8:11] = 1.0  # 3 cells wide: unknown
    rho[2, 2:12] = 1.0  # a one-cell band: edge noise
    params = SensingParams(grid_size=15)
    out = noise_map(_cells(occ, rho), np.zeros((2, 2), bool), np.zeros((2, 2), bool), np.zeros((2, 2), bool), params)
    assert not out.train_mask[5:10, 8:11].any() and out.train_mask[2, 2:12].all()
    assert out.uncertain[2, 2:12].all()
    assert (out.noise[~out.train_mask] >= params.disagreement_variance_m2).all()
    assert np.array_equal(_extended_regions(rho > 0.5), ~out.train_mask)


def test_no_occupied_cell_is_refused_and_nothing_uncertain_propagates_nothing():
    params = SensingParams(grid_size=9)
    with pytest.raises(ValueError, match='no object found'):
        noise_map(_cells(np.zeros((9, 9)), np.zeros((9, 9))), np.zeros((2, 2), bool), np.zeros((2, 2), bool),
                  np.zeros((2, 2), bool), params)
    g = make_geometry(9, 0.005)
    occ = np.zeros((9, 9), bool)
    occ[3:6, 3:6] = True
    assert not _propagation_variance(occ, np.zeros((9, 9), bool), ~occ, g, params).any()
    uncertain = np.zeros((9, 9), bool)
    uncertain[3:6, 6] = True
    var = _propagation_variance(occ | uncertain, uncertain, np.ones((9, 9), bool), g, params)
    assert var[4, 8] > 0 and var[4, 0] == 0.0  # beside the uncertain column, not beyond the object


def test_the_sdf_change_near_a_component_is_the_whole_grids_bit_for_bit():
    """200 random grids (blobs, specks, objects at the border, components inside and outside the occupancy, reach
    discs of 1-12 cells, grids 5-60 cells): the windowed difference equals the whole-grid signed distances'
    difference exactly on the cells near the component, and is 0 elsewhere."""
    rng = np.random.default_rng(12)
    for case in range(200):
        h, w = rng.integers(5, 61, size=2)
        occ = rng.random((h, w)) < rng.uniform(0.02, 0.4)
        occ = cv2.morphologyEx(occ.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)).astype(bool)
        comp = np.zeros((h, w), bool)
        v, u = rng.integers(0, h), rng.integers(0, w)
        dv, du = rng.integers(1, max(2, h // 3)), rng.integers(1, max(2, w // 3))
        comp[v:v + dv, u:u + du] = True
        if rng.random() < 0.5:
            comp &= occ | (rng.random((h, w)) < 0.5)
        rest = occ & ~comp
        if not comp.any() or not rest.any():
            continue
        res = 0.004
        radius = rng.integers(1, 13) * res
        near = cv2.distanceTransform((~comp).astype(np.uint8), cv2.DIST_L2, 5) * res <= radius
        full = np.where(near, signed_distance(occ | comp, res) - signed_distance(rest, res), 0.0)
        np.testing.assert_array_equal(_sdf_change_near(occ, comp, near, res), full, err_msg=f'case {case}')


def test_the_compiled_distance_transform_is_scipys_bit_for_bit():
    """400 random masks (1-80 cells a side, sparse to dense, single cells, lines, one feature): the compiled
    squared distances, square-rooted, are scipy's Euclidean distance transform to the last bit, both ways."""
    from scipy.ndimage import distance_transform_edt

    from gpis_grasp_ros.core.sensing.noise_map import _squared_distances

    rng = np.random.default_rng(21)
    for case in range(400):
        h, w = (int(v) for v in rng.integers(1, 81, size=2))
        win = rng.random((h, w)) < rng.choice([0.01, 0.1, 0.5, 0.9, 0.99])
        if case % 7 == 0:
            win[:] = False
            win[rng.integers(h), rng.integers(w)] = True
        for feature in (True, False):
            if not (win == feature).any():
                continue
            out = np.empty((h, w))
            _squared_distances(win, feature, out)
            ref = distance_transform_edt(win != feature)
            np.testing.assert_array_equal(np.sqrt(out), ref, err_msg=f'case {case}, feature {feature}')
