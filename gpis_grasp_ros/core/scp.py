"""Sequential convex programming with ℓ1 penalties and a trust region (paper section VI-C, ref. [34]).

Solves, for several independent starting points at once::

    minimise f(x)   subject to   g_i(x) <= 0,  lower <= x <= upper

following Schulman et al., "Finding locally optimal, collision-free trajectories with sequential
convex optimization" (RSS 2013), Algorithm 1:

* **Penalty loop.** The constraints enter the merit ``φ(x) = f(x) + μ Σ_i max(g_i(x), 0)``
  (an exact ℓ1 penalty: for μ above the largest Lagrange multiplier its local minima are those
  of the constrained problem). When the inner loop has converged with a constraint violated by
  more than ``constraint_tol``, μ is multiplied by ``penalty_factor`` (up to ``penalty_max``)
  and the trust region is reset.
* **Convexify loop.** f and g are linearised at the current point with finite differences
  (user step ``fd_step``; forward by default, central optional). The convex model is the linear
  ``f + ∇fᵀd + μ Σ_i max(g_i + ∇g_iᵀd, 0)``, minimised over the trust box ``|d|_∞ <= s`` as a QP with slack variables
  ``t_i >= max(g_i + ∇g_iᵀd, 0)``. A proximal term keeps the QP strictly convex, which OSQP
  (ADMM) needs to converge quickly on what would otherwise be a degenerate LP: ``½ ρ_d ‖d‖²`` with
  ``ρ_d = prox_rel · (‖∇f‖∞ + w_μ μ max_i ‖∇g_i‖₁) / s`` (so that, in box-normalised units d/s,
  the curvature is ``prox_rel`` times the largest linear coefficient and the step still reaches
  the box when the model says so; ``w_μ = prox_penalty_weight`` < 1 keeps a large penalty from
  damping the objective's own step — with w_μ = 1 and μ = 10³ the steps along an active
  constraint shrank to a few hundredths of a cell and SCP crept for ~100 iterations) and
  ``½ ρ_t ‖t‖²`` with ``ρ_t = prox_rel · μ / max(|g|, s‖∇g‖₁)``.
* **Trust region.** The step is accepted when the ratio of actual to predicted merit
  improvement is at least ``accept_ratio``; the box then grows by ``trust_expand`` (to at most
  ``trust_radius_max``), otherwise it shrinks by ``trust_shrink``. With
  ``trust_expand_from_step`` the update is relative to the step actually taken (grow to
  ``trust_expand·‖d‖∞`` if that is larger than the box, shrink to ``trust_shrink·‖d‖∞``), which
  avoids iterations spent shrinking a box the step did not reach.
* **Convergence test** (per restart, checked only at a point whose constraints hold to
  ``constraint_tol``; otherwise the penalty is raised instead). A restart has *converged* when
  one of these holds:

  1. *model stationarity*: the predicted merit improvement of the QP step is at most
     ``improve_tol · max(1, |φ|)``;
  2. *step and objective tolerance*: an accepted step moved x by at most ``step_tol``
     (∞-norm) and improved the merit by at most ``objective_tol · max(1, |φ|)``;
  3. *trust region*: after a rejected step the box is below ``trust_radius_min`` (no step larger
     than that improves the merit enough — the step tolerance seen from the other side).

  A run that ends otherwise is *not* converged and says why: the iteration cap
  (``max_iterations``), constraints still violated at ``penalty_max``, or
  ``max_qp_failures`` consecutive failed QP subproblems.
* **QP solver.** ``qp_solver='active-set'`` (default) solves each subproblem exactly with the
  compiled primal active-set method of :mod:`small_qp` (all restarts in one call, microseconds
  each); ``'osqp'`` uses OSQP (ADMM, accurate to ``osqp_eps``, polished). Both solve the same QP;
  with polishing OSQP returns the same active-set solution, so the runs agree (tested), and the
  exact solver is ~20x cheaper per subproblem on the planners' benchmark.
* **QP status.** The solver's status is checked on every solve: only ``solved`` / ``solved inaccurate``
  with a finite step is used. A failed subproblem is never read as stationarity (a zero step would
  otherwise look converged): the box shrinks and the failure is counted per restart
  (``ScpResult.qp_failures``, ``qp_status``).
* **History.** ``objective_history[i]`` / ``merit_history[i]`` hold restart i's objective and
  merit at the start and after every iteration it took part in (the supplementary convergence
  plots of the paper).

**Batching.** All restarts advance in lock-step; each restart has its own subproblem, solved
for the active restarts only, so a failed subproblem concerns only its restart. With OSQP each
restart has its own small problem, set up once (on its first iteration); each iteration only
updates its vectors and matrix values (``OSQP.update``, warm-started from the previous solution)
and solves it (a block-diagonal problem of all restarts would run as many ADMM iterations as its
hardest block needs and fail for all restarts at once). The
objective/constraint function is called on a batch of points (all candidates, or all
finite-difference points of all restarts, at once), so it can be vectorised by the caller.

Per restart the result reports iterations (QP solves), function evaluations, a convergence
flag, feasibility, the reason the run stopped, failed QP solves and the objective history.
``monitor`` (optional) is called after every iteration and may raise to abort (cooperative
cancellation).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import osqp
import scipy.sparse as sp

from gpis_grasp_ros.core.small_qp import STATUS_TEXT, trust_region_steps

#: ``fun(X (B, n)) -> (f (B,), g (B, m))``: objective and constraint values of a batch of points.
BatchFunction = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]

REASON_CONVERGED_MODEL = 'converged: predicted improvement below tolerance'
REASON_CONVERGED_TRUST = 'converged: trust region below minimum size'
REASON_CONVERGED_STEP = 'converged: step and objective change below tolerance'
REASON_PENALTY_LIMIT = 'stopped: constraints violated at the maximum penalty'
REASON_ITERATION_LIMIT = 'stopped: iteration limit'
REASON_QP_FAILED = 'stopped: QP solver failed'

#: QP statuses whose solution is used as a step (anything else is a failed subproblem).
QP_OK_STATUSES = ('solved', 'solved inaccurate')


@dataclass(frozen=True)
class ScpSettings:
    """Settings of :func:`scp_minimize` (lengths in the units of x)."""

    fd_step: float | tuple[float, ...] = 1e-6
    central_differences: bool = False
    trust_radius_init: float = 1.0
    trust_radius_min: float = 1e-4
    trust_radius_max: float = 10.0
    trust_shrink: float = 0.3
    trust_expand: float = 2.0
    trust_expand_from_step: bool = False
    accept_ratio: float = 0.1
    penalty_init: float = 10.0
    penalty_factor: float = 10.0
    penalty_max: float = 1e4
    constraint_tol: float = 1e-4
    improve_tol: float = 1e-8
    step_tol: float = 0.0
    objective_tol: float = 0.0
    max_qp_failures: int = 3
    max_iterations: int = 200
    prox: float = 1e-8
    prox_rel: float = 0.1
    prox_penalty_weight: float = 0.01
    #: 'active-set' (exact, :mod:`small_qp`, default) or 'osqp' (ADMM, one small OSQP problem per restart)
    qp_solver: str = 'active-set'
    qp_max_iter: int = 200  # working-set changes of the active-set solver before it reports a failure
    osqp_eps: float = 1e-6
    osqp_max_iter: int = 20000
    osqp_rho: float = 0.1
    osqp_rho_interval: int = 25
    #: Objective evaluations are made in batches of at most this many points (0: one batch per call),
    #: with ``poll`` called between batches. A row-wise ``fun`` gives the same values either way.
    eval_chunk: int = 0
    #: While a QP is solved (in a worker thread, only when ``poll`` is given) ``poll`` runs every this many s.
    poll_interval: float = 0.02


@dataclass
class ScpResult:
    """Outcome of :func:`scp_minimize` for R restarts (arrays indexed by restart)."""

    x: np.ndarray
    fun: np.ndarray
    constraints: np.ndarray
    penalty: np.ndarray
    iterations: np.ndarray
    evaluations: np.ndarray
    converged: np.ndarray
    feasible: np.ndarray
    reason: list[str]
    qp_solves: int = 0
    qp_time: float = 0.0
    eval_time: float = 0.0
    history: list[np.ndarray] = field(default_factory=list)
    objective_history: list[np.ndarray] = field(default_factory=list)  # per restart: f at x after each iteration
    merit_history: list[np.ndarray] = field(default_factory=list)  # per restart: ℓ1 merit (current μ)
    qp_failures: np.ndarray | None = None  # (R,) failed QP subproblems seen by each restart
    qp_status: list[str] = field(default_factory=list)  # per restart: last failed OSQP status, '' if none

    @property
    def merit(self) -> np.ndarray:
        """ℓ1 merit f + μ Σ max(g, 0) at the returned points."""
        return self.fun + self.penalty * np.maximum(self.constraints, 0.0).sum(axis=1)


class _BlockQp:
    """R copies of the trust-region subproblem in one block-diagonal OSQP problem.

    Block variables z = [d (n), t (m)]; rows: ``J d − t <= −g`` (m), ``t >= 0`` (m),
    ``lo <= d <= hi`` (n). The sparsity pattern is fixed so every iteration is an ``update``.
    """

    def __init__(self, r: int, n: int, m: int, settings: ScpSettings) -> None:
        self.r, self.n, self.m = r, n, m
        self.prox = settings.prox
        self.prox_rel = settings.prox_rel
        self.prox_mu = settings.prox_penalty_weight
        nv, nc = n + m, 2 * m + n
        self.nv, self.nc = nv, nc
        # P: diagonal of the d block + t diagonal.
        self._pi = self._pj = np.arange(n)
        p_rows = np.concatenate([self._pi, np.arange(n, nv)])
        p_cols = np.concatenate([self._pj, np.arange(n, nv)])
        offs_v = (np.arange(r) * nv)[:, None]
        p_data = np.tile(np.concatenate([np.where(self._pi == self._pj, self.prox, 0.0), np.full(m, self.prox)]), r)
        self.P = sp.csc_matrix((p_data, ((p_rows[None] + offs_v).ravel(), (p_cols[None] + offs_v).ravel())),
                               shape=(r * nv, r * nv))
        self.P.sort_indices()
        # A in CSC order per block: column j of d holds rows 0..m-1 (J[:, j]) and 2m + j (1);
        # column i of t holds rows i (-1) and m + i (1).
        col_ptr = [0]
        rows: list[int] = []
        for j in range(n):
            rows.extend(range(m))
            rows.append(2 * m + j)
            col_ptr.append(len(rows))
        for i in range(m):
            rows.extend([i, m + i])
            col_ptr.append(len(rows))
        nnz = len(rows)
        indices = (np.asarray(rows)[None] + (np.arange(r) * nc)[:, None]).ravel()
        indptr = np.concatenate([[0], (np.asarray(col_ptr[1:])[None] + (np.arange(r) * nnz)[:, None]).ravel()])
        self._t_data = np.tile([-1.0, 1.0], m)
        data = self._a_data(np.zeros((r, m, n)))
        self.A = sp.csc_matrix((data, indices, indptr), shape=(r * nc, r * nv))
        self.solver = osqp.OSQP()
        q, lo, hi = self._vectors(np.zeros((r, n)), np.ones(r), -np.ones((r, m)), np.zeros((r, n)), np.zeros((r, n)))
        # rho adapted every `osqp_rho_interval` ADMM iterations (OSQP's default adapts on a wall-clock
        # budget, which would make the iterates — and so the planned grasp — depend on machine load).
        self.solver.setup(self.P, q, self.A, lo, hi, verbose=False, polishing=True, eps_abs=settings.osqp_eps,
                          eps_rel=settings.osqp_eps, max_iter=settings.osqp_max_iter,
                          adaptive_rho_interval=settings.osqp_rho_interval, rho=settings.osqp_rho)

    def _a_data(self, jac: np.ndarray) -> np.ndarray:
        r, m, n = jac.shape
        d_cols = np.concatenate([np.transpose(jac, (0, 2, 1)), np.ones((r, n, 1))], axis=2).reshape(r, -1)
        return np.concatenate([d_cols, np.broadcast_to(self._t_data, (r, 2 * m))], axis=1).ravel()

    def _vectors(self, grad, mu, g, lo, hi):
        r, m = g.shape
        q = np.concatenate([grad, np.repeat(mu[:, None], m, axis=1)], axis=1).ravel()
        low = np.concatenate([np.full((r, m), -np.inf), np.zeros((r, m)), lo], axis=1).ravel()
        up = np.concatenate([-g, np.full((r, m), np.inf), hi], axis=1).ravel()
        return q, low, up

    def solve(self, grad, jac, g, mu, lo, hi, radius) -> tuple[np.ndarray, np.ndarray, str]:
        """Steps d (R, n), multipliers (R, m) of the linearised constraints of all blocks, OSQP status.

        Inactive blocks: pass zeros and lo = hi = 0. The status is OSQP's (``'solved'``, ...),
        or ``'non-finite solution'`` when the returned step is not finite (the step is then zero
        and must not be used: see :data:`QP_OK_STATUSES`).
        """
        q, low, up = self._vectors(grad, mu, g, lo, hi)
        rho_d, rho_t = _prox_weights(grad, jac, g, mu, radius, self.prox, self.prox_rel, self.prox_mu)
        diag = (self._pi == self._pj)[None, :]
        hp = np.where(diag, rho_d[:, None], 0.0)
        px = np.concatenate([hp, np.repeat(rho_t[:, None], self.m, axis=1)], axis=1).ravel()
        self.solver.update(q=q, l=low, u=up, Ax=self._a_data(jac), Px=px)
        res = self.solver.solve(raise_error=False)
        status = str(res.info.status)
        z = np.asarray(res.x if res.x is not None else np.full(self.r * self.nv, np.nan),
                       dtype=np.float64).reshape(self.r, self.nv)
        d = z[:, :self.n]
        y = res.y if res.y is not None else np.full(self.r * self.nc, np.nan)
        lam = np.asarray(y, dtype=np.float64).reshape(self.r, self.nc)[:, :self.m]
        if not np.all(np.isfinite(d)):
            d = np.zeros_like(d)
            if status in QP_OK_STATUSES:
                status = 'non-finite solution'
        lam = np.where(np.isfinite(lam), np.clip(lam, 0.0, mu[:, None]), 0.0)
        return np.clip(d, lo, hi), lam, status


def _prox_weights(grad, jac, g, mu, radius, prox: float, prox_rel: float, prox_mu: float):
    """Proximal weights ρ_d, ρ_t (R,) of the subproblems (see the module docstring)."""
    jn = np.abs(jac).sum(axis=2)  # (R, m) ‖∇g_i‖₁
    rad = np.maximum(radius, 1e-12)
    lin = np.abs(grad).max(axis=1, initial=0.0) + prox_mu * mu * jn.max(axis=1, initial=0.0)
    rho_d = np.maximum(prox, prox_rel * lin / rad)
    t_scale = np.maximum(np.maximum(np.abs(g), rad[:, None] * jn).max(axis=1, initial=0.0), 1e-12)
    rho_t = np.maximum(prox, prox_rel * mu / t_scale)
    return rho_d, rho_t


class _ActiveSetQps:
    """Every active restart's subproblem solved exactly by :func:`small_qp.trust_region_steps` (one call)."""

    def __init__(self, r: int, n: int, m: int, settings: ScpSettings) -> None:
        self.r, self.n, self.m = r, n, m
        self.settings = settings
        self.curvature = np.zeros((r, n, n))  # the model is linear: no curvature besides the proximal term

    def solve(self, active, grad, jac, g, mu, lo, hi, radius) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """Steps d (R, n), multipliers (R, m), status per restart ('' for inactive restarts)."""
        st = self.settings
        rho_d, rho_t = _prox_weights(grad, jac, g, mu, radius, st.prox, st.prox_rel, st.prox_penalty_weight)
        d = np.empty((self.r, self.n))
        lam = np.empty((self.r, self.m))
        codes = np.empty(self.r, dtype=np.int64)
        f64 = np.float64
        trust_region_steps(np.ascontiguousarray(active, dtype=np.bool_), np.ascontiguousarray(grad, dtype=f64),
                           self.curvature, np.ascontiguousarray(jac, dtype=f64),
                           np.ascontiguousarray(g, dtype=f64), np.ascontiguousarray(mu, dtype=f64),
                           np.ascontiguousarray(lo, dtype=f64), np.ascontiguousarray(hi, dtype=f64),
                           np.ascontiguousarray(rho_d, dtype=f64), np.ascontiguousarray(rho_t, dtype=f64),
                           int(st.qp_max_iter), d, lam, codes)
        lam = np.clip(lam, 0.0, mu[:, None])
        return np.clip(d, lo, hi), lam, [STATUS_TEXT[int(c)] for c in codes]


class _RestartQps:
    """One small OSQP problem (a :class:`_BlockQp` with one block) per restart, set up on first use.

    Each restart's subproblem is solved on its own, so OSQP's termination test, its iteration
    count and a failure concern that restart only (a block-diagonal problem of all restarts runs
    as many ADMM iterations as its hardest block needs and fails for all of them at once).
    """

    def __init__(self, r: int, n: int, m: int, settings: ScpSettings) -> None:
        self.r, self.n, self.m = r, n, m
        self.settings = settings
        self.blocks: list[_BlockQp | None] = [None] * r

    def solve(self, active, grad, jac, g, mu, lo, hi, radius) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """Steps d (R, n), multipliers (R, m) and OSQP status per restart ('' for inactive ones, whose
        step and multipliers are zero); see :meth:`_BlockQp.solve`."""
        d = np.zeros((self.r, self.n))
        lam = np.zeros((self.r, self.m))
        status = [''] * self.r
        for i in np.flatnonzero(active):
            qp = self.blocks[i]
            if qp is None:
                qp = self.blocks[i] = _BlockQp(1, self.n, self.m, self.settings)
            sl = slice(i, i + 1)
            di, li, status[i] = qp.solve(grad[sl], jac[sl], g[sl], mu[sl], lo[sl], hi[sl], radius[sl])
            d[i], lam[i] = di[0], li[0]
        return d, lam, status


def _merit(f: np.ndarray, g: np.ndarray, mu: np.ndarray) -> np.ndarray:
    m = f + mu * np.maximum(g, 0.0).sum(axis=1)
    return np.where(np.isfinite(m), m, np.inf)


@dataclass(frozen=True)
class ScpProgress:
    """State passed to the ``monitor`` of :func:`scp_minimize` after every iteration (read-only views)."""

    iteration: int  # QP solves so far
    active: np.ndarray  # (R,) restarts still running
    x: np.ndarray  # (R, n) current points
    fun: np.ndarray  # (R,) objective values
    constraints: np.ndarray  # (R, m)


def scp_minimize(fun: BatchFunction, x0: np.ndarray, settings: ScpSettings | None = None,
                 lower: np.ndarray | None = None, upper: np.ndarray | None = None,
                 record_history: bool = False,
                 monitor: Callable[[ScpProgress], None] | None = None,
                 poll: Callable[[], None] | None = None,
                 penalty0: np.ndarray | None = None) -> ScpResult:
    """Run SCP from each row of ``x0`` (R, n); see the module docstring.

    ``fun`` maps a batch of points (B, n) to objective values (B,) and constraint values (B, m)
    (``g <= 0`` is feasible). ``lower``/``upper`` are hard box bounds on x (kept exactly).
    ``monitor`` is called after every iteration with an :class:`ScpProgress`; it may raise to
    abort the run (cooperative cancellation: the exception propagates to the caller).
    ``poll`` (finer-grained cancellation inside an iteration) is called between batches of
    ``settings.eval_chunk`` objective evaluations and every ``settings.poll_interval`` s while the
    batched QP is solved; it may raise to abort. The QP then runs in a worker thread (OSQP releases
    the GIL) whose result is discarded on abort; the iterates are the same with or without ``poll``.
    ``penalty0`` (R,) the initial penalty μ of each restart (default ``penalty_init``): a run resumed from
    where an earlier one ended starts with the penalty that run reached.
    """
    st = ScpSettings() if settings is None else settings
    x = np.array(x0, dtype=np.float64, ndmin=2)
    r, n = x.shape
    if penalty0 is None:
        mu = np.full(r, st.penalty_init)
    else:
        mu = np.array(np.broadcast_to(np.asarray(penalty0, dtype=np.float64), (r,)))
        if not (np.isfinite(mu).all() and (mu > 0).all() and (mu <= st.penalty_max * (1 + 1e-12)).all()):
            raise ValueError(f'penalty0 must be positive and at most penalty_max={st.penalty_max:g}, got {mu}')
    lower = np.broadcast_to(-np.inf if lower is None else np.asarray(lower, float), (r, n))
    upper = np.broadcast_to(np.inf if upper is None else np.asarray(upper, float), (r, n))
    x = np.clip(x, lower, upper)
    h = np.broadcast_to(np.asarray(st.fd_step, dtype=np.float64), (n,))
    evals = np.zeros(r, dtype=np.int64)
    timers = {'eval': 0.0, 'qp': 0.0}

    def call_one(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t0 = time.perf_counter()
        fv, gv = fun(points)
        timers['eval'] += time.perf_counter() - t0
        fv = np.asarray(fv, dtype=np.float64).reshape(points.shape[0])
        gv = np.asarray(gv, dtype=np.float64).reshape(points.shape[0], -1)
        return fv, gv

    def call(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        chunk = st.eval_chunk if st.eval_chunk > 0 else max(points.shape[0], 1)
        parts = []
        for start in range(0, points.shape[0], chunk):
            if poll is not None:
                poll()
            parts.append(call_one(points[start:start + chunk]))
        if len(parts) <= 1:
            return parts[0] if parts else call_one(points)
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])

    def derivatives(rows: np.ndarray, fv: np.ndarray, gv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Finite-difference gradient (k, n) and Jacobian (k, m, n) at x[rows]."""
        k = rows.size
        mg = gv.shape[1]
        eye = np.eye(n) * h
        xs = x[rows]
        if st.central_differences:
            pts = np.concatenate([xs[:, None, :] + eye[None], xs[:, None, :] - eye[None]], axis=1)
            fp, gp = call(pts.reshape(-1, n))
            fp = fp.reshape(k, 2, n)
            gp = gp.reshape(k, 2, n, mg)
            grad = (fp[:, 0] - fp[:, 1]) / (2 * h)
            jac = np.transpose(gp[:, 0] - gp[:, 1], (0, 2, 1)) / (2 * h)
            evals[rows] += 2 * n
        else:
            fp, gp = call((xs[:, None, :] + eye[None]).reshape(-1, n))
            grad = (fp.reshape(k, n) - fv[:, None]) / h
            jac = np.transpose(gp.reshape(k, n, mg) - gv[:, None, :], (0, 2, 1)) / h
            evals[rows] += n
        bad = ~np.isfinite(grad)
        grad[bad] = 0.0
        jac[~np.isfinite(jac)] = 0.0
        return grad, jac

    f, g = call(x)
    evals += 1
    m = g.shape[1]
    all_rows = np.arange(r)
    grad, jac = derivatives(all_rows, f, g)
    s = np.full(r, st.trust_radius_init)
    active = np.ones(r, dtype=bool)
    iterations = np.zeros(r, dtype=np.int64)
    converged = np.zeros(r, dtype=bool)
    reason = [''] * r
    if st.qp_solver not in ('active-set', 'osqp'):
        raise ValueError(f"qp_solver must be 'active-set' or 'osqp', got {st.qp_solver!r}")
    qp = _ActiveSetQps(r, n, m, st) if st.qp_solver == 'active-set' else _RestartQps(r, n, m, st)
    qp_solves = 0
    qp_failures = np.zeros(r, dtype=np.int64)
    qp_failed_run = np.zeros(r, dtype=np.int64)  # consecutive failures
    qp_status = [''] * r
    history = [x.copy()] if record_history else []
    f_hist: list[list[float]] = [[float(v)] for v in f]
    m_hist: list[list[float]] = [[float(v)] for v in _merit(f, g, mu)]

    while active.any():
        # Trust-region subproblem for every active restart (inactive blocks are trivial).
        lo = np.where(active[:, None], np.maximum(-s[:, None], lower - x), 0.0)
        hi = np.where(active[:, None], np.minimum(s[:, None], upper - x), 0.0)
        act = active[:, None]
        t0 = time.perf_counter()
        d, _, status = _polled(poll, st.poll_interval, qp.solve, active.copy(), np.where(act, grad, 0.0),
                                 np.where(active[:, None, None], jac, 0.0),
                                 np.where(act, g, -1.0), np.where(active, mu, 1.0), lo, hi, np.where(active, s, 1.0))
        timers['qp'] += time.perf_counter() - t0
        qp_solves += 1
        iterations[active] += 1
        solved = active & np.array([st_i in QP_OK_STATUSES for st_i in status], dtype=bool)
        failed = active & ~solved
        merit = _merit(f, g, mu)
        accept = np.zeros(r, dtype=bool)
        reject = np.zeros(r, dtype=bool)
        small = np.zeros(r, dtype=bool)
        flat = np.zeros(r, dtype=bool)
        if solved.any():
            qp_failed_run[solved] = 0
            model = (f + np.einsum('rn,rn->r', grad, d)
                     + mu * np.maximum(g + np.einsum('rmn,rn->rm', jac, d), 0.0).sum(axis=1))
            predicted = merit - model
            scale = np.maximum(1.0, np.abs(merit))
            small = solved & ~(predicted > st.improve_tol * scale)
            cand = np.flatnonzero(solved & ~small)
            if cand.size:
                xn = np.clip(x[cand] + d[cand], lower[cand], upper[cand])
                fn, gn = call(xn)
                evals[cand] += 1
                actual = merit[cand] - _merit(fn, gn, mu[cand])
                ok = actual >= st.accept_ratio * predicted[cand]
                acc = cand[ok]
                accept[acc] = True
                reject[cand[~ok]] = True
                if acc.size:
                    step = xn[ok] - x[acc]
                    # objective and step tolerance: an accepted step that moved x by at most step_tol
                    # (∞-norm) and the merit by at most objective_tol (relative to max(1, |φ|))
                    flat[acc] = ((np.abs(step).max(axis=1, initial=0.0) <= st.step_tol)
                                 & (actual[ok] <= st.objective_tol * scale[acc]))
                    x[acc] = xn[ok]
                    f[acc] = fn[ok]
                    g[acc] = gn[ok]
                    # expand from the step actually taken (an interior step says the box was not binding)
                    taken = np.abs(d[acc]).max(axis=1, initial=0.0)
                    s[acc] = np.minimum(np.maximum(s[acc], taken * st.trust_expand), st.trust_radius_max) \
                        if st.trust_expand_from_step else np.minimum(s[acc] * st.trust_expand, st.trust_radius_max)
                    grad[acc], jac[acc] = derivatives(acc, f[acc], g[acc])
                if st.trust_expand_from_step:  # shrink below the rejected step, not just the box
                    s[reject] = st.trust_shrink * np.minimum(s[reject], np.abs(d[reject]).max(axis=1, initial=0.0))
                else:
                    s[reject] *= st.trust_shrink
        if failed.any():
            # A failed subproblem says nothing about stationarity: never "converged" from it. Shrink
            # the box (a smaller, better-conditioned QP) and stop after max_qp_failures in a row.
            qp_failures[failed] += 1
            qp_failed_run[failed] += 1
            for i in np.flatnonzero(failed):
                qp_status[i] = status[i]
            s[failed] *= st.trust_shrink
            for i in np.flatnonzero(failed & (qp_failed_run >= st.max_qp_failures)):
                active[i] = False
                reason[i] = f'{REASON_QP_FAILED} ({status[i]})'
        if record_history:
            history.append(x.copy())
        tiny = reject & (s < st.trust_radius_min)
        inner_done = small | tiny | flat
        for i in np.flatnonzero(inner_done):
            if np.max(g[i], initial=-np.inf) <= st.constraint_tol:
                active[i] = False
                converged[i] = True
                reason[i] = (REASON_CONVERGED_MODEL if small[i] else REASON_CONVERGED_STEP if flat[i]
                             else REASON_CONVERGED_TRUST)
            elif mu[i] * st.penalty_factor > st.penalty_max * (1 + 1e-12):
                active[i] = False
                reason[i] = REASON_PENALTY_LIMIT
            else:
                mu[i] *= st.penalty_factor
                s[i] = max(s[i], st.trust_radius_init)
        over = active & (iterations >= st.max_iterations)
        for i in np.flatnonzero(over):
            active[i] = False
            reason[i] = REASON_ITERATION_LIMIT
        merit_now = _merit(f, g, mu)
        for i in np.flatnonzero(iterations == qp_solves):  # restarts that took part in this iteration
            f_hist[i].append(float(f[i]))
            m_hist[i].append(float(merit_now[i]))
        if monitor is not None:
            monitor(ScpProgress(iteration=qp_solves, active=active.copy(), x=x.copy(), fun=f.copy(),
                                constraints=g.copy()))

    feasible = np.max(g, axis=1, initial=-np.inf) <= st.constraint_tol
    return ScpResult(x=x, fun=f, constraints=g, penalty=mu, iterations=iterations, evaluations=evals,
                     converged=converged, feasible=feasible, reason=reason, qp_solves=qp_solves,
                     qp_time=timers['qp'], eval_time=timers['eval'], history=history,
                     objective_history=[np.asarray(h) for h in f_hist], merit_history=[np.asarray(h) for h in m_hist],
                     qp_failures=qp_failures, qp_status=qp_status)


def _polled(poll: Callable[[], None] | None, interval: float, fn: Callable, *args):
    """``fn(*args)``; with ``poll``, run it in a worker thread and call ``poll`` every ``interval`` s
    until it returns. If ``poll`` raises, the exception propagates at once and the thread's result
    (computed on objects nobody uses any more) is discarded. The thread is not a daemon: an
    interpreter exiting right after a stop waits for the one QP in flight instead of tearing it
    down mid-solve (which aborts the process)."""
    if poll is None:
        return fn(*args)
    poll()
    out: dict[str, object] = {}

    def run() -> None:
        try:
            out['value'] = fn(*args)
        except BaseException as exc:  # handed to the caller below
            out['error'] = exc

    worker = threading.Thread(target=run, name='scp-qp', daemon=False)
    worker.start()
    while True:
        worker.join(interval)
        if not worker.is_alive():
            break
        poll()
    if 'error' in out:
        raise out['error']
    return out['value']

