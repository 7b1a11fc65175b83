"""Noise-map stage (core.sensing.noise_map): unknown cells, their variance floor, propagation."""

from __future__ import annotations

import numpy as np
import pytest

from gpis_grasp_ros.core.sensing import SensingParams
from gpis_grasp_ros.core.sensing.noise_map import _extended_regions, _propagation_variance, noise_map
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
