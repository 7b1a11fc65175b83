"""Simulated execution of a planned grasp on the true shape (sim.execution)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.core.quality import draw_shape_samples, probability_force_closure
from gpis_grasp_ros.sim.execution import execute_grasp_trials
from support.synthetic_shapes import make_posterior, rectangle_sdf


def test_execute_grasp_trials_on_a_finer_true_grid() -> None:
    """Simulated execution closes on the TRUE SDF, whose grid differs from the planning grid."""
    true_g = GridGeometry(-0.02, -0.01, 0.002, 80, 80)
    c = np.array([0.0625, 0.0625])
    true_sdf = rectangle_sdf(true_g, tuple(c), (0.015, 0.01))
    gripper = GripperParams()  # σ_g in metres: the same on the planning grid and on the true grid
    rng = np.random.default_rng(0)
    good = execute_grasp_trials(true_sdf, true_g, c - [0.045, 0], c + [0.045, 0], gripper, 200, rng)
    assert good >= 195
    beside = execute_grasp_trials(true_sdf, true_g, c + [-0.045, 0.02], c + [0.045, 0.02], gripper, 50, rng)
    assert beside == 0
    too_wide = execute_grasp_trials(true_sdf, true_g, c - [0.05, 0], c + [0.05, 0], gripper, 50, rng)
    assert too_wide == 0
    tilted = np.array([math.sin(math.radians(33)), math.cos(math.radians(33))])  # > arctan γ from the normal
    assert execute_grasp_trials(true_sdf, true_g, c - 0.045 * tilted, c + 0.045 * tilted, gripper, 50, rng) <= 5


def _pf_and_execution(truth: np.ndarray, truth_g: GridGeometry, plan_sdf: np.ndarray, plan_g: GridGeometry,
                      n_grasps: int, trials: int) -> tuple[np.ndarray, np.ndarray]:
    """P_F of random grasps on a zero-variance posterior of ``plan_sdf`` and their closure rate on ``truth``."""
    post = make_posterior(plan_sdf, plan_g, 0.0)  # zero variance: every shape sample is the mean
    gripper = GripperParams()
    samples = draw_shape_samples(post, trials, np.random.default_rng(1))
    rng = np.random.default_rng(2)
    centre = np.array([0.0625, 0.0625]) + rng.uniform(-0.012, 0.012, (n_grasps, 2))
    angle = rng.uniform(0.0, np.pi, n_grasps)
    axis = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    j1, j2 = centre - 0.04 * axis, centre + 0.04 * axis
    pf = probability_force_closure(j1, j2, samples, gripper, gripper.sigma_g).p
    ex = np.array([execute_grasp_trials(truth, truth_g, a, b, gripper, trials, rng) for a, b in zip(j1, j2,
                                                                                                   strict=True)])
    return pf, ex / trials


def _lozenge(g: GridGeometry) -> np.ndarray:
    """A rounded, notched rectangle: flat faces, corners and a notch give closure rates between 0 and 1."""
    c = (0.0625, 0.0625)
    body = rectangle_sdf(g, c, (0.016, 0.009), angle=0.3) - 0.003
    return np.maximum(body, -rectangle_sdf(g, (0.0625 + 0.012, 0.0625 + 0.008), (0.005, 0.005)))


def test_pf_on_a_certain_posterior_is_the_simulated_closure_rate() -> None:
    """One execution model: a grasp's P_F on a posterior that IS the truth (zero variance) is its closure rate
    in simulated execution on that truth - same gripper, jaw noise, contacts and force-closure test - up to
    Monte-Carlo error (400 draws each: std of a difference <= 0.035, fixed seeds)."""
    g = GridGeometry(0.0, 0.0, 0.005, 25, 25)
    sdf = _lozenge(g)
    pf, rate = _pf_and_execution(sdf, g, sdf, g, 200, 400)
    between = (pf > 0.05) & (pf < 0.95)
    assert between.sum() >= 30  # the test exercises grasps whose outcome the jaw noise decides
    assert np.max(np.abs(pf - rate)) <= 0.05 + 3.5 * 0.035  # every grasp, a 4.5-sigma Monte-Carlo band
    assert np.mean(np.abs(pf - rate)) <= 0.05
    assert abs(np.mean(pf - rate)) <= 0.01  # no bias



def test_other_objects_fail_the_jaws_that_meet_them() -> None:
    """The truth's other objects are obstacles, as in the planner's world: a grasp whose jaw closes through or
    starts in a neighbour fails every trial (its nominal grasp is 'on_obstacle' / 'start_inside'); a grasp whose
    jaws stay clear of it is executed exactly as without it (same draws, same successes)."""
    from gpis_grasp_ros.tools.evaluation.truth import TrueShape

    g = GridGeometry(-0.02, -0.01, 0.001, 170, 170)
    c = np.array([0.0625, 0.0625])
    target = rectangle_sdf(g, tuple(c), (0.015, 0.01))
    neighbour = rectangle_sdf(g, (0.0625 + 0.045, 0.0625), (0.018, 0.02))  # 12 mm right of the target
    gripper = GripperParams()
    free, blocked = TrueShape(target, g), TrueShape(target, g, obstacles=neighbour)
    across = (c - [0.022, 0.0], c + [0.066, 0.0])  # the right jaw starts beyond the neighbour and closes through it
    assert free.execute(*across, gripper, 100, np.random.default_rng(0)) >= 95
    assert blocked.execute(*across, gripper, 100, np.random.default_rng(0)) == 0
    assert blocked.nominal_quality(*across, gripper)[1] == 'on_obstacle'
    inside = (c - [0.040, 0.0], c + [0.045, 0.0])  # the right jaw starts in the neighbour's middle (6 sigma_g deep)
    assert blocked.nominal_quality(*inside, gripper)[1] == 'start_inside'
    assert blocked.execute(*inside, gripper, 100, np.random.default_rng(0)) == 0
    along = (c - [0.0, 0.030], c + [0.0, 0.030])  # across the short side, 12 mm from the neighbour's face
    n_free = free.execute(*along, gripper, 200, np.random.default_rng(3))
    assert n_free >= 190
    assert blocked.execute(*along, gripper, 200, np.random.default_rng(3)) == n_free
    assert free.com == pytest.approx(blocked.com) and free.rho == blocked.rho  # the target's, not the scene's


def test_every_execution_is_counted_once_by_what_it_did() -> None:
    """The outcome of a grasp's executions: closures as execute_grasp_trials counts them (same draws); a jaw
    closing through a neighbour is a collision, a grasp beside the object a miss, a grasp whose closing line
    leaves the friction cone a slip, a jaw starting inside the object a collision too; the causes add up to the
    trials; too wide an opening fails every trial."""
    from gpis_grasp_ros.sim.execution import execute_grasp_outcome

    g = GridGeometry(-0.02, -0.01, 0.001, 170, 170)
    c = np.array([0.0625, 0.0625])
    target = rectangle_sdf(g, tuple(c), (0.015, 0.01))
    neighbour = rectangle_sdf(g, (0.0625 + 0.045, 0.0625), (0.018, 0.02))
    gripper = GripperParams()
    tilted = np.array([-math.sin(math.radians(40)), math.cos(math.radians(40))])  # 40 deg > arctan 0.5 off the normal
    cases = {'across': ((c - [0.022, 0.0], c + [0.066, 0.0]), neighbour, 'collision'),
             'inside': ((c - [0.04, 0.0], c + [0.005, 0.0]), None, 'collision'),
             'beside': ((c + [-0.04, -0.035], c + [0.02, -0.035]), neighbour, 'missed'),
             'tilted': ((c - 0.04 * tilted, c + 0.04 * tilted), None, 'slipped'),
             'good': ((c - [0.0, 0.03], c + [0.0, 0.03]), neighbour, 'closed')}
    for name, ((j1, j2), obstacles, cause) in cases.items():
        out = execute_grasp_outcome(target, g, j1, j2, gripper, 100, np.random.default_rng(5), obstacles=obstacles)
        assert out.closed + out.collision + out.missed + out.slipped == out.trials == 100, (name, out)
        assert getattr(out, cause) >= 90, (name, out)
        assert out.closed == execute_grasp_trials(target, g, j1, j2, gripper, 100, np.random.default_rng(5),
                                                  obstacles=obstacles)
    wide = execute_grasp_outcome(target, g, c - [0.05, 0.0], c + [0.05, 0.0], gripper, 7, np.random.default_rng(0))
    assert (wide.too_wide, wide.closed, wide.trials) == (7, 0, 7) and 'too wide' in wide.describe()
    assert execute_grasp_outcome(target, g, *cases['good'][0], gripper, 0, np.random.default_rng(0)).trials == 0
