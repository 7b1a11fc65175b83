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
from scipy.linalg import cho_factor, cho_solve
from scipy.linalg.lapack import dpotri
from scipy.optimize import minimize

from gpis_grasp_ros.core.gpis.kernel import _DenseKernel
from gpis_grasp_ros.core.gpis.observations import VALUE, _Observations
from gpis_grasp_ros.core.gpis.threads import blas_threads
from gpis_grasp_ros.core.grid import GridGeometry

if TYPE_CHECKING:  # pragma: no cover
    from gpis_grasp_ros.core.gpis.regression import GpisParams

LOG_2PI = math.log(2.0 * math.pi)
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


def negative_log_marginal_likelihood(log_theta: np.ndarray, kernel: _DenseKernel, resid: np.ndarray,
                                     noise: np.ndarray) -> tuple[float, np.ndarray]:
    """-log p(y | X, C, l) and its gradient in (log C, log l) (Rasmussen & Williams eqs. 5.8, 5.9).

    ``kernel`` is the joint value/gradient Gram matrix of the observations as a function of l,
    ``resid`` = y - m (values) or the gradient observation, ``noise`` per-observation variances
    (jitter included). Raises ``numpy.linalg.LinAlgError`` when K + N is not numerically
    positive definite (the caller records it; no silent substitute value).
    """
    c, ell = math.exp(log_theta[0]), math.exp(log_theta[1])
    k0, dk0 = kernel(ell, with_dlog=True)
    a = c * k0
    a[np.diag_indices_from(a)] += noise
    cf = cho_factor(a, lower=True, check_finite=False)  # raises LinAlgError if not positive definite
    alpha = cho_solve(cf, resid, check_finite=False)
    n = resid.size
    nll = 0.5 * float(resid @ alpha) + float(np.sum(np.log(np.diag(cf[0])))) + 0.5 * n * LOG_2PI
    # d nll / d theta = -1/2 tr((alpha alpha^T - A^-1) dA/dtheta); A^-1 is needed for the trace term
    # (R&W Algorithm 5.1) and is formed from the Cholesky factor (LAPACK potri); it never solves a system.
    inv, info = dpotri(cf[0], lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f'potri failed with info={info}')
    inv_lower = np.tril(inv)  # potri fills the lower triangle only; A^-1 and dA/dtheta are symmetric

    def trace_inv(b: np.ndarray) -> float:  # tr(A^-1 B) for symmetric B from the lower triangle
        return 2.0 * float(np.vdot(inv_lower, b)) - float(np.dot(np.diag(inv_lower), np.diag(b)))

    grad = 0.5 * np.array([
        c * (trace_inv(k0) - float(alpha @ (k0 @ alpha))),  # dA / dlog C = C k0
        c * (trace_inv(dk0) - float(alpha @ (dk0 @ alpha))),  # dA / dlog l = C dk0 / dlog l
    ])
    if not (math.isfinite(nll) and np.all(np.isfinite(grad))):
        raise np.linalg.LinAlgError('non-finite marginal likelihood')
    return nll, grad


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
                        eligible: np.ndarray | None = None,
                        inscribed_radius_m: float | None = None) -> HyperparameterFit:
    """Maximum-marginal-likelihood C (m^2) and l (m) from values and gradient observations.

    L-BFGS-B on (log C, log l) within :func:`hyperparameter_bounds`, on a seeded subset of at most
    ``max_opt_points`` observations. Binding bounds and Cholesky failures are logged and
    reported on the returned :class:`HyperparameterFit`.
    """
    with blas_threads(params.blas_threads):
        return _fit_hyperparameters(geometry, obs, params, eligible, inscribed_radius_m)


def _fit_hyperparameters(geometry: GridGeometry, obs: _Observations, params: GpisParams,
                         eligible: np.ndarray | None, inscribed_radius_m: float | None) -> HyperparameterFit:
    rng = np.random.default_rng(params.seed)
    sub = _search_subset(obs, params.max_opt_points, rng, eligible)
    kernel = _DenseKernel(sub)
    resid = sub.y - np.where(sub.kind == VALUE, params.prior_mean, 0.0)
    noise = sub.noise + params.jitter
    (c_lo, c_hi), (l_lo, l_hi) = bounds = hyperparameter_bounds(geometry, params, inscribed_radius_m)
    log_bounds = [(math.log(c_lo), math.log(c_hi)), (math.log(l_lo), math.log(l_hi))]
    c0, l0 = initial_hyperparameters(geometry, sub.y[:sub.n_values], params, inscribed_radius_m)
    starts = [np.log([np.clip(c0, c_lo, c_hi), np.clip(l0, l_lo, l_hi)])]
    for _ in range(params.n_restarts):
        starts.append(np.array([rng.uniform(*log_bounds[0]), rng.uniform(*log_bounds[1])]))
    failures = [0]

    def objective(x: np.ndarray) -> tuple[float, np.ndarray]:
        try:
            return negative_log_marginal_likelihood(x, kernel, resid, noise)
        except np.linalg.LinAlgError:
            failures[0] += 1
            return _WALL, np.zeros(2)

    best_x, best_f, failed_starts = starts[0], math.inf, 0
    for x0 in starts:
        before = failures[0]
        f0 = objective(x0)[0]
        if failures[0] > before:
            failed_starts += 1
            continue  # L-BFGS-B cannot move from a start without a likelihood
        res = minimize(objective, x0, jac=True, method='L-BFGS-B', bounds=log_bounds, options={'maxiter': 200})
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
                             failed_starts=failed_starts, n_starts=len(starts), n_observations=sub.size, ok=ok)
