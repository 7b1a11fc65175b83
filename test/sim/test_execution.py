"""Simulated execution of a planned grasp on the true shape (sim.execution)."""

from __future__ import annotations

import math

import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.sim.execution import execute_grasp_trials
from support.synthetic_shapes import make_geometry, rectangle_sdf


def test_execute_grasp_trials_on_a_finer_true_grid() -> None:
    """Simulated execution closes on the TRUE SDF, whose grid differs from the planning grid."""
    true_g = GridGeometry(-0.02, -0.01, 0.002, 80, 80)
    c = np.array([0.0625, 0.0625])
    true_sdf = rectangle_sdf(true_g, tuple(c), (0.015, 0.01))
    gripper = GripperParams().resolved(make_geometry())  # σ_g fixed on the 5 mm planning grid
    rng = np.random.default_rng(0)
    good = execute_grasp_trials(true_sdf, true_g, c - [0.045, 0], c + [0.045, 0], gripper, 200, rng)
    assert good >= 195
    beside = execute_grasp_trials(true_sdf, true_g, c + [-0.045, 0.02], c + [0.045, 0.02], gripper, 50, rng)
    assert beside == 0
    too_wide = execute_grasp_trials(true_sdf, true_g, c - [0.05, 0], c + [0.05, 0], gripper, 50, rng)
    assert too_wide == 0
    tilted = np.array([math.sin(math.radians(33)), math.cos(math.radians(33))])  # > arctan γ from the normal
    assert execute_grasp_trials(true_sdf, true_g, c - 0.045 * tilted, c + 0.045 * tilted, gripper, 50, rng) <= 5
