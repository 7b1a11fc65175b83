"""The exact active-set solver of the SCP subproblems (core/small_qp.py).

Property test over random subproblems of the SCP's form (trust box, ℓ1 slacks, proximal terms,
with and without a quasi-Newton Hessian): the solution satisfies the KKT conditions to round-off
and agrees with OSQP run to high accuracy; failures are reported by status, never as a step.
"""

from __future__ import annotations

import numpy as np
import osqp
import pytest
import scipy.sparse as sp

from gpis_grasp_ros.core.small_qp import (
    INACTIVE,
    MAX_ITER,
    NON_FINITE,
    SOLVED,
    active_set_qp,
    trust_region_steps,
)


def _random_problem(rng: np.random.Generator, n: int, m: int, curvature: bool):
    grad = rng.normal(0, 1, n) * 10 ** rng.uniform(-3, 1)
    jac = rng.normal(0, 1, (m, n)) * 10 ** rng.uniform(-2, 1, (m, 1))
    jac[rng.random(m) < 0.15] = 0.0  # constraints with no gradient (invalid contacts)
    g = rng.normal(0, 1, m) * 10 ** rng.uniform(-3, 0.5, m)
    mu = 10.0 ** rng.integers(1, 4)
    s = 10 ** rng.uniform(-1.5, 0.5)
    lo = -np.full(n, s)
    hi = np.full(n, s)
    at_bound = rng.random(n) < 0.2  # x at a hard bound: one side of the box is 0
    lo[at_bound] = 0.0
    hess = np.zeros((n, n))
    if curvature:
        a = rng.normal(0, 1, (n, n))
        hess = a @ a.T * 10 ** rng.uniform(-2, 1)
    rho_d = 0.1 * (np.abs(grad).max() + 0.01 * mu * np.abs(jac).sum(axis=1).max()) / s
    rho_t = 0.1 * mu / max(np.abs(g).max(), s * np.abs(jac).sum(axis=1).max(), 1e-12)
    return grad, hess, jac, g, mu, lo, hi, max(rho_d, 1e-8), max(rho_t, 1e-8)


def _full_qp(grad, hess, jac, g, mu, lo, hi, rho_d, rho_t):
    n, m = grad.size, g.size
    p = np.zeros((n + m, n + m))
    p[:n, :n] = hess + rho_d * np.eye(n)
    p[n:, n:] = rho_t * np.eye(m)
    q = np.concatenate([grad, np.full(m, mu)])
    c = np.zeros((2 * m + 2 * n, n + m))
    c[:m, :n] = jac
    c[:m, n:] = -np.eye(m)
    c[m:2 * m, n:] = -np.eye(m)
    c[2 * m:2 * m + n, :n] = np.eye(n)
    c[2 * m + n:, :n] = -np.eye(n)
    b = np.concatenate([-g, np.zeros(m), hi, -lo])
    return p, q, c, b


@pytest.mark.parametrize('curvature', [False, True])
def test_solutions_satisfy_kkt_and_match_osqp(curvature: bool) -> None:
    rng = np.random.default_rng(3 + curvature)
    worst_kkt = worst_osqp = 0.0
    unsolved = 0
    for _ in range(300):
        n, m = 4, int(rng.choice([3, 6]))
        data = _random_problem(rng, n, m, curvature)
        p, q, c, b = _full_qp(*data)
        z = np.concatenate([np.zeros(n), np.maximum(data[3], 0.0)])
        status, lam = active_set_qp(p, q, c, b, z, 200)
        assert status == SOLVED
        scale = max(1.0, np.abs(q).max(), np.abs(p).max())
        # KKT: feasibility, λ >= 0, complementarity, stationarity
        slack = b - c @ z
        assert slack.min() >= -1e-9 * max(1.0, np.abs(b).max())
        assert lam.min() >= 0.0
        assert np.abs(lam * slack).max() <= 1e-9 * scale * max(1.0, np.abs(b).max())
        stat = np.abs(p @ z + q + c.T @ lam).max() / scale
        worst_kkt = max(worst_kkt, stat)
        # OSQP, high accuracy, on the same problem
        solver = osqp.OSQP()
        solver.setup(sp.csc_matrix(np.triu(p)), q, sp.csc_matrix(c), np.full(b.size, -np.inf), b, verbose=False,
                     eps_abs=1e-10, eps_rel=1e-10, max_iter=100000, polishing=True)
        ref = solver.solve(raise_error=False)
        if ref.info.status != 'solved':
            unsolved += 1  # ADMM may not reach 1e-10 on the worst-conditioned cases
            continue
        worst_osqp = max(worst_osqp, np.abs(ref.x[:n] - z[:n]).max() / max(1.0, np.abs(z[:n]).max()))
    assert worst_kkt < 1e-9
    assert worst_osqp < 1e-6 and unsolved < 30


def test_batched_steps_and_statuses() -> None:
    rng = np.random.default_rng(11)
    r, n, m = 6, 4, 6
    probs = [_random_problem(rng, n, m, False) for _ in range(r)]
    grad, hess, jac, g, mu, lo, hi, rho_d, rho_t = (np.array([pr[k] for pr in probs], dtype=float) for k in range(9))
    active = np.array([True, True, False, True, True, True])
    g[4, 0] = np.nan  # non-finite data: reported, no step
    d = np.empty((r, n))
    lam = np.empty((r, m))
    codes = np.empty(r, dtype=np.int64)
    trust_region_steps(active, grad, hess, jac, g, mu, lo, hi, rho_d, rho_t, 200, d, lam, codes)
    assert list(codes) == [SOLVED, SOLVED, INACTIVE, SOLVED, NON_FINITE, SOLVED]
    assert np.all(d[2] == 0) and np.all(d[4] == 0)
    for i in (0, 1, 3, 5):  # each equals the single-problem solution
        p, q, c, b = _full_qp(*probs[i])
        z = np.concatenate([np.zeros(n), np.maximum(probs[i][3], 0.0)])
        assert active_set_qp(p, q, c, b, z, 200)[0] == SOLVED
        np.testing.assert_allclose(d[i], z[:n], atol=1e-12)
        assert np.all(d[i] <= hi[i] + 1e-12) and np.all(d[i] >= lo[i] - 1e-12)
    trust_region_steps(active, grad, hess, jac, g, mu, lo, hi, rho_d, rho_t, 1, d, lam, codes)
    assert MAX_ITER in set(codes.tolist())  # too few working-set changes: a reported failure
    assert np.all(d[codes == MAX_ITER] == 0)
