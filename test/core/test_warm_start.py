"""Replanning from a previous plan's optima (``core/planners/warm_start.py``)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.planners import PlannerParams, WarmStart, plan
from gpis_grasp_ros.core.planners import warm_start as warm_module
from support.synthetic_shapes import transparent_part_posterior

POST, _ = transparent_part_posterior()
PARAMS = PlannerParams()


def _evaluations(result) -> int:
    return sum(r.evaluations for r in result.restarts)


@pytest.mark.parametrize('seed', [0, 3])
def test_warm_plan_on_the_same_posterior_keeps_the_optimum_with_fewer_evaluations(seed: int) -> None:
    """Restarted at its own optima, the plan keeps the best one (the same objective and grasp, or a better
    one a fresh start found) and spends fewer eq. 6 evaluations: each warm run is already converged."""
    cold = plan('gp-gpis-opt', POST, PARAMS, seed=seed)
    ws = WarmStart.from_result(cold, POST.geometry)
    assert ws is not None and ws.size == sum(r.converged for r in cold.restarts) >= 15
    warm = plan('gp-gpis-opt', POST, PARAMS, seed=seed, warm_start=ws)
    n_warm = sum(r.warm for r in warm.restarts)
    assert n_warm == PARAMS.n_initial_grasps - math.ceil(warm_module.FRESH_SHARE * PARAMS.n_initial_grasps) == 15
    np.testing.assert_array_equal([r.penalty for r in warm.restarts[:n_warm]] >= ws.penalty[:n_warm], True)
    assert [r.warm for r in warm.restarts] == [True] * n_warm + [False] * (len(warm.restarts) - n_warm)
    assert warm.objective >= cold.objective - 1e-9
    res = POST.geometry.resolution
    for r in warm.restarts[:n_warm]:  # started at a (converged, not exact) optimum: it stays within a cell
        assert r.converged and r.objective_history[-1] >= r.objective_history[0] - 1e-12
        assert np.linalg.norm(r.jaw1 - r.initial_jaw1) < res and np.linalg.norm(r.jaw2 - r.initial_jaw2) < res
    assert _evaluations(warm) < 0.8 * _evaluations(cold)
    # the best optimum comes first, and it is the chosen grasp of the cold plan
    np.testing.assert_allclose(warm.restarts[0].initial_jaw1, cold.jaw1, atol=1e-9)


def test_optima_that_are_no_longer_valid_are_dropped() -> None:
    """An object that moved away from the optima leaves none valid: the plan is the cold plan."""
    cold = plan('gp-gpis-opt', POST, PARAMS, seed=1)
    ws = WarmStart.from_result(cold, POST.geometry)
    far = WarmStart(ws.jaw1 + np.array([5.0, 0.0, 0.0]), ws.jaw2 + np.array([5.0, 0.0, 0.0]))  # 5 m off
    warm = plan('gp-gpis-opt', POST, PARAMS, seed=1, warm_start=far)
    assert not any(r.warm for r in warm.restarts)
    np.testing.assert_array_equal(warm.jaw1, cold.jaw1)
    np.testing.assert_array_equal(warm.jaw2, cold.jaw2)
    assert warm.p_f == cold.p_f


def _rotation_z(theta: float) -> tuple[float, ...]:
    c, s = math.cos(theta), math.sin(theta)
    return (c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)


def test_optima_are_kept_in_the_sensor_frame() -> None:
    """A grid rotated and moved between two bursts maps the optima to the same points in the world."""
    rng = np.random.default_rng(5)
    g1 = GridGeometry(origin_x=-0.05, origin_y=-0.04, resolution=0.004, width=25, height=25, z=0.6)
    g2 = dataclasses.replace(g1, origin_x=0.01, origin_y=-0.02, z=0.6, rotation=_rotation_z(0.7))
    j1, j2 = rng.uniform(-0.05, 0.05, (20, 2)), rng.uniform(-0.05, 0.05, (20, 2))
    ws = WarmStart(g1.to_sensor(j1), g1.to_sensor(j2))
    k1, k2 = ws.on(g2)
    np.testing.assert_allclose(g2.to_sensor(k1), g1.to_sensor(j1), atol=1e-12)
    np.testing.assert_allclose(g2.to_sensor(k2), g1.to_sensor(j2), atol=1e-12)
    # the rotation about the table normal turns the grid-frame coordinates by -0.7 rad
    c, s = math.cos(0.7), math.sin(0.7)
    np.testing.assert_allclose(k1, j1 @ np.array([[c, -s], [s, c]]), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(k1 - k2, axis=1), np.linalg.norm(j1 - j2, axis=1), atol=1e-12)


def test_from_result_orders_feasible_optima_by_objective() -> None:
    cold = plan('gp-gpis-opt', POST, PARAMS, seed=2)
    ws = WarmStart.from_result(cold, POST.geometry)
    order = sorted((r for r in cold.restarts if r.converged), key=lambda r: (not r.feasible, -r.objective))
    np.testing.assert_allclose(ws.on(POST.geometry)[0], np.array([r.jaw1 for r in order]), atol=1e-12)
    np.testing.assert_array_equal(ws.penalty, [r.penalty for r in order])
    # a run stopped by the iteration cap is no optimum to resume
    capped = dataclasses.replace(cold, restarts=[dataclasses.replace(r, converged=False) for r in cold.restarts])
    assert WarmStart.from_result(capped, POST.geometry) is None
    assert WarmStart.from_result(plan('gp-m', POST, PARAMS, seed=2), POST.geometry) is None


def test_sampling_planners_refuse_a_warm_start() -> None:
    ws = WarmStart(np.zeros((1, 3)), np.ones((1, 3)))
    for method in ('gp-m', 'gp-p', 'gp-u-single'):
        with pytest.raises(ValueError, match='no warm start'):
            plan(method, POST, PARAMS, seed=0, warm_start=ws)


@pytest.mark.parametrize('bad', [np.zeros((3, 2)), np.full((2, 3), np.nan), np.zeros(3)])
def test_malformed_warm_start_is_rejected(bad: np.ndarray) -> None:
    with pytest.raises(ValueError, match='warm start'):
        WarmStart(bad, bad)
    with pytest.raises(ValueError, match='differ in shape'):
        WarmStart(np.zeros((2, 3)), np.zeros((3, 3)))
    for mu in ([1.0], [1.0, -1.0], [1.0, np.inf]):
        with pytest.raises(ValueError, match='penalty'):
            WarmStart(np.zeros((2, 3)), np.ones((2, 3)), np.array(mu))


def test_scp_resumes_with_the_given_penalty() -> None:
    """scp_minimize's penalty0: a violated constraint at the resumed penalty is not raised from the default."""
    from gpis_grasp_ros.core.scp import ScpSettings, scp_minimize

    def fun(x):  # minimise x0 + x1 subject to 1 - x0 <= 0 and 1 - x1 <= 0: the optimum (1, 1)
        return x.sum(axis=1), np.stack([1.0 - x[:, 0], 1.0 - x[:, 1]], axis=1)

    st = ScpSettings(penalty_init=10.0, penalty_max=1e3)
    x0 = np.array([[3.0, 2.0], [3.0, 2.0]])
    res = scp_minimize(fun, x0, st, penalty0=np.array([10.0, 100.0]))
    np.testing.assert_allclose(res.x, 1.0, atol=1e-4)
    assert res.penalty[0] >= 10.0 and res.penalty[1] >= 100.0
    for bad in (np.array([0.0, 1.0]), np.array([1.0, 1e4]), np.array([np.nan, 1.0])):
        with pytest.raises(ValueError, match='penalty0'):
            scp_minimize(fun, x0, st, penalty0=bad)
