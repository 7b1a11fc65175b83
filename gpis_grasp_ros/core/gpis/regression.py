"""GPIS regression: the posterior from a grid SDF and noise map (paper sections III-A, III-B, eqs. 1 and 2).

:func:`fit_gpis` fits the hyperparameters and conditions the prior on the observations;
:func:`posterior_from_data` rebuilds the same posterior from its training data. Both go through
:func:`_condition` (weight-space conditioning on the Kronecker basis, docs/gpis-model.md, Computation),
so they give identical posteriors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular

from gpis_grasp_ros.core.gpis.basis import (
    _axis_index,
    _covariance_factor,
    _grid_axes,
    _kronecker_basis,
    _precision_on_grid,
)
from gpis_grasp_ros.core.gpis.hyperparameters import (
    HyperparameterFit,
    fit_hyperparameters,
    initial_hyperparameters,
)
from gpis_grasp_ros.core.gpis.kernel import KernelParams, _DenseKernel, _se_1d
from gpis_grasp_ros.core.gpis.likelihood import LOG_2PI
from gpis_grasp_ros.core.gpis.observations import (
    GRAD_X,
    GRAD_Y,
    VALUE,
    _Observations,
    _observations_from,
    gradient_observations,
)
from gpis_grasp_ros.core.gpis.posterior import GpisPosterior
from gpis_grasp_ros.core.gpis.threads import blas_threads
from gpis_grasp_ros.core.grid import GridGeometry


@dataclass(frozen=True)
class GpisParams:
    """Settings of :func:`fit_gpis` (lengths in metres, variances in m^2, gradients dimensionless)."""

    prior_mean: float = -0.01  # constant prior mean m (m), negative = "object" (section III-B)
    optimize_hyperparameters: bool = True  # maximise the log marginal likelihood over C and l
    signal_variance: float | None = None  # C (m^2): fixed value, or start of the search; None = data-driven
    length_scale: float | None = None  # l (m): fixed value, or start of the search; None = extent / 12
    n_restarts: int = 2  # extra random starts, searched when a factorisation failed (the reference search: always)
    seed: int = 0  # seeds restarts and the model-selection subset
    jitter: float = 1e-10  # added to every noise variance (diagonal of K + N), m^2 for values, 1 for gradients
    gradient_observations: bool = True  # also train on the SDF gradient (section III, derivative observations)
    gradient_noise_variance: float = 0.01  # g0: discretisation noise of one central-difference gradient component
    max_exact_points: int = 2500  # up to this many training cells mean and variance are exact
    search_band_cells: float | None = 3.0  # hyperparameter search on training cells with |SDF| <= this many cells
    max_opt_points: int = 450  # observations (values + gradient components) in the hyperparameter search subset
    rank_tolerance: float = 1e-10  # modes of prior variance below this x the largest's are dropped (std < 1e-5 x)
    max_rank: int = 2000  # cap on the basis size r on every path (cost r^3 / 3, memory H*W*r*8 bytes)
    blas_threads: int | None = 1  # BLAS threads during the fit (None = library default), see blas_threads()
    length_scale_min_cells: float = 1.0  # lower bound on l in grid cells (docs/gpis-model.md, Hyperparameters)
    length_scale_max_extent: float = 1.0 / 6.0  # upper bound on l as a multiple of the grid extent E
    length_scale_max_thickness: float | None = 3.0  # upper bound on l as a multiple of the inscribed radius r_in
    signal_std_bounds: tuple[float, float] = (1e-3, 10.0)  # sqrt(C) x grid extent
    warm_start_significance: float = 0.05  # level of the score test that keeps a warm start's C and l

    def __post_init__(self) -> None:
        if self.jitter < 0 or not math.isfinite(self.jitter):
            raise ValueError(f'jitter must be a non-negative number of m^2, got {self.jitter}')
        for name in ('signal_variance', 'length_scale'):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f'{name} must be positive, got {value}')
        if not (math.isfinite(self.gradient_noise_variance) and self.gradient_noise_variance >= 0):
            raise ValueError(f'gradient_noise_variance must be >= 0, got {self.gradient_noise_variance}')
        if self.max_rank < 1 or not (0 <= self.rank_tolerance < 1):
            raise ValueError('max_rank must be >= 1 and rank_tolerance in [0, 1)')
        if self.length_scale_max_thickness is not None and not (0 < self.length_scale_max_thickness < math.inf):
            raise ValueError('length_scale_max_thickness must be positive or None, got '
                             f'{self.length_scale_max_thickness}')
        if not (0 < self.length_scale_min_cells and 0 < self.length_scale_max_extent < math.inf):
            raise ValueError('length_scale_min_cells and length_scale_max_extent must be positive, got '
                             f'{self.length_scale_min_cells}, {self.length_scale_max_extent}')
        if not (0 < self.warm_start_significance < 1):
            raise ValueError(f'warm_start_significance must be in (0, 1), got {self.warm_start_significance}')
        lo, hi = self.signal_std_bounds
        if not (0 < lo < hi and math.isfinite(hi)):
            raise ValueError(f'signal_std_bounds must satisfy 0 < low < high, got {self.signal_std_bounds}')


def _condition(geometry: GridGeometry, kp: KernelParams, obs: _Observations, jitter: float, max_exact_points: int,
               rank_tolerance: float, max_rank: int, hyperparameters_optimized: bool,
               fit: HyperparameterFit | None = None) -> GpisPosterior:
    """GPIS posterior on ``geometry`` from values and gradient observations (eqs. 1, 2, kernel derivatives)."""
    c, ell, m = float(kp.signal_variance), float(kp.length_scale), float(kp.prior_mean)
    if not (c > 0 and ell > 0 and math.isfinite(c) and math.isfinite(ell) and math.isfinite(m)):
        raise ValueError(f'invalid kernel parameters {kp}')
    noise = obs.noise + jitter
    if np.any(noise <= 0):
        raise ValueError('noise variance + jitter must be > 0 m^2 for every training point')
    n = obs.size
    h, w = geometry.shape
    resid = obs.y - np.where(obs.kind == VALUE, m, 0.0)  # the constant prior mean has zero gradient
    xs, ys = _grid_axes(geometry)
    cols, col_on = _axis_index(obs.xy[:, 0], xs, geometry.resolution)
    rows, row_on = _axis_index(obs.xy[:, 1], ys, geometry.resolution)
    on_grid = bool(np.all(col_on) and np.all(row_on))
    exact = obs.n_values <= max_exact_points  # off the grid: mean and variance by a function-space Cholesky
    joint = obs.has_gradients
    # at most max_rank modes on either path: the conditioning costs r^3 / 3 (a thin object's 45 x 45 grid
    # would keep 4000+ modes above the tolerance and take seconds)
    basis = _kronecker_basis(geometry, ell, rank_tolerance, max_rank, joint)
    approximation = 'reduced_rank' if not exact or (basis.capped and on_grid) else 'exact'
    sqrt_c = math.sqrt(c)
    kinds = [k for k in (VALUE, GRAD_X, GRAD_Y) if np.any(obs.kind == k)]
    sel = {k: obs.kind == k for k in kinds}
    rows_sel = {}
    for k in kinds:  # (H, r), (W, r): observation type k on the grid is sum_k w_k fy[:, k] fx[:, k]^T
        fy_all, fx_all = basis.rows(k)
        rows_sel[k] = (sqrt_c * fy_all[:, basis.a], fx_all[:, basis.b])

    # weight-space precision P = I + G_X^T N^-1 G_X and G_X^T N^-1 (y - m) (R&W eq. 2.8 with Sigma_p = I)
    precision = None
    if on_grid:
        weights, rhs = {}, {}
        for k in kinds:
            weights[k] = np.zeros((h, w))
            np.add.at(weights[k], (rows[sel[k]], cols[sel[k]]), 1.0 / noise[sel[k]])
            rhs[k] = np.zeros((h, w))
            np.add.at(rhs[k], (rows[sel[k]], cols[sel[k]]), resid[sel[k]] / noise[sel[k]])
        precision = _precision_on_grid(basis, sqrt_c, weights)
        g_rhs = sum(np.einsum('ik,ij,jk->k', rows_sel[k][0], rhs[k], rows_sel[k][1]) for k in kinds)
    g_train = None
    if precision is None:
        g_train = np.empty((n, basis.rank))
        for k in kinds:
            s = sel[k]
            fx_tr = basis.x.rows_at(obs.xy[s, 0], cols[s], col_on[s], basis.b, k == GRAD_X)
            fy_tr = basis.y.rows_at(obs.xy[s, 1], rows[s], row_on[s], basis.a, k == GRAD_Y)
            g_train[s] = sqrt_c * fy_tr * fx_tr  # (n_k, r) basis functionals at the training inputs
        g_scaled = g_train / noise[:, None]
        precision = g_train.T @ g_scaled
        g_rhs = g_scaled.T @ resid
    precision[np.diag_indices_from(precision)] += 1.0
    chol_p = np.linalg.cholesky(precision)  # P >= I: always positive definite, no jitter needed

    # cross-covariance columns of the grid values with every observation: cov(f(x*), L_i f) / C (off the grid;
    # on it the mean and gradient take the separable route of _mean_on_grid)
    kx_star = ky_star = None
    if not on_grid:
        kx_star = _se_1d(xs, obs.xy[:, 0], ell, 0, obs.px)  # (W, N)
        ky_star = _se_1d(ys, obs.xy[:, 1], ell, 0, obs.py)  # (H, N)
    variance = None
    if on_grid or not exact:
        # representer weights from the weight-space posterior mean (Woodbury, R&W eq. A.9):
        # alpha = (K + N)^-1 (y - m) = N^-1 (y - m - G_X w),  w = P^-1 G_X^T N^-1 (y - m)
        w_mean = cho_solve((chol_p, True), g_rhs, check_finite=False)
        if g_train is not None:
            f_train = g_train @ w_mean
        else:
            f_train = np.empty(n)
            for k in kinds:
                fy_k, fx_k = rows_sel[k]
                f_train[sel[k]] = ((fy_k * w_mean[None, :]) @ fx_k.T)[rows[sel[k]], cols[sel[k]]]
        alpha = (resid - f_train) / noise
        # log |K + N| = log |P| + log |N| (determinant lemma, R&W eq. A.10); lml is R&W eq. 2.30
        logdet = 2.0 * float(np.sum(np.log(np.diag(chol_p)))) + float(np.sum(np.log(noise)))
        lml = -0.5 * float(resid @ alpha) - 0.5 * logdet - 0.5 * n * LOG_2PI
    else:  # exact with inputs off the grid: function-space Cholesky (the basis only serves sampling)
        k_xx = c * _DenseKernel(obs)(ell)[0]
        k_xx[np.diag_indices_from(k_xx)] += noise
        cf = cho_factor(k_xx, lower=True, check_finite=False)
        alpha = cho_solve(cf, resid, check_finite=False)
        lml = -0.5 * float(resid @ alpha) - float(np.sum(np.log(np.diag(cf[0])))) - 0.5 * n * LOG_2PI  # R&W 2.30
        variance = _exact_variance(cf[0], c, kx_star, ky_star)

    # Sigma = G P^-1 G^T = (G L_P^-T)(G L_P^-T)^T over the grid values; its diagonal is eq. 2
    cov_factor = _covariance_factor(basis, sqrt_c, chol_p, h, w)
    if variance is None:
        variance = np.einsum('ij,ij->i', cov_factor, cov_factor)

    # eq. 1 and its gradient: separable products of the kernel and its derivatives
    if on_grid:
        mean, grad_x, grad_y = _mean_on_grid(xs, ys, ell, m, c * alpha, rows, cols, sel)
    else:  # (H x N)(N x W)
        weighted = ky_star * (c * alpha)[None, :]  # (H, N)
        mean = m + weighted @ kx_star.T
        grad_x = weighted @ _se_1d(xs, obs.xy[:, 0], ell, 1, obs.px).T
        grad_y = (_se_1d(ys, obs.xy[:, 1], ell, 1, obs.py) * (c * alpha)[None, :]) @ kx_star.T
    nv = obs.n_values
    return GpisPosterior(
        geometry=geometry, mean=mean, variance=np.clip(variance.reshape(h, w), 0.0, None),
        gradient=np.stack([grad_x, grad_y], axis=-1), cov_factor=cov_factor, params=kp,
        train_xy=obs.xy[:nv], train_y=obs.y[:nv], train_noise=obs.noise[:nv], jitter=float(jitter),
        hyperparameters_optimized=hyperparameters_optimized, alpha=alpha, approximation=approximation,
        rank=basis.rank, truncation=basis.truncation, log_marginal_likelihood=lml,
        train_grad_xy=obs.xy[nv:], train_grad_axis=(obs.kind[nv:] == GRAD_Y).astype(np.int64),
        train_grad=obs.y[nv:], train_grad_noise=obs.noise[nv:], hyperparameter_fit=fit)


def _mean_on_grid(xs: np.ndarray, ys: np.ndarray, ell: float, m: float, weights: np.ndarray, rows: np.ndarray,
                  cols: np.ndarray, sel: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Posterior mean (eq. 1) and its x / y gradient on the grid for observations on cell centres.

    With every observation at a cell centre its cross-covariance column is a column of the (H, H) and
    (W, W) kernel matrices between the grid's axes, so sum_i w_i ky_i kx_i^T = sum_k Ty_k S_k Tx_k^T with
    S_k the weights w = C alpha of observation type k summed into their cells: O(H W (H + W)) per type
    instead of O(H W N) and the (H, N), (W, N) cross-covariances.
    """
    h, w = ys.size, xs.size
    mean = np.full((h, w), m)
    grad_x = np.zeros((h, w))
    grad_y = np.zeros((h, w))
    for kind, s in sel.items():
        qx, qy = int(kind == GRAD_X), int(kind == GRAD_Y)  # the observation's derivative orders
        scattered = np.zeros((h, w))
        np.add.at(scattered, (rows[s], cols[s]), weights[s])
        ty, tx = _se_1d(ys, ys, ell, 0, qy), _se_1d(xs, xs, ell, 0, qx)
        ty_s = ty @ scattered  # (H, W)
        mean += ty_s @ tx.T
        grad_x += ty_s @ _se_1d(xs, xs, ell, 1, qx).T
        grad_y += (_se_1d(ys, ys, ell, 1, qy) @ scattered) @ tx.T
    return mean, grad_x, grad_y


def _exact_variance(chol_lower: np.ndarray, c: float, kx_star: np.ndarray, ky_star: np.ndarray,
                    max_block: int = 4_000_000) -> np.ndarray:
    """Eq. 2 on every cell (row-major): C - k*^T (K + N)^-1 k*, as ||L^-1 k*||^2 in chunks."""
    n = kx_star.shape[1]
    h, w = ky_star.shape[0], kx_star.shape[0]
    rows, cols = np.divmod(np.arange(h * w), w)
    chunk = max(1, max_block // max(n, 1))
    out = np.empty(h * w)
    for start in range(0, h * w, chunk):
        sl = slice(start, min(start + chunk, h * w))
        k_star = (c * ky_star[rows[sl]] * kx_star[cols[sl]]).T  # (n, chunk)
        v = solve_triangular(chol_lower, k_star, lower=True, check_finite=False)
        out[sl] = c - np.einsum('ij,ij->j', v, v)
    return out


def fit_gpis(sdf_m: np.ndarray, noise_variance_m2: np.ndarray, train_mask: np.ndarray, geometry: GridGeometry,
             params: GpisParams = GpisParams(), *, warm_start: HyperparameterFit | None = None) -> GpisPosterior:
    """GPIS posterior from a grid SDF and noise map (sections III-A, III-B, V-A).

    Args:
        sdf_m: ``(H, W)`` observed signed distances (m), e.g. :func:`~gpis_grasp_ros.core.sdf.signed_distance`.
        noise_variance_m2: ``(H, W)`` observation-noise variance of each SDF value (m^2).
        train_mask: ``(H, W)`` bool, cells used for training (missing measurements excluded).
        geometry: placement of the grid (cell centres are the training inputs, m).
        params: prior mean, gradient observations, hyperparameter search, numerical settings.
        warm_start: the previous frame's :class:`HyperparameterFit` of the same scene
            (``posterior.hyperparameter_fit``): the search starts there and runs only when the
            likelihood rejects it (:func:`fit_hyperparameters`); None = cold multi-start search.

    Returns:
        :class:`GpisPosterior` with mean (eq. 1), variance (eq. 2), mean gradient, joint
        covariance factor and the training data that reproduce it (:func:`posterior_from_data`).
        With ``params.gradient_observations`` the GP is also trained on the SDF's central-difference
        gradient (:func:`gradient_observations`).
    """
    sdf = np.asarray(sdf_m, dtype=np.float64)
    noise = np.asarray(noise_variance_m2, dtype=np.float64)
    mask = np.asarray(train_mask, dtype=bool)
    if sdf.shape != geometry.shape or noise.shape != geometry.shape or mask.shape != geometry.shape:
        raise ValueError(f'sdf {sdf.shape}, noise {noise.shape} and train_mask {mask.shape} must all match the '
                         f'grid shape {geometry.shape}')
    if not mask.any():
        raise ValueError('train_mask selects no cell: nothing to fit the GPIS to')
    if not (np.all(np.isfinite(sdf[mask])) and np.all(np.isfinite(noise[mask]))):
        raise ValueError('training data contain non-finite values')
    centers = geometry.cell_centers()
    gradients = None
    if params.gradient_observations:
        gradients = gradient_observations(sdf, noise, mask, geometry, params.gradient_noise_variance)
    obs = _observations_from(centers[mask], sdf[mask], noise[mask], gradients)
    inscribed_radius = max(0.0, -float(sdf.min()))  # m, largest inscribed radius of the object (Thickness bound)
    with blas_threads(params.blas_threads):
        fit = None
        if params.optimize_hyperparameters:
            eligible = None
            if params.search_band_cells is not None:
                eligible = np.abs(sdf[mask]) <= params.search_band_cells * geometry.resolution
            fit = fit_hyperparameters(geometry, obs, params, eligible, inscribed_radius, warm_start)
            c, ell = fit.signal_variance, fit.length_scale
        else:
            c, ell = initial_hyperparameters(geometry, obs.y[:obs.n_values], params, inscribed_radius)
        kp = KernelParams(signal_variance=c, length_scale=ell, prior_mean=params.prior_mean)
        return _condition(geometry, kp, obs, params.jitter, params.max_exact_points, params.rank_tolerance,
                          params.max_rank, params.optimize_hyperparameters, fit)


def posterior_from_data(geometry: GridGeometry, kernel_params: KernelParams, train_xy: np.ndarray,
                        train_y: np.ndarray, train_noise: np.ndarray, jitter: float = 0.0, *,
                        train_grad_xy: np.ndarray | None = None, train_grad_axis: np.ndarray | None = None,
                        train_grad: np.ndarray | None = None, train_grad_noise: np.ndarray | None = None,
                        hyperparameters_optimized: bool = False, max_exact_points: int = 2500,
                        rank_tolerance: float = 1e-10, max_rank: int = 2000,
                        blas_threads_limit: int | None = 1) -> GpisPosterior:
    """Rebuild the GPIS posterior from its training data (what a ``GpisModel`` message carries).

    Values ``train_*`` and, optionally, gradient observations ``train_grad_*`` (component
    ``train_grad_axis`` 0 = d/dx, 1 = d/dy at ``train_grad_xy``, dimensionless values and noise).
    With the same numerical settings as the :class:`GpisParams` used by :func:`fit_gpis` (the
    defaults match), the result equals ``fit_gpis``'s to rounding. Training inputs may lie
    off the cell centres: mean, variance and gradient stay exact (exact path), while the
    Kronecker basis behind ``cov_factor`` is extended by the Nystroem formula, which drops the
    part of the prior not determined by the grid values (~1e-4 C for l = 2 cells).
    """
    gradients = None
    if train_grad_xy is not None and np.asarray(train_grad_xy).size:
        gradients = (train_grad_xy, train_grad_axis, train_grad, train_grad_noise)
    obs = _observations_from(train_xy, np.asarray(train_y, dtype=np.float64).ravel(),
                             np.asarray(train_noise, dtype=np.float64).ravel(), gradients)
    with blas_threads(blas_threads_limit):
        return _condition(geometry, kernel_params, obs, float(jitter), max_exact_points, rank_tolerance, max_rank,
                          hyperparameters_optimized)
