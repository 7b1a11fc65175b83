"""Maximum-likelihood GPIS hyperparameters C and l (paper section III-A: "set using maximum-likelihood estimation").

Fisher scoring on the negative log marginal likelihood of values and gradient observations (its analytic
gradient and Fisher information), within bounds that keep the paper's "missing = object" mechanism and thin
objects intact (docs/gpis-model.md, Hyperparameters). A multi-start L-BFGS-B search is kept as the
reference it is tested against (:func:`reference_search`).
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import minimize
from scipy.stats import chi2

from gpis_grasp_ros.core.gpis.likelihood import (
    _LikelihoodWorkspace,
    fisher_information,
    negative_log_marginal_likelihood,
    profile_signal_variance,
)
from gpis_grasp_ros.core.gpis.observations import VALUE, _Observations
from gpis_grasp_ros.core.gpis.threads import blas_threads
from gpis_grasp_ros.core.grid import GridGeometry

if TYPE_CHECKING:  # pragma: no cover
    from gpis_grasp_ros.core.gpis.regression import GpisParams

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class HyperparameterFit:
    """Outcome of the maximum-likelihood search (:func:`fit_hyperparameters`).

    ``bound_hits`` names every bound the optimum sits on (``'length_scale_lower'``,
    ``'length_scale_upper'``, ``'signal_variance_lower'``, ``'signal_variance_upper'``): the
    likelihood would rise beyond it, the value is the bound's, not the data's. Every binding
    bound is also logged (warning, logger ``gpis_grasp_ros.core.gpis.hyperparameters``). ``cholesky_failures``
    counts likelihood evaluations whose K + N was not numerically positive definite (the search
    treats them as a wall; logged); ``failed_starts`` counts starts at which the factorisation
    failed, so that the search could not move from them. ``ok`` is False when no start produced a
    finite likelihood: the search then keeps the start values (logged as an error).

    A warm-started fit (``warm_started``) began at a previous fit's C and l; ``drift_statistic`` is
    the score statistic there, ``drift_ratio`` the likelihood ratio of one scoring step where that
    statistic was inconclusive, and ``searched`` tells whether the test rejected the previous values
    so that the search ran (docs/gpis-model.md, Warm start).
    """

    signal_variance: float  # C, m^2
    length_scale: float  # l, m
    log_likelihood: float  # on the search subset (nats)
    bounds: tuple[tuple[float, float], tuple[float, float]]  # (C_lo, C_hi) m^2, (l_lo, l_hi) m
    bound_hits: tuple[str, ...] = ()
    cholesky_failures: int = 0
    failed_starts: int = 0
    n_starts: int = 1
    n_observations: int = 0  # size of the search subset (values + gradient components)
    ok: bool = True
    n_evaluations: int = 0  # likelihood evaluations (each one Cholesky of the search subset)
    warm_started: bool = False
    searched: bool = True  # False: a warm start whose previous C and l the score test kept
    drift_statistic: float = math.nan  # score statistic at the warm start (chi^2 with 1-2 dof)
    drift_ratio: float = math.nan  # likelihood ratio of the scoring step, where the score test was inconclusive


def hyperparameter_bounds(geometry: GridGeometry, params: GpisParams,
                          inscribed_radius_m: float | None = None) -> tuple[tuple[float, float], tuple[float, float]]:
    """Bounds (m^2, m) for C and l (docs/gpis-model.md, Hyperparameters).

    l in [``length_scale_min_cells`` cells, min(``length_scale_max_extent`` x E,
    ``length_scale_max_thickness`` x ``inscribed_radius_m``)], sqrt(C) in ``signal_std_bounds`` x E,
    E the grid's metric extent (its longer side), ``inscribed_radius_m`` the object's largest
    inscribed radius (m; None or <= 0: no thickness bound).
    """
    extent = max(geometry.size_m)
    lo_l = params.length_scale_min_cells * geometry.resolution
    hi_l = params.length_scale_max_extent * extent
    if params.length_scale_max_thickness is not None and inscribed_radius_m is not None and inscribed_radius_m > 0:
        hi_l = min(hi_l, params.length_scale_max_thickness * inscribed_radius_m)
    hi_l = max(hi_l, 1.01 * lo_l)
    lo_s, hi_s = (params.signal_std_bounds[0] * extent, params.signal_std_bounds[1] * extent)
    return (lo_s ** 2, hi_s ** 2), (lo_l, hi_l)


def initial_hyperparameters(geometry: GridGeometry, train_y: np.ndarray, params: GpisParams,
                            inscribed_radius_m: float | None = None) -> tuple[float, float]:
    """Start / default (C, l): given values, else C = mean (y - m)^2 and l = extent / 12 (~2 cells at M = 25)."""
    (c_lo, c_hi), (l_lo, l_hi) = hyperparameter_bounds(geometry, params, inscribed_radius_m)
    c0 = params.signal_variance
    if c0 is None:
        c0 = float(np.clip(np.mean((train_y - params.prior_mean) ** 2), c_lo, c_hi))
    l0 = params.length_scale if params.length_scale is not None else float(
        np.clip(max(geometry.size_m) / 12.0, l_lo, l_hi))
    return float(c0), float(l0)


_WALL = 1e25  # objective value the search sees where K + N cannot be factorised (counted and logged)
_PROFILE_STEPS, _PROFILE_TOL = 1, 0.05  # C steps of a start (profile_signal_variance) and when to stop them
_BASIN = 0.05  # a restart whose iterate comes this close (in log C and log l) to a found optimum is stopped
_SCORING_GAIN = 1e-3  # nats: the scoring search stops when a step predicts less gain than this
_SECANT_MAX = 8.0  # longest secant extrapolation of a scoring step, in steps
_SCORING_EVALUATIONS = 30  # likelihood evaluations of one start of the scoring search at most


def _search_subset(obs: _Observations, max_points: int, rng: np.random.Generator,
                   eligible: np.ndarray | None = None) -> _Observations:
    """At most ``max_points`` observations: a random subset of the (``eligible``) value cells with their gradients."""
    pool = np.arange(obs.n_values) if eligible is None else np.flatnonzero(eligible)
    if pool.size == 0:
        pool = np.arange(obs.n_values)
    if eligible is None and obs.size <= max_points:
        return obs
    n_cells = min(pool.size, max(1, int(max_points * obs.n_values / obs.size)))
    cells = rng.choice(pool, n_cells, replace=False)
    keys = {tuple(p) for p in np.round(obs.xy[cells] * 1e9).astype(np.int64).tolist()}
    grads = np.arange(obs.n_values, obs.size)
    grad_keys = np.round(obs.xy[grads] * 1e9).astype(np.int64).tolist()
    chosen = grads[np.array([tuple(p) in keys for p in grad_keys], dtype=bool)] if grads.size else grads
    return obs.subset(np.concatenate([cells, chosen]))


def fit_hyperparameters(geometry: GridGeometry, obs: _Observations, params: GpisParams,
                        eligible: np.ndarray | None = None, inscribed_radius_m: float | None = None,
                        warm_start: HyperparameterFit | None = None) -> HyperparameterFit:
    """Maximum-marginal-likelihood C (m^2) and l (m) from values and gradient observations.

    Fisher scoring on (log C, log l) within :func:`hyperparameter_bounds`, on a seeded subset of at most
    ``max_opt_points`` observations, from the data-driven start (:func:`initial_hyperparameters`, one
    closed-form C step); the ``n_restarts`` random starts are searched too when a factorisation failed.
    Binding bounds and Cholesky failures are logged and reported on the returned :class:`HyperparameterFit`.

    ``warm_start`` (the previous frame's fit of the same scene) replaces the multi-start search:
    its C and l are kept when the score test at ``params.warm_start_significance`` does not reject
    them on this data, else the search runs from them alone (docs/gpis-model.md, Warm start).
    """
    with blas_threads(params.blas_threads):
        return _fit_hyperparameters(geometry, obs, params, eligible, inscribed_radius_m, warm_start)


def _free_coordinates(x: np.ndarray, grad: np.ndarray, log_bounds: list[tuple[float, float]]) -> list[int]:
    """The coordinates free to move: not on a bound with the gradient pointing out of the box (there the
    Karush-Kuhn-Tucker condition holds)."""
    return [i for i, (lo, hi) in enumerate(log_bounds)
            if not ((x[i] <= lo + 1e-9 and grad[i] > 0) or (x[i] >= hi - 1e-9 and grad[i] < 0))]


def _constrained_step(x: np.ndarray, grad: np.ndarray, info: np.ndarray, lo: np.ndarray,
                      hi: np.ndarray) -> tuple[np.ndarray, float]:
    """The step d minimising the quadratic model g^T d + d^T I d / 2 within lo <= x + d <= hi, and the gain -model(d).

    Exact for the two coordinates: every active set (each coordinate free, at its lower or at its upper bound) is
    solved and the feasible one with the lowest model value kept (the model is convex, so its box minimum is one
    of them). Raises ``numpy.linalg.LinAlgError`` for a singular ``info``."""
    n = x.size
    best_d, best_m = np.zeros(n), 0.0
    for choice in itertools.product((None, 'lo', 'hi'), repeat=n):
        d = np.zeros(n)
        fixed = [i for i, c in enumerate(choice) if c is not None]
        for i in fixed:
            d[i] = (lo[i] if choice[i] == 'lo' else hi[i]) - x[i]
        free = [i for i in range(n) if choice[i] is None]
        if free:
            d[free] = -np.linalg.solve(info[np.ix_(free, free)], grad[free] + info[np.ix_(free, fixed)] @ d[fixed])
        if np.any(x + d < lo - 1e-12) or np.any(x + d > hi + 1e-12):
            continue
        m = float(grad @ d + 0.5 * d @ info @ d)
        if m < best_m:
            best_d, best_m = d, m
    return best_d, -best_m


def _drift_statistic(x: np.ndarray, grad: np.ndarray, log_bounds: list[tuple[float, float]],
                     workspace: _LikelihoodWorkspace, noise: np.ndarray) -> tuple[float, int, np.ndarray | None]:
    """Score statistic at ``x``: twice the likelihood gain of the Fisher-scoring step kept within the bounds, its
    degrees of freedom |F| and the Fisher information I (None when no coordinate is free).

    F are the coordinates free to move: a coordinate on a bound whose gradient points out of the
    box cannot (its Karush-Kuhn-Tucker condition holds). Away from the bounds the statistic is
    g_F^T I_FF^-1 g_F, chi^2 with |F| degrees of freedom under the hypothesis that the data are a
    draw of the GP with these hyperparameters (Rao's score test). Near a bound the step is stopped
    there (:func:`_constrained_step`): a coordinate a hair inside a bound that the gradient pushes
    against counts only the gain of the hair's move, as one on the bound counts none (the one-sided
    score test; its null distribution is a mixture of chi^2 with at most |F| degrees of freedom, so
    the chi^2(|F|) threshold is conservative).
    """
    free = _free_coordinates(x, grad, log_bounds)
    if not free:
        return 0.0, 0, None
    info = fisher_information(workspace, noise)
    lo, hi = np.array([b[0] for b in log_bounds]), np.array([b[1] for b in log_bounds])
    try:
        _, gain = _constrained_step(x, grad, info, lo, hi)
    except np.linalg.LinAlgError:  # pragma: no cover - singular information: treat as drifted
        return math.inf, len(free), None
    return 2.0 * gain, len(free), info


def _search_setup(geometry: GridGeometry, obs: _Observations, params: GpisParams, eligible: np.ndarray | None,
                  inscribed_radius_m: float | None, rng: np.random.Generator):
    """The search subset (drawn with ``rng``), its likelihood workspace, residuals, noise and (C, l) bounds."""
    sub = _search_subset(obs, params.max_opt_points, rng, eligible)
    resid = sub.y - np.where(sub.kind == VALUE, params.prior_mean, 0.0)
    bounds = hyperparameter_bounds(geometry, params, inscribed_radius_m)
    return sub, _LikelihoodWorkspace(sub), resid, sub.noise + params.jitter, bounds


def _secant_corrected(info: np.ndarray, s: np.ndarray, y: np.ndarray) -> np.ndarray | None:
    """The curvature model after a step s that changed the gradient by y: the BFGS update of ``info``, so that
    it has the likelihood's curvature along s (where the GP is not the data's model the Fisher information is
    not the curvature, and full scoring steps overshoot or fall short by a constant factor). None when s^T y is
    not positive (no curvature information; the Fisher information is read afresh)."""
    sy = float(s @ y)
    bs = info @ s
    sbs = float(s @ bs)
    if not (sy > 1e-12 * float(np.linalg.norm(s) * np.linalg.norm(y)) and sbs > 0.0):
        return None
    return info - np.outer(bs, bs) / sbs + np.outer(y, y) / sy


def _fit_hyperparameters(geometry: GridGeometry, obs: _Observations, params: GpisParams,
                         eligible: np.ndarray | None, inscribed_radius_m: float | None,
                         warm_start: HyperparameterFit | None = None, reference: bool = False) -> HyperparameterFit:
    rng = np.random.default_rng(params.seed)  # the subset, then the restarts' starts
    sub, workspace, resid, noise, bounds = _search_setup(geometry, obs, params, eligible, inscribed_radius_m, rng)
    (c_lo, c_hi), (l_lo, l_hi) = bounds
    log_bounds = [(math.log(c_lo), math.log(c_hi)), (math.log(l_lo), math.log(l_hi))]
    lo, hi = np.array([b[0] for b in log_bounds]), np.array([b[1] for b in log_bounds])
    failures, evaluations = [0], [0]
    last: list = [None, None]  # (x, (f, g)) of the last evaluation: the workspace holds it

    def objective(x: np.ndarray) -> tuple[float, np.ndarray]:
        # evaluated unless x is the last point evaluated, so afterwards the workspace (the Fisher information
        # and the C step read it) is at x; L-BFGS-B re-evaluates its start
        if last[0] is not None and np.array_equal(x, last[0]):
            return last[1][0], last[1][1].copy()
        evaluations[0] += 1
        try:
            out = negative_log_marginal_likelihood(x, workspace, resid, noise)
        except np.linalg.LinAlgError:
            failures[0] += 1
            out = (_WALL, np.zeros(2))
        last[:] = [np.array(x, dtype=np.float64), out]
        return out[0], out[1].copy()

    def profiled(x: np.ndarray, f: float) -> tuple[np.ndarray, float]:
        # C steps to the closed-form optimum given l (profile_signal_variance) from an evaluated start
        for _ in range(_PROFILE_STEPS):
            step = profile_signal_variance(workspace)
            if abs(step) < _PROFILE_TOL:
                break
            y = np.array([np.clip(x[0] + step, *log_bounds[0]), x[1]])
            fy = objective(y)[0]
            if not fy < f:
                break
            x, f = y, fy
        return x, f

    optima: list[np.ndarray] = []

    def scoring(x: np.ndarray, f: float, g: np.ndarray, info0: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """Fisher scoring from an evaluated x: d = -I^-1 g over the coordinates free to move, projected into the
        bounds and halved until the likelihood rises, I corrected after each step by the step's gradient change
        (:func:`_secant_corrected`); stops when the predicted gain g^T I^-1 g / 2 is below
        _SCORING_GAIN nats, after _SCORING_EVALUATIONS evaluations, or in a found optimum's basin. ``info0``: the
        Fisher information at x if already computed (the score test's)."""
        first = evaluations[0]
        info, x_last, g_last = info0, None, None
        while evaluations[0] - first < _SCORING_EVALUATIONS:
            free = _free_coordinates(x, g, log_bounds)
            if not free:
                break
            d = np.zeros(2)
            try:
                if x_last is not None:
                    info = _secant_corrected(info, x - x_last, g - g_last) if info is not None else None
                if info is None:
                    objective(x)  # the Fisher information is read at x (no evaluation when x was the last one)
                    info = fisher_information(workspace, noise)
                d[free] = -np.linalg.solve(info[np.ix_(free, free)], g[free])
                if -float(g[free] @ d[free]) < 2.0 * _SCORING_GAIN:
                    break
                # a coordinate the step takes beyond its bound stops there; the others take the step of the
                # quadratic model given that move (projecting the joint step would keep a move that was only
                # made to go with the blocked one)
                blocked = [i for i in free if not lo[i] <= x[i] + d[i] <= hi[i]]
                rest = [i for i in free if i not in blocked]
                if blocked and rest:
                    d[blocked] = np.clip(x[blocked] + d[blocked], lo[blocked], hi[blocked]) - x[blocked]
                    d[rest] = -np.linalg.solve(info[np.ix_(rest, rest)],
                                               g[rest] + info[np.ix_(rest, blocked)] @ d[blocked])
            except np.linalg.LinAlgError:  # singular information: no scoring direction from x (surfaced)
                logger.warning('hyperparameter search: singular Fisher information at C = %.3g m^2, l = %.3g m; '
                               'the search stops there', math.exp(x[0]), math.exp(x[1]))
                break
            t, moved, x_last, g_last = 1.0, False, x, g
            while evaluations[0] - first < _SCORING_EVALUATIONS and t > 1e-3:
                y = np.clip(x + t * d, lo, hi)
                fy, gy = objective(y)
                if fy < f:
                    slope0, slope1 = float(g @ d), float(gy @ d)
                    x, f, g, moved = y, fy, gy, True
                    # where the model is misspecified the Fisher information is not the curvature: when the
                    # slope along d says the minimum along d is far from the full step (beyond 2 or short of
                    # 1/2 of it), try the secant minimiser along d as well (at most 8 steps)
                    if t == 1.0 and slope0 < min(slope1, 0.0) and evaluations[0] - first < _SCORING_EVALUATIONS:
                        t_star = min(_SECANT_MAX, slope0 / (slope0 - slope1))
                        if t_star > 2.0 or t_star < 0.5:
                            z = np.clip(y - d + t_star * d, lo, hi)
                            fz, gz = objective(z)
                            if fz < f:
                                x, f, g = z, fz, gz
                    break
                t *= 0.5
            if not moved or any(np.max(np.abs(x - o)) < _BASIN for o in optima):
                break
        return x, f

    def lbfgs(x: np.ndarray, f: float) -> tuple[np.ndarray, float]:
        def same_basin(intermediate_result) -> None:  # a restart that reaches a found optimum would end there
            if any(np.max(np.abs(intermediate_result.x - o)) < _BASIN for o in optima):
                raise StopIteration

        res = minimize(objective, x, jac=True, method='L-BFGS-B', bounds=log_bounds, options={'maxiter': 200},
                       callback=same_basin if optima else None)
        return (res.x, float(res.fun)) if res.fun < _WALL else (x, f)

    warm, drift, searched, f_prev, info_prev = warm_start is not None and warm_start.ok, math.nan, True, math.inf, None
    drift_ratio = math.nan
    if warm:
        x_prev = np.array([np.clip(math.log(warm_start.signal_variance), *log_bounds[0]),
                           np.clip(math.log(warm_start.length_scale), *log_bounds[1])])
        f_prev, g_prev = objective(x_prev)
        warm = f_prev < _WALL  # no likelihood at the previous values: search cold
        if warm:
            drift, dof, info_prev = _drift_statistic(x_prev, g_prev, log_bounds, workspace, noise)
            threshold = chi2.isf(params.warm_start_significance, dof) if dof > 0 else math.inf
            searched = drift > threshold
            if not searched and info_prev is not None and drift > chi2.isf(0.5, dof):
                # inconclusive (above the median of its null distribution): the quadratic model the statistic
                # rests on can understate a drift far from the optimum, so the likelihood of the scoring step
                # decides, its likelihood ratio against the same threshold (one more evaluation)
                step, _ = _constrained_step(x_prev, g_prev, info_prev, lo, hi)
                x_step = np.clip(x_prev + step, lo, hi)
                f_step = objective(x_step)[0]
                drift_ratio = 2.0 * (f_prev - f_step) if f_step < _WALL else math.nan
                searched = drift_ratio > threshold
                if searched:  # the search goes on from the better point
                    x_prev, info_prev = x_step, None
    c0, l0 = initial_hyperparameters(geometry, sub.y[:sub.n_values], params, inscribed_radius_m)
    data_start = np.log([np.clip(c0, c_lo, c_hi), np.clip(l0, l_lo, l_hi)])
    random_starts = [np.array([rng.uniform(*log_bounds[0]), rng.uniform(*log_bounds[1])])
                     for _ in range(params.n_restarts)]
    starts = [x_prev] if warm else [data_start]
    best_x, best_f, failed_starts, n_starts = starts[0], (math.inf if searched else f_prev), 0, 0
    queue = list(starts) if searched else []
    while queue:
        x0 = queue.pop(0)
        n_starts += 1
        before = failures[0]
        f0, g0 = objective(x0)  # the warm start: the evaluation the score test used
        if failures[0] > before and f0 >= _WALL:
            failed_starts += 1
        else:
            x0, f0 = profiled(x0, f0)
            if reference:
                x, fun = lbfgs(x0, f0)
            else:
                f0, g0 = objective(x0)  # the Fisher information is read at x0 (after a rejected C step)
                x, fun = scoring(x0, f0, g0, info_prev if warm and np.array_equal(x0, x_prev) else None)
            optima.append(np.array(x))
            if fun < best_f:
                best_x, best_f = x, fun
        if n_starts == 1 and not warm:
            # the reference search always runs the random starts; the scoring search only when the data-driven
            # start met a failed factorisation (the wall may hide the optimum). On every shipped bag the
            # restarts of the reference end in the scoring search's optimum (bench gpis --bags).
            if reference or failures[0]:
                queue.extend(random_starts)
    starts_used = max(n_starts, 1)
    ok = math.isfinite(best_f)
    if failures[0]:
        logger.warning('hyperparameter search: K + N was not positive definite at %d of the likelihood '
                       'evaluations (%d of %d starts unusable)', failures[0], failed_starts, starts_used)
    if not ok:
        logger.error('hyperparameter search failed at every start: keeping the start values C = %.3g m^2, '
                     'l = %.3g m', math.exp(starts[0][0]), math.exp(starts[0][1]))
    hits = []
    for i, name in enumerate(('signal_variance', 'length_scale')):
        lo_i, hi_i = log_bounds[i]
        if ok and best_x[i] <= lo_i + 1e-6:
            hits.append(f'{name}_lower')
        elif ok and best_x[i] >= hi_i - 1e-6:
            hits.append(f'{name}_upper')
    c, ell = math.exp(best_x[0]), math.exp(best_x[1])
    if hits:
        logger.warning('maximum-likelihood hyperparameters sit on the bound(s) %s: C = %.3g m^2 in [%.3g, %.3g], '
                       'l = %.3g m in [%.3g, %.3g]', ', '.join(hits), c, c_lo, c_hi, ell, l_lo, l_hi)
    return HyperparameterFit(signal_variance=c, length_scale=ell, log_likelihood=-best_f if ok else math.nan,
                             bounds=bounds, bound_hits=tuple(hits), cholesky_failures=failures[0],
                             failed_starts=failed_starts, n_starts=starts_used, n_observations=sub.size, ok=ok,
                             n_evaluations=evaluations[0], warm_started=warm, searched=searched,
                             drift_statistic=drift, drift_ratio=drift_ratio)


def reference_search(geometry: GridGeometry, obs: _Observations, params: GpisParams,
                     eligible: np.ndarray | None = None, inscribed_radius_m: float | None = None) -> HyperparameterFit:
    """The reference cold search the scoring search is tested against: L-BFGS-B from the data-driven start and
    from every one of ``params.n_restarts`` random starts (the same subset, bounds and starts)."""
    with blas_threads(params.blas_threads):
        return _fit_hyperparameters(geometry, obs, params, eligible, inscribed_radius_m, None, reference=True)
