"""Exact primal active-set solver for the small trust-region QPs of :mod:`scp` (compiled with numba).

Each SCP restart's subproblem (paper section VI-C; Schulman et al. 2013, the convexified
problem with slacks) is, in z = (d (n), t (m))::

    minimise   gradᵀd + ½ dᵀ(H + ρ_d I)d + μ Σ t_i + ½ ρ_t ‖t‖²
    subject to J d − t <= −g,   t >= 0,   lo <= d <= hi

— a strictly convex QP with at most a dozen variables. It is solved exactly by the primal
active-set method of Nocedal & Wright (Numerical Optimization, 2nd ed., Algorithm 16.3) from the
feasible point ``d = 0, t = max(g, 0)`` (the trust box always contains d = 0): each iteration
solves the equality-constrained QP on the working set (its KKT system by Gaussian elimination with
partial pivoting), steps to the first blocking constraint, or — at the minimiser of the working
set (a zero step, or right after a full unblocked step) — drops the constraint with the most
negative multiplier or stops when none is negative. A blocking constraint is only added when
the step moves toward it, so the working set stays linearly independent and the KKT matrix
nonsingular; termination is finite barring cycling, which the iteration cap turns into a
reported failure (never a silent step).

Status codes: :data:`SOLVED`, :data:`MAX_ITER` (cap reached), :data:`SINGULAR` (a KKT pivot
vanished), :data:`NON_FINITE` (non-finite data or solution); :data:`STATUS_TEXT` maps them to
the strings :mod:`scp` reports. All restarts are solved in one call (no Python per restart).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

SOLVED = 0
MAX_ITER = 1
SINGULAR = 2
NON_FINITE = 3
INACTIVE = 4
STATUS_TEXT = {SOLVED: 'solved', MAX_ITER: 'maximum iterations reached', SINGULAR: 'singular KKT system',
               NON_FINITE: 'non-finite solution', INACTIVE: ''}


@njit(cache=True, nogil=True)
def _lu_solve(a, b):
    """Solve a x = b in place (Gaussian elimination, partial pivoting); False if a pivot vanishes."""
    n = b.shape[0]
    scale = 0.0
    for i in range(n):
        for j in range(n):
            scale = max(scale, abs(a[i, j]))
    tiny = 1e-14 * max(scale, 1e-300)
    for k in range(n):
        p = k
        best = abs(a[k, k])
        for i in range(k + 1, n):
            if abs(a[i, k]) > best:
                best = abs(a[i, k])
                p = i
        if best <= tiny:
            return False
        if p != k:
            for j in range(n):
                tmp = a[k, j]
                a[k, j] = a[p, j]
                a[p, j] = tmp
            tmp = b[k]
            b[k] = b[p]
            b[p] = tmp
        for i in range(k + 1, n):
            f = a[i, k] / a[k, k]
            if f != 0.0:
                for j in range(k, n):
                    a[i, j] -= f * a[k, j]
                b[i] -= f * b[k]
    for k in range(n - 1, -1, -1):
        s = b[k]
        for j in range(k + 1, n):
            s -= a[k, j] * b[j]
        b[k] = s / a[k, k]
    return True


@njit(cache=True, nogil=True)
def active_set_qp(hess, lin, cons, rhs, z, max_iter):
    """Minimise ½ zᵀ hess z + linᵀz subject to cons z <= rhs from the feasible point ``z`` (updated).

    ``hess`` must be positive definite. Returns ``(status, multipliers (nc,))``; multipliers are
    those of the final working set (zero elsewhere), >= 0 at a solution.
    """
    nz = z.shape[0]
    nc = rhs.shape[0]
    work = np.zeros(nc, dtype=np.bool_)
    lam = np.zeros(nc)
    members = np.empty(nc, dtype=np.int64)
    at_minimum = False  # z minimises the QP on the current working set (after a full, unblocked step)
    for _it in range(max_iter):
        k = 0
        for i in range(nc):
            if work[i]:
                members[k] = i
                k += 1
        size = nz + k
        kkt = np.zeros((size, size))
        vec = np.zeros(size)
        for i in range(nz):
            s = lin[i]
            for j in range(nz):
                kkt[i, j] = hess[i, j]
                s += hess[i, j] * z[j]
            vec[i] = -s
        for a in range(k):
            row = members[a]
            for j in range(nz):
                kkt[nz + a, j] = cons[row, j]
                kkt[j, nz + a] = cons[row, j]
        if not _lu_solve(kkt, vec):
            return SINGULAR, lam
        zmax = 1.0
        pmax = 0.0
        for j in range(nz):
            zmax = max(zmax, abs(z[j]))
            pmax = max(pmax, abs(vec[j]))
        if not math.isfinite(pmax):
            return NON_FINITE, lam
        if at_minimum or pmax <= 1e-12 * zmax:
            worst = -1
            worst_val = 0.0
            for a in range(k):
                val = vec[nz + a]
                if val < worst_val:
                    worst_val = val
                    worst = a
            # multipliers are relative to the gradient scale
            gscale = 1e-300
            for i in range(nz):
                s = lin[i]
                for j in range(nz):
                    s += hess[i, j] * z[j]
                gscale = max(gscale, abs(s))
            if worst < 0 or worst_val >= -1e-10 * gscale:
                lam[:] = 0.0
                for a in range(k):
                    lam[members[a]] = max(vec[nz + a], 0.0)
                return SOLVED, lam
            work[members[worst]] = False
            at_minimum = False
            continue
        alpha = 1.0
        block = -1
        for i in range(nc):
            if work[i]:
                continue
            cp = 0.0
            cz = 0.0
            cn = 0.0
            for j in range(nz):
                cp += cons[i, j] * vec[j]
                cz += cons[i, j] * z[j]
                cn = max(cn, abs(cons[i, j]))
            if cp > 1e-14 * cn * pmax:
                r = max((rhs[i] - cz) / cp, 0.0)
                if r < alpha:
                    alpha = r
                    block = i
        for j in range(nz):
            z[j] += alpha * vec[j]
        if block >= 0:
            work[block] = True
        else:
            at_minimum = True
    return MAX_ITER, lam


@njit(cache=True, nogil=True)
def trust_region_steps(active, grad, hess, jac, g, mu, lo, hi, rho_d, rho_t, max_iter, d_out, lam_out, status_out):
    """Solve the SCP subproblem (module docstring) of every active restart: steps ``d_out`` (R, n),
    multipliers of the linearised constraints ``lam_out`` (R, m), status codes ``status_out`` (R,)."""
    r, n = grad.shape
    m = g.shape[1]
    nz = n + m
    nc = 2 * m + 2 * n
    for i in range(r):
        d_out[i, :] = 0.0
        lam_out[i, :] = 0.0
        if not active[i]:
            status_out[i] = INACTIVE
            continue
        ok = math.isfinite(mu[i]) and math.isfinite(rho_d[i]) and math.isfinite(rho_t[i])
        h = np.zeros((nz, nz))
        c = np.zeros((nc, nz))
        b = np.zeros(nc)
        q = np.zeros(nz)
        z = np.zeros(nz)
        for j in range(n):
            q[j] = grad[i, j]
            for k in range(n):
                h[j, k] = hess[i, j, k]
            h[j, j] += rho_d[i]
            c[2 * m + j, j] = 1.0  # d_j <= hi_j
            b[2 * m + j] = hi[i, j]
            c[2 * m + n + j, j] = -1.0  # -d_j <= -lo_j
            b[2 * m + n + j] = -lo[i, j]
            ok = ok and math.isfinite(grad[i, j]) and math.isfinite(lo[i, j]) and math.isfinite(hi[i, j])
        for a in range(m):
            q[n + a] = mu[i]
            h[n + a, n + a] = rho_t[i]
            for j in range(n):
                c[a, j] = jac[i, a, j]  # J d - t <= -g
                ok = ok and math.isfinite(jac[i, a, j])
            c[a, n + a] = -1.0
            b[a] = -g[i, a]
            c[m + a, n + a] = -1.0  # -t <= 0
            z[n + a] = max(g[i, a], 0.0)
            ok = ok and math.isfinite(g[i, a])
        if not ok:
            status_out[i] = NON_FINITE
            continue
        st, lam = active_set_qp(h, q, c, b, z, max_iter)
        status_out[i] = st
        if st == SOLVED:
            for j in range(n):
                d_out[i, j] = z[j]
            for a in range(m):
                lam_out[i, a] = lam[a]
