"""Sequential convex programming (ℓ1 penalties, trust region, exact active-set or OSQP subproblems) on toy problems."""

from __future__ import annotations

import numpy as np
import pytest

import gpis_grasp_ros.core.scp as scp_module
from gpis_grasp_ros.core.scp import (
    REASON_CONVERGED_STEP,
    REASON_ITERATION_LIMIT,
    REASON_PENALTY_LIMIT,
    REASON_QP_FAILED,
    ScpSettings,
    scp_minimize,
)


def quadratic(x: np.ndarray):
    """min (x−2)² + (y−1)²  s.t.  x + y <= 2  →  (1.5, 0.5)."""
    return (x[:, 0] - 2) ** 2 + (x[:, 1] - 1) ** 2, (x[:, 0] + x[:, 1] - 2)[:, None]


def rosenbrock(x: np.ndarray):
    """Rosenbrock with the linear constraint x + y <= 1.5 (active at the optimum)."""
    return (1 - x[:, 0]) ** 2 + 100 * (x[:, 1] - x[:, 0] ** 2) ** 2, (x[:, 0] + x[:, 1] - 1.5)[:, None]


def circle(x: np.ndarray):
    """min x + y  s.t.  x² + y² <= 1  →  (−1/√2, −1/√2)."""
    return x[:, 0] + x[:, 1], (x[:, 0] ** 2 + x[:, 1] ** 2 - 1)[:, None]


STARTS = np.array([[0.0, 0.0], [5.0, 5.0], [-3.0, 2.0], [2.0, -4.0]])


def test_constrained_quadratic() -> None:
    res = scp_minimize(quadratic, STARTS, ScpSettings(fd_step=1e-6))
    np.testing.assert_allclose(res.x, np.tile([1.5, 0.5], (4, 1)), atol=2e-4)
    assert res.converged.all() and res.feasible.all()
    assert all(r.startswith('converged') for r in res.reason)
    assert np.all(res.iterations >= 1) and np.all(res.evaluations > res.iterations)
    assert res.qp_solves == res.iterations.max()


def test_nonlinear_constraint_from_infeasible_start() -> None:
    starts = np.array([[2.0, 2.0], [0.0, 0.0], [-1.0, 0.5], [0.3, -1.5]])
    res = scp_minimize(circle, starts, ScpSettings(fd_step=1e-7))
    np.testing.assert_allclose(res.x, np.tile([-np.sqrt(0.5)] * 2, (4, 1)), atol=3e-3)
    assert res.feasible.all()
    assert res.merit == pytest.approx(res.fun + res.penalty * np.maximum(res.constraints, 0).sum(axis=1))


def test_bounds_are_hard_and_limits_reported() -> None:
    # unconstrained linear objective pushes against the box
    def lin(x: np.ndarray):
        return -x[:, 0] - 2 * x[:, 1], np.zeros((x.shape[0], 0))

    res = scp_minimize(lin, np.zeros((2, 2)), ScpSettings(trust_radius_max=0.5), lower=[-1, -1], upper=[1, 0.25])
    np.testing.assert_allclose(res.x, np.tile([1.0, 0.25], (2, 1)), atol=1e-6)
    # iteration limit
    short = scp_minimize(rosenbrock, np.array([[-1.2, 1.0]]), ScpSettings(max_iterations=2))
    assert short.reason == [REASON_ITERATION_LIMIT] and not short.converged[0]
    # infeasible problem: g = 1 everywhere → penalty limit
    def infeasible(x: np.ndarray):
        return x[:, 0] ** 2, np.ones((x.shape[0], 1))

    bad = scp_minimize(infeasible, np.array([[1.0]]), ScpSettings(penalty_max=1e3))
    assert bad.reason == [REASON_PENALTY_LIMIT] and not bad.feasible[0] and not bad.converged[0]


def test_batched_restarts_match_single_runs_and_central_differences() -> None:
    st = ScpSettings(fd_step=1e-5, central_differences=True)
    batch = scp_minimize(quadratic, STARTS, st)
    for i, x0 in enumerate(STARTS):
        single = scp_minimize(quadratic, x0[None], st)
        np.testing.assert_allclose(batch.x[i], single.x[0], atol=1e-4)


def test_function_called_in_batches() -> None:
    calls = []

    def counted(x: np.ndarray):
        calls.append(x.shape[0])
        return quadratic(x)

    scp_minimize(counted, STARTS, ScpSettings(fd_step=1e-6))
    assert calls[0] == 4 and calls[1] == 8  # all starts at once, then all their FD points at once


@pytest.mark.parametrize('solver', [dict(qp_solver='osqp', osqp_max_iter=1),
                                    dict(qp_solver='active-set', qp_max_iter=1)])
def test_failed_qp_is_never_converged(solver) -> None:
    """A QP solver stopping at its iteration limit is a failed subproblem, not a zero (stationary) step."""
    res = scp_minimize(rosenbrock, STARTS, ScpSettings(fd_step=1e-6, max_qp_failures=3, **solver))
    assert not res.converged.any()
    assert all(r.startswith(REASON_QP_FAILED) and 'maximum iterations' in r for r in res.reason)
    assert np.all(res.qp_failures == 3) and all(st == 'maximum iterations reached' for st in res.qp_status)
    np.testing.assert_array_equal(res.x, STARTS)  # no step was taken
    ok = scp_minimize(quadratic, STARTS, ScpSettings(fd_step=1e-6, qp_solver=solver['qp_solver']))
    assert np.all(ok.qp_failures == 0) and ok.qp_status == [''] * len(STARTS)


def test_a_failed_qp_concerns_only_its_restart() -> None:
    """Restarts have separate subproblems: one whose data is not finite fails alone."""

    def nan_near_origin(x: np.ndarray):
        f, g = quadratic(x)
        bad = np.linalg.norm(x - STARTS[0], axis=1) < 0.5  # around the first start only
        return f, np.where(bad[:, None], np.nan, g)

    res = scp_minimize(nan_near_origin, STARTS, ScpSettings(fd_step=1e-6))
    assert res.qp_failures[0] > 0 and not res.converged[0] and 'non-finite' in res.qp_status[0]
    assert np.all(res.qp_failures[1:] == 0) and res.converged[1:].all()


@pytest.mark.parametrize('problem', [quadratic, circle])
def test_active_set_and_osqp_subproblems_give_the_same_runs(problem) -> None:
    exact = scp_minimize(problem, STARTS, ScpSettings(fd_step=1e-6))
    admm = scp_minimize(problem, STARTS, ScpSettings(fd_step=1e-6, qp_solver='osqp', osqp_eps=1e-9))
    np.testing.assert_allclose(exact.x, admm.x, atol=1e-4)
    assert exact.converged.all() and admm.converged.all()


def test_non_finite_qp_solution_is_a_failure(monkeypatch) -> None:
    """A 'solved' status with a NaN solution must not become a zero step that looks converged."""
    real_solve = scp_module.osqp.OSQP.solve

    def nan_solve(self, *args, **kwargs):
        res = real_solve(self, *args, **kwargs)
        res.x[:] = np.nan
        return res

    monkeypatch.setattr(scp_module.osqp.OSQP, 'solve', nan_solve)
    res = scp_minimize(quadratic, STARTS, ScpSettings(fd_step=1e-6, qp_solver='osqp'))
    assert not res.converged.any() and np.all(res.qp_failures > 0)
    assert all('non-finite solution' in r for r in res.reason)
    np.testing.assert_array_equal(res.x, STARTS)  # no step was taken


def test_objective_history_and_convergence_from_feasible_starts() -> None:
    """From feasible starts the objective never gets worse along the run (merit = objective there),
    and every converged restart improved on its start."""
    starts = np.array([[0.0, 0.0], [-3.0, 2.0], [2.0, -4.0], [0.5, 0.5]])  # all satisfy x + y <= 2
    res = scp_minimize(quadratic, starts, ScpSettings(fd_step=1e-6, step_tol=1e-6, objective_tol=1e-10))
    assert res.converged.all()
    f0, _ = quadratic(starts)
    for i, h in enumerate(res.objective_history):
        assert h.shape == (res.iterations[i] + 1,) and h[0] == pytest.approx(f0[i])
        assert np.all(np.diff(h) <= 1e-12)  # minimisation: non-increasing
        assert h[-1] < h[0] and h[-1] == pytest.approx(res.fun[i])
        np.testing.assert_allclose(res.merit_history[i], h, atol=1e-9)  # feasible throughout here
    # a loose step/objective tolerance stops earlier, with that reason, still improving
    loose = scp_minimize(rosenbrock, np.array([[-1.2, 1.0]]), ScpSettings(fd_step=1e-7,
                                                                          step_tol=0.05, objective_tol=1e-3,
                                                                          max_iterations=300))
    assert loose.converged[0] and loose.reason[0] == REASON_CONVERGED_STEP
    assert loose.objective_history[0][-1] < loose.objective_history[0][0]
