"""Recorded scenes read back for offline use (data/bags.load_bag)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gpis_grasp_ros.core.gpis import center_of_mass
from gpis_grasp_ros.data.bags import load_bag

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize('bag', [ROOT / 'bags' / 'D_toy_plane.mcap', ROOT / 'bags' / 'head' / 'D_toy_plane.mcap'])
def test_true_center_of_mass_is_in_the_truth_grid_frame(bag):
    """The bag's ground-truth centre of mass (a camera-frame 3D point) comes back as (x, y) of the true
    grid's frame: equal to the centroid of the true shape on that grid, top-down and tilted alike."""
    scene = load_bag(bag, frames=1)
    assert scene.true_center_of_mass.shape == (2,)
    centroid = center_of_mass(scene.true_sdf[None], scene.true_geometry)[0]
    assert np.linalg.norm(scene.true_center_of_mass - centroid) < 1.5 * scene.true_geometry.resolution
