"""Maximum-likelihood GPIS hyperparameters C and l (paper section III-A: "set using maximum-likelihood estimation").

L-BFGS-B on the negative log marginal likelihood of values and gradient observations, within
bounds that keep the paper's "missing = object" mechanism and thin objects intact
(docs/gpis-model.md, Hyperparameters).
"""

from __future__ import annotations

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
    counts likelihood evaluations whose K + N was not numerically positive definite (L-BFGS-B
    treats them as a wall; logged); ``failed_starts`` counts starts at which the factorisation
    failed, so that L-BFGS-B could not move from them. ``ok`` is False when no start produced a
    finite likelihood: the search then keeps the start values (logged as an error).

    A warm-started fit (``warm_started``) began at a previous fit's C and l; ``drift_statistic`` is
    the score statistic there and ``searched`` tells whether it exceeded its threshold so that
    L-BFGS-B ran (docs/gpis-model.md, Warm start).
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


_WALL = 1e25  # objective value L-BFGS-B sees where K + N cannot be factorised (counted and logged)
_PROFILE_STEPS, _PROFILE_TOL = 1, 0.05  # C steps of a start (profile_signal_variance) and when to stop them
_BASIN = 0.05  # a restart whose iterate comes this close (in log C and log l) to a found optimum is stopped


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

    L-BFGS-B on (log C, log l) within :func:`hyperparameter_bounds`, on a seeded subset of at most
    ``max_opt_points`` observations. Binding bounds and Cholesky failures are logged and
    reported on the returned :class:`HyperparameterFit`.

    ``warm_start`` (the previous frame's fit of the same scene) replaces the multi-start search:
    its C and l are kept when the score test at ``params.warm_start_significance`` does not reject
    them on this data, else L-BFGS-B runs from them alone (docs/gpis-model.md, Warm start).
    """
    with blas_threads(params.blas_threads):
        return _fit_hyperparameters(geometry, obs, params, eligible, inscribed_radius_m, warm_start)


def _drift_statistic(x: np.ndarray, grad: np.ndarray, log_bounds: list[tuple[float, float]],
                     workspace: _LikelihoodWorkspace, noise: np.ndarray) -> tuple[float, int]:
    """Score statistic g_F^T I_FF^-1 g_F at ``x`` and its degrees of freedom |F|.

    F are the coordinates free to move: a coordinate on a bound whose gradient points out of the
    box cannot (its Karush-Kuhn-Tucker condition holds). I is the Fisher information. Under the
    hypothesis that the data are a draw of the GP with these hyperparameters the statistic is
    chi^2 with |F| degrees of freedom; it is also twice the likelihood gain a Fisher-scoring step
    predicts.
    """
    free = []
    for i, (lo, hi) in enumerate(log_bounds):
        blocked = (x[i] <= lo + 1e-9 and grad[i] > 0) or (x[i] >= hi - 1e-9 and grad[i] < 0)
        if not blocked:
            free.append(i)
    if not free:
        return 0.0, 0
    info = fisher_information(workspace, noise)[np.ix_(free, free)]
    g = grad[free]
    try:
        return float(g @ np.linalg.solve(info, g)), len(free)
    except np.linalg.LinAlgError:  # pragma: no cover - singular information: treat as drifted
        return math.inf, len(free)


def _search_setup(geometry: GridGeometry, obs: _Observations, params: GpisParams, eligible: np.ndarray | None,
                  inscribed_radius_m: float | None, rng: np.random.Generator):
    """The search subset (drawn with ``rng``), its likelihood workspace, residuals, noise and (C, l) bounds."""
    sub = _search_subset(obs, params.max_opt_points, rng, eligible)
    resid = sub.y - np.where(sub.kind == VALUE, params.prior_mean, 0.0)
    bounds = hyperparameter_bounds(geometry, params, inscribed_radius_m)
    return sub, _LikelihoodWorkspace(sub), resid, sub.noise + params.jitter, bounds


def _fit_hyperparameters(geometry: GridGeometry, obs: _Observations, params: GpisParams,
                         eligible: np.ndarray | None, inscribed_radius_m: float | None,
                         warm_start: HyperparameterFit | None = None) -> HyperparameterFit:
    rng = np.random.default_rng(params.seed)  # the subset, then the restarts' starts
    sub, workspace, resid, noise, bounds = _search_setup(geometry, obs, params, eligible, inscribed_radius_m, rng)
    (c_lo, c_hi), (l_lo, l_hi) = bounds
    log_bounds = [(math.log(c_lo), math.log(c_hi)), (math.log(l_lo), math.log(l_hi))]
    failures, evaluations = [0], [0]

    last: list = [None, None]  # (x, (f, g)) of the last evaluation: L-BFGS-B re-evaluates its start

    def objective(x: np.ndarray) -> tuple[float, np.ndarray]:
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

    warm, drift, searched, f_prev = warm_start is not None and warm_start.ok, math.nan, True, math.inf
    if warm:
        x_prev = np.array([np.clip(math.log(warm_start.signal_variance), *log_bounds[0]),
                           np.clip(math.log(warm_start.length_scale), *log_bounds[1])])
        f_prev, g_prev = objective(x_prev)
        warm = f_prev < _WALL  # no likelihood at the previous values: search cold
        if warm:
            starts = [x_prev]
            drift, dof = _drift_statistic(x_prev, g_prev, log_bounds, workspace, noise)
            searched = dof > 0 and drift > chi2.isf(params.warm_start_significance, dof)
    if not warm:
        c0, l0 = initial_hyperparameters(geometry, sub.y[:sub.n_values], params, inscribed_radius_m)
        starts = [np.log([np.clip(c0, c_lo, c_hi), np.clip(l0, l_lo, l_hi)])]
        for _ in range(params.n_restarts):
            starts.append(np.array([rng.uniform(*log_bounds[0]), rng.uniform(*log_bounds[1])]))

    best_x, best_f, failed_starts = starts[0], (math.inf if searched else f_prev), 0
    optima: list[np.ndarray] = []

    def same_basin(intermediate_result) -> None:  # a restart that reaches a found optimum would end there
        if any(np.max(np.abs(intermediate_result.x - x)) < _BASIN for x in optima):
            raise StopIteration

    for x0 in (starts if searched else []):
        before = failures[0]
        f0 = f_prev if warm else objective(x0)[0]
        if failures[0] > before:
            failed_starts += 1
            continue  # L-BFGS-B cannot move from a start without a likelihood
        if not warm:
            x0, f0 = profiled(x0, f0)
        res = minimize(objective, x0, jac=True, method='L-BFGS-B', bounds=log_bounds, options={'maxiter': 200},
                       callback=same_basin if optima else None)
        if res.fun < _WALL and res.status != 99:  # 99: stopped in a found optimum's basin
            optima.append(np.array(res.x))
        fun = float(res.fun) if res.fun < _WALL else f0
        x = res.x if res.fun < _WALL else x0
        if fun < best_f:
            best_x, best_f = x, fun
    ok = math.isfinite(best_f)
    if failures[0]:
        logger.warning('hyperparameter search: K + N was not positive definite at %d of the likelihood '
                       'evaluations (%d of %d starts unusable)', failures[0], failed_starts, len(starts))
    if not ok:
        logger.error('hyperparameter search failed at every start: keeping the start values C = %.3g m^2, '
                     'l = %.3g m', math.exp(starts[0][0]), math.exp(starts[0][1]))
    hits = []
    for i, name in enumerate(('signal_variance', 'length_scale')):
        lo, hi = log_bounds[i]
        if ok and best_x[i] <= lo + 1e-6:
            hits.append(f'{name}_lower')
        elif ok and best_x[i] >= hi - 1e-6:
            hits.append(f'{name}_upper')
    c, ell = math.exp(best_x[0]), math.exp(best_x[1])
    if hits:
        logger.warning('maximum-likelihood hyperparameters sit on the bound(s) %s: C = %.3g m^2 in [%.3g, %.3g], '
                       'l = %.3g m in [%.3g, %.3g]', ', '.join(hits), c, c_lo, c_hi, ell, l_lo, l_hi)
    return HyperparameterFit(signal_variance=c, length_scale=ell, log_likelihood=-best_f if ok else math.nan,
                             bounds=bounds, bound_hits=tuple(hits), cholesky_failures=failures[0],
                             failed_starts=failed_starts, n_starts=len(starts), n_observations=sub.size, ok=ok,
                             n_evaluations=evaluations[0], warm_started=warm, searched=searched,
                             drift_statistic=drift)


def fisher_scoring_search(geometry: GridGeometry, obs: _Observations, params: GpisParams,
                          eligible: np.ndarray | None = None, inscribed_radius_m: float | None = None,
                          max_evaluations: int = 10) -> HyperparameterFit:
    """A cold maximum-likelihood search in at most ``max_evaluations`` likelihood evaluations (docs/speed.md).

    From the single data-driven start of :func:`initial_hyperparameters` (one closed-form C step,
    :func:`profile_signal_variance`), Fisher scoring on (log C, log l): the step solves I d = -g with
    I the Fisher information (the expected Hessian of the negative log likelihood, one GEMM), over
    the coordinates free to move, projected into the bounds and halved until the likelihood rises;
    it stops when the predicted gain g^T I^-1 g / 2 is below 1e-3 nats. The same search subset and
    bounds as :func:`fit_hyperparameters`. Not the default: it has no restarts (the shipped search's
    three starts guard against a second optimum); ``bench gpis --bags`` compares the two.
    """
    with blas_threads(params.blas_threads):
        sub, ws, resid, noise, bounds = _search_setup(geometry, obs, params, eligible, inscribed_radius_m,
                                                      np.random.default_rng(params.seed))
        (c_lo, c_hi), (l_lo, l_hi) = bounds
        lo, hi = np.log([c_lo, l_lo]), np.log([c_hi, l_hi])
        log_bounds = list(zip(lo.tolist(), hi.tolist(), strict=True))
        evaluations = [0]

        def evaluate(x: np.ndarray) -> tuple[float, np.ndarray]:  # LinAlgError propagates: no silent wall
            evaluations[0] += 1
            return negative_log_marginal_likelihood(x, ws, resid, noise)

        x = np.clip(np.log(initial_hyperparameters(geometry, sub.y[:sub.n_values], params, inscribed_radius_m)),
                    lo, hi)
        f, g = evaluate(x)
        step = profile_signal_variance(ws)
        if abs(step) >= _PROFILE_TOL:
            y = np.array([np.clip(x[0] + step, lo[0], hi[0]), x[1]])
            fy, gy = evaluate(y)
            if fy < f:
                x, f, g = y, fy, gy
            else:
                f, g = evaluate(x)  # the Fisher information below is read at the last evaluation
        while evaluations[0] < max_evaluations:
            free = [i for i in range(2)
                    if not ((x[i] <= lo[i] + 1e-9 and g[i] > 0) or (x[i] >= hi[i] - 1e-9 and g[i] < 0))]
            if not free:
                break
            d = np.zeros(2)
            d[free] = -np.linalg.solve(fisher_information(ws, noise)[np.ix_(free, free)], g[free])
            if -float(g[free] @ d[free]) < 2e-3:
                break
            t, moved = 1.0, False
            while evaluations[0] < max_evaluations:
                y = np.clip(x + t * d, lo, hi)
                fy, gy = evaluate(y)
                if fy < f:
                    x, f, g, moved = y, fy, gy, True
                    break
                t *= 0.5
            if not moved:
                break
    hits = tuple(f'{name}_{side}' for i, name in enumerate(('signal_variance', 'length_scale'))
                 for side, on in (('lower', x[i] <= log_bounds[i][0] + 1e-6),
                                  ('upper', x[i] >= log_bounds[i][1] - 1e-6)) if on)
    return HyperparameterFit(signal_variance=math.exp(x[0]), length_scale=math.exp(x[1]), log_likelihood=-f,
                             bounds=bounds, bound_hits=hits, n_observations=sub.size, n_evaluations=evaluations[0])
