"""GPIS regression (gpis_grasp_ros.core.gpis): eqs. 1-2, hyperparameters, sampling, gradients, approximation."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from gpis_grasp_ros.core import gpis as gp
from gpis_grasp_ros.core.gpis import (
    GpisParams,
    GpisPosterior,
    KernelParams,
    com_spread,
    fit_gpis,
    gradient_observations,
    hyperparameters,
    posterior_from_data,
)
from gpis_grasp_ros.core.gpis.likelihood import _LikelihoodWorkspace
from gpis_grasp_ros.core.gpis.observations import _Observations
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.pipeline import posterior_from_grids
from gpis_grasp_ros.core.sdf import signed_distance

VALUE_ONLY = dict(gradient_observations=False)

NOISE = (0.5e-3) ** 2  # (0.5 mm)^2, a 10-frame Carmine average at 0.7 m


def _disc_grid(m: int = 25, size: float = 0.12, radius: float = 0.035):
    g = GridGeometry(-size / 2, -size / 2, size / m, m, m, z=0.7, frame_id='cam')
    c = g.cell_centers()
    true = np.hypot(c[..., 0], c[..., 1]) - radius
    return g, true, signed_distance(true < 0, g.resolution)


def _reference_posterior(g: GridGeometry, kp: KernelParams, xy: np.ndarray, y: np.ndarray, noise: np.ndarray):
    """Dense textbook GPR (eqs. 1 and 2 with the full covariance), independent of the module."""
    test = g.cell_centers().reshape(-1, 2)

    def k(a, b):
        d2 = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
        return kp.signal_variance * np.exp(-0.5 * d2 / kp.length_scale ** 2)

    a = k(xy, xy) + np.diag(noise)
    ks = k(test, xy)
    mean = kp.prior_mean + ks @ np.linalg.solve(a, y - kp.prior_mean)
    cov = k(test, test) - ks @ np.linalg.solve(a, ks.T)
    return mean.reshape(g.shape), cov


def _joint_kernel(kp: KernelParams, a: np.ndarray, ta: np.ndarray, b: np.ndarray, tb: np.ndarray) -> np.ndarray:
    """Textbook joint covariance of values (type 0) and gradient components (1: d/dx, 2: d/dy).

    With k = C exp(-|x - x'|^2 / (2 l^2)) and r = x - x':  cov(f, f) = k,
    cov(f(x), d f(x') / d x'_j) = k r_j / l^2,  cov(d f(x) / d x_i, f(x')) = -k r_i / l^2,
    cov(d f(x) / d x_i, d f(x') / d x'_j) = k (delta_ij / l^2 - r_i r_j / l^4)  (Solak et al. 2003).
    """
    ell2 = kp.length_scale ** 2
    r = a[:, None, :] - b[None, :, :]
    k = kp.signal_variance * np.exp(-0.5 * (r ** 2).sum(-1) / ell2)
    out = np.zeros_like(k)
    for i in (0, 1, 2):
        for j in (0, 1, 2):
            blk = np.ix_(ta == i, tb == j)
            kb, rb = k[blk], r[blk]
            if i == 0 and j == 0:
                out[blk] = kb
            elif i == 0:
                out[blk] = kb * rb[..., j - 1] / ell2
            elif j == 0:
                out[blk] = -kb * rb[..., i - 1] / ell2
            else:
                out[blk] = kb * (float(i == j) / ell2 - rb[..., i - 1] * rb[..., j - 1] / ell2 ** 2)
    return out


def _joint_reference(g: GridGeometry, kp: KernelParams, xy, kind, y, noise):
    """Dense GPR with value and gradient observations → grid mean, covariance, mean gradient."""
    test = g.cell_centers().reshape(-1, 2)
    t0 = np.zeros(len(test), int)
    a = _joint_kernel(kp, xy, kind, xy, kind) + np.diag(noise)
    resid = y - np.where(kind == 0, kp.prior_mean, 0.0)
    ks = _joint_kernel(kp, test, t0, xy, kind)
    mean = kp.prior_mean + ks @ np.linalg.solve(a, resid)
    cov = _joint_kernel(kp, test, t0, test, t0) - ks @ np.linalg.solve(a, ks.T)
    grad = np.stack([_joint_kernel(kp, test, np.full(len(test), t), xy, kind) @ np.linalg.solve(a, resid)
                     for t in (1, 2)], axis=-1)
    return mean.reshape(g.shape), cov, grad.reshape(*g.shape, 2)


def _all_observations(post: GpisPosterior):
    kind = np.concatenate([np.zeros(len(post.train_y), int), 1 + np.asarray(post.train_grad_axis)])
    return (np.vstack([post.train_xy, post.train_grad_xy]), kind, np.concatenate([post.train_y, post.train_grad]),
            np.concatenate([post.train_noise, post.train_grad_noise]))


@pytest.fixture(scope='module')
def disc_full():
    g, true, sdf = _disc_grid()
    post = fit_gpis(sdf, np.full(g.shape, NOISE), np.ones(g.shape, bool), g, GpisParams())
    return g, true, sdf, post


@pytest.fixture(scope='module')
def disc_sector():
    g, true, sdf = _disc_grid()
    c = g.cell_centers()
    ang, r = np.arctan2(c[..., 1], c[..., 0]), np.hypot(c[..., 0], c[..., 1])
    sector = (ang > 0) & (ang < np.pi / 2) & (r > 0.5 * 0.035)  # a quadrant without data, out to the grid edge
    post = fit_gpis(sdf, np.full(g.shape, NOISE), ~sector, g, GpisParams())
    return g, true, sdf, sector, post


def test_contract_fields(disc_full):
    g, _, _, post = disc_full
    n = g.width * g.height
    assert post.mean.shape == g.shape and post.variance.shape == g.shape
    assert post.gradient.shape == (*g.shape, 2)
    assert post.cov_factor.shape[0] == n and 1 <= post.cov_factor.shape[1] <= n
    assert post.train_xy.shape == (n, 2) and post.train_y.shape == (n,) and post.train_noise.shape == (n,)
    # gradient observations: both components at every cell whose two neighbours are in the grid
    k = post.train_grad.size
    assert k == 2 * g.height * (g.width - 2) and post.train_grad_xy.shape == (k, 2)
    assert post.train_grad_axis.shape == (k,) and post.train_grad_noise.shape == (k,)
    assert np.all(post.train_grad_noise >= 0.01) and post.alpha.shape == (n + k,)
    assert post.hyperparameters_optimized and post.approximation == 'exact'
    assert post.hyperparameter_fit is not None and post.hyperparameter_fit.ok
    assert post.bound_hits == post.hyperparameter_fit.bound_hits
    assert post.params.prior_mean < 0
    assert np.isfinite(post.log_marginal_likelihood)
    for arr in (post.mean, post.variance, post.gradient, post.cov_factor):
        assert arr.dtype == np.float64 and np.all(np.isfinite(arr))


def test_fully_observed_disc_zero_level_set_and_small_variance(disc_full):
    g, true, _, post = disc_full
    # the zero level set is within one cell of the true circle: the sign is right beyond one cell
    far = np.abs(true) > g.resolution
    assert np.all(np.sign(post.mean[far]) == np.sign(true[far]))
    # and every cell the mean calls "surface" (a sign change to a neighbour) is within a cell of it
    flips = np.zeros(g.shape, bool)
    flips[:, :-1] |= np.sign(post.mean[:, :-1]) != np.sign(post.mean[:, 1:])
    flips[:-1, :] |= np.sign(post.mean[:-1, :]) != np.sign(post.mean[1:, :])
    assert np.max(np.abs(true[flips])) <= g.resolution
    # observed everywhere with 0.5 mm noise: the posterior std cannot exceed the noise std
    assert np.sqrt(post.variance.max()) <= math.sqrt(NOISE)
    # shape uncertainty is negligible: the centre of mass hardly moves (condition 1)
    assert com_spread(post, 300, np.random.default_rng(1)) < 0.1 * g.resolution


def test_missing_sector_is_uncertain_and_leans_to_object(disc_sector):
    g, true, sdf, sector, post = disc_sector
    ratio = post.variance[sector].mean() / np.median(post.variance[~sector])
    assert ratio > 100.0
    # without data the mean reverts to the negative prior mean: below the true SDF and the observed-style SDF
    assert np.mean(post.mean[sector] - true[sector]) < -0.002
    far = sector & (true > 0.02)  # > 2 cm outside the disc, far from any data
    assert far.sum() > 5
    assert np.mean(post.mean[far] - sdf[far]) < -0.005
    full = fit_gpis(sdf, np.full(g.shape, NOISE), np.ones(g.shape, bool), g,
                    GpisParams(optimize_hyperparameters=False))
    assert com_spread(post, 300, np.random.default_rng(2)) > com_spread(full, 300, np.random.default_rng(2))


def test_matches_textbook_gpr_with_missing_cells():
    g, _, sdf = _disc_grid(m=14)
    mask = np.ones(g.shape, bool)
    mask[2:6, 8:13] = False
    noise = np.full(g.shape, NOISE)
    noise[9:12, 2:5] = 4e-5  # a noisier patch
    kp = KernelParams(6e-4, 0.02, -0.01)
    params = GpisParams(optimize_hyperparameters=False, signal_variance=kp.signal_variance,
                        length_scale=kp.length_scale, prior_mean=kp.prior_mean, jitter=0.0, rank_tolerance=1e-14,
                        **VALUE_ONLY)
    post = fit_gpis(sdf, noise, mask, g, params)
    assert post.train_grad.size == 0
    mean, cov = _reference_posterior(g, kp, g.cell_centers()[mask], sdf[mask], noise[mask])
    assert np.max(np.abs(post.mean - mean)) < 1e-9
    assert np.max(np.abs(post.variance - np.diag(cov).reshape(g.shape))) < 1e-12
    # joint covariance factor: Sigma ~= L L^T up to the basis truncation (1e-10 of C)
    lcov = post.cov_factor @ post.cov_factor.T
    assert np.max(np.abs(lcov - cov)) < 1e-9 * kp.signal_variance


@pytest.mark.parametrize('max_exact', [2500, 0])
def test_gradient_observations_match_dense_joint_kernel(max_exact):
    """Values + gradient observations (Solak et al.) against a dense textbook joint GP, exact and large-grid path."""
    g, _, sdf = _disc_grid(m=14)
    mask = np.ones(g.shape, bool)
    mask[2:6, 8:13] = False
    noise = np.full(g.shape, NOISE)
    noise[9:12, 2:5] = 4e-5  # a noisier patch: its gradients get the propagated noise
    kp = KernelParams(6e-4, 0.02, -0.01)
    params = GpisParams(optimize_hyperparameters=False, signal_variance=kp.signal_variance,
                        length_scale=kp.length_scale, prior_mean=kp.prior_mean, jitter=0.0,
                        max_exact_points=max_exact, rank_tolerance=1e-14)
    post = fit_gpis(sdf, noise, mask, g, params)
    assert post.approximation == ('exact' if max_exact else 'reduced_rank')
    mean, cov, grad = _joint_reference(g, kp, *_all_observations(post))
    assert np.max(np.abs(post.mean - mean)) <= 1e-8
    assert np.max(np.abs(post.variance - np.diag(cov).reshape(g.shape))) <= 1e-8 * kp.signal_variance
    assert np.max(np.abs(post.gradient - grad)) <= 1e-8
    assert np.max(np.abs(post.cov_factor @ post.cov_factor.T - cov)) <= 1e-8 * kp.signal_variance
    # off-grid evaluation agrees with the grid fields
    centres = g.cell_centers()
    assert np.max(np.abs(post.predict_mean(centres) - mean)) <= 1e-8
    assert np.max(np.abs(post.predict_gradient(centres) - grad)) <= 1e-8


def test_gradient_observations_property_random_hyperparameters():
    """Over random grids, masks, noise and hyperparameters the joint posterior equals the dense reference."""
    rng = np.random.default_rng(11)
    ranks = []
    for case in range(12):
        m = int(rng.integers(6, 11))
        res = float(rng.uniform(0.003, 0.01))
        g = GridGeometry(*rng.uniform(-0.05, 0.0, 2), res, m, int(rng.integers(6, 11)))
        centres = g.cell_centers()
        true = np.hypot(*(centres - centres.reshape(-1, 2).mean(0) - rng.uniform(-res, res, 2)).transpose(2, 0, 1))
        sdf = signed_distance(true < rng.uniform(0.2, 0.4) * m * res, g.resolution)
        mask = rng.random(g.shape) > 0.25
        noise = np.exp(rng.uniform(np.log(1e-7), np.log(1e-4), g.shape))
        kp = KernelParams(float(np.exp(rng.uniform(np.log(1e-5), np.log(1e-3)))),
                          float(rng.uniform(0.8, 4.0)) * res, float(rng.uniform(-0.02, 0.0)))
        params = GpisParams(optimize_hyperparameters=False, signal_variance=kp.signal_variance,
                            length_scale=kp.length_scale, prior_mean=kp.prior_mean, jitter=0.0,
                            gradient_noise_variance=float(rng.uniform(1e-3, 0.1)), rank_tolerance=1e-14)
        post = fit_gpis(sdf, noise, mask, g, params)
        assert post.train_grad.size > 0, case
        mean, cov, grad = _joint_reference(g, kp, *_all_observations(post))
        assert np.max(np.abs(post.mean - mean)) <= 1e-8, case
        assert np.max(np.abs(post.variance - np.diag(cov).reshape(g.shape))) <= 1e-8 * kp.signal_variance, case
        assert np.max(np.abs(post.gradient - grad)) <= 1e-8 * max(1.0, np.abs(grad).max()), case
        assert np.max(np.abs(post.cov_factor @ post.cov_factor.T - cov)) <= 1e-8 * kp.signal_variance, case
        # the default tolerance (modes of prior variance below 1e-10 of the largest dropped): fewer modes, and
        # the posterior within nanometres of the exact one
        default = fit_gpis(sdf, noise, mask, g, dataclasses.replace(params, rank_tolerance=GpisParams.rank_tolerance))
        assert default.rank <= post.rank, case
        assert np.max(np.abs(default.mean - mean)) <= 1e-8, case
        assert np.max(np.abs(default.variance - np.diag(cov).reshape(g.shape))) <= 1e-8 * kp.signal_variance, case
        assert np.max(np.abs(default.gradient - grad)) <= 1e-6 * max(1.0, np.abs(grad).max()), case
        assert np.max(np.abs(default.cov_factor @ default.cov_factor.T - cov)) <= 1e-8 * kp.signal_variance, case
        ranks.append((post.rank, default.rank))
    assert sum(d < e for e, d in ranks) >= 8  # the tolerance drops modes on most grids


def test_gradient_observation_noise_model():
    g, true, sdf = _disc_grid(m=25)
    noise = np.full(g.shape, NOISE)
    noise[10, :] = 1e-4  # one noisy row: its neighbours' y-differences carry the propagated noise
    mask = np.ones(g.shape, bool)
    mask[3, 3] = False
    xy, axis, value, var = gradient_observations(sdf, noise, mask, g, 0.01)
    res = g.resolution
    cols = np.rint((xy[:, 0] - g.origin_x) / res - 0.5).astype(int)
    rows = np.rint((xy[:, 1] - g.origin_y) / res - 0.5).astype(int)
    # central differences of the SDF, only where the cell and both neighbours are training cells
    fx = (sdf[rows, np.minimum(cols + 1, 24)] - sdf[rows, np.maximum(cols - 1, 0)]) / (2 * res)
    fy = (sdf[np.minimum(rows + 1, 24), cols] - sdf[np.maximum(rows - 1, 0), cols]) / (2 * res)
    np.testing.assert_allclose(value, np.where(axis == 0, fx, fy), atol=1e-12)
    assert not np.any((rows == 3) & (np.abs(cols - 3) <= 1) & (axis == 0))
    assert not np.any((cols == 3) & (np.abs(rows - 3) <= 1) & (axis == 1))
    assert np.all(np.where(axis == 0, (cols > 0) & (cols < 24), (rows > 0) & (rows < 24)))
    # noise: g0 + kink term + propagated value noise
    above = (axis == 1) & ((rows == 9) | (rows == 11)) & (np.abs(xy[:, 0]) > 0.045)
    assert above.sum() > 4
    np.testing.assert_allclose(var[above], 0.01 + (1e-4 + NOISE) / (4 * res ** 2), rtol=0.05)
    # away from the disc centre (the medial point) the EDT gradient approximates the true one
    r = np.hypot(xy[:, 0], xy[:, 1])
    true_grad = np.where(axis == 0, xy[:, 0], xy[:, 1]) / np.maximum(r, 1e-12)
    far = (r > 0.015) & (var < 0.02)
    assert far.sum() > 500
    assert np.sqrt(np.mean((value[far] - true_grad[far]) ** 2)) < 0.15
    # the medial point has |g| far from 1: its components get a large noise
    centre = r < 0.6 * res
    assert np.all(var[centre] > 0.2)


def test_joint_samples_match_posterior_covariance():
    g, _, sdf = _disc_grid(m=12)
    mask = np.ones(g.shape, bool)
    mask[1:5, 6:11] = False  # missing block: strongly correlated, high-variance cells
    kp = KernelParams(5e-4, 0.018, -0.01)
    post = fit_gpis(sdf, np.full(g.shape, NOISE), mask, g, GpisParams(
        optimize_hyperparameters=False, signal_variance=kp.signal_variance, length_scale=kp.length_scale, jitter=0.0))
    assert post.train_grad.size > 0  # joint value / gradient posterior
    mean, cov, _ = _joint_reference(g, kp, *_all_observations(post))
    n = 5000
    samples = post.sample(n, np.random.default_rng(0)).reshape(n, -1)
    # Entry (i, j) of a sample covariance of n Gaussian draws has standard deviation
    # sqrt((S_ij^2 + S_ii S_jj) / n) <= sqrt(2 / n) s_i s_j, i.e. <= 0.02 s_i s_j for n = 5000.
    # The maximum over the 144^2 / 2 distinct entries of such (correlated) errors stays below
    # ~4.5 standard deviations, so 6 x sqrt(2 / n) = 0.12 is a safe bound on the normalised error.
    emp = np.cov(samples, rowvar=False)
    sd = np.sqrt(np.diag(cov))
    normalised = np.abs(emp - cov) / np.outer(sd, sd)
    assert normalised.max() < 6 * math.sqrt(2 / n)
    # the mean of the samples: standard error s_i / sqrt(n); 5 standard errors
    assert np.all(np.abs(samples.mean(0) - mean.ravel()) < 5 * sd / math.sqrt(n))


def test_mean_gradient_matches_finite_differences():
    g, _, sdf = _disc_grid(m=20)
    mask = np.ones(g.shape, bool)
    mask[12:18, 3:9] = False
    post = fit_gpis(sdf, np.full(g.shape, NOISE), mask, g,
                    GpisParams(optimize_hyperparameters=False, signal_variance=5e-4, length_scale=0.02))
    rng = np.random.default_rng(3)
    pts = rng.uniform(-0.05, 0.05, size=(40, 2))
    h = 1e-6
    fd = np.stack([(post.predict_mean(pts + [h, 0]) - post.predict_mean(pts - [h, 0])) / (2 * h),
                   (post.predict_mean(pts + [0, h]) - post.predict_mean(pts - [0, h])) / (2 * h)], axis=-1)
    grad = post.predict_gradient(pts)
    assert np.max(np.abs(grad - fd)) < 1e-5 * max(1.0, np.abs(fd).max())
    # the grid fields agree with the point-wise predictions at the cell centres
    centres = g.cell_centers()
    assert np.allclose(post.predict_mean(centres), post.mean, atol=1e-12)
    assert np.allclose(post.predict_gradient(centres), post.gradient, atol=1e-10)
    # an SDF has |grad| ~ 1 near the surface
    near = np.abs(post.mean) < g.resolution
    assert np.all(np.abs(np.linalg.norm(post.gradient[near], axis=-1) - 1.0) < 0.35)


def _joint_draw(g: GridGeometry, c: float, ell: float, prior: float, noise: float, grad_noise: float,
                rng: np.random.Generator):
    """Values and both gradient components at every cell, drawn jointly from the SE prior, plus noise."""
    xy = g.cell_centers().reshape(-1, 2)
    n = len(xy)
    pts = np.vstack([xy, xy, xy])
    kind = np.repeat([0, 1, 2], n)
    k = _joint_kernel(KernelParams(c, ell, prior), pts, kind, pts, kind)
    with gp.blas_threads(1):  # one BLAS thread: predictable on a loaded machine
        lam, u = np.linalg.eigh(k)
    f = u @ (np.sqrt(np.clip(lam, 0, None)) * rng.standard_normal(3 * n))
    noise_all = np.where(kind == 0, noise, grad_noise)
    y = f + np.where(kind == 0, prior, 0.0) + np.sqrt(noise_all) * rng.standard_normal(3 * n)
    return _Observations.build(xy, y[:n], np.full(n, noise), pts[n:], kind[n:] - 1, y[n:], noise_all[n:])


@pytest.mark.parametrize('ell_cells', [1.5, 2.5, 4.0])
def test_maximum_likelihood_recovers_a_known_length_scale(ell_cells):
    """ML on a joint value/gradient draw of a known GP recovers l within 20 % (fixed seed)."""
    m = 16
    g = GridGeometry(0.0, 0.0, 0.12 / m, m, m)
    c_true, l_true, prior = 4e-4, ell_cells * g.resolution, -0.01
    obs = _joint_draw(g, c_true, l_true, prior, 1e-7, 1e-3, np.random.default_rng(int(ell_cells * 10)))
    params = GpisParams(prior_mean=prior, length_scale_max_extent=1.0)
    fit = gp.fit_hyperparameters(g, obs, params)
    assert fit.ok and fit.bound_hits == () and fit.cholesky_failures == 0
    assert fit.length_scale == pytest.approx(l_true, rel=0.2)
    assert fit.signal_variance == pytest.approx(c_true, rel=0.5)


def test_hyperparameters_recovered_from_a_known_gp_values_only():
    m = 24
    g = GridGeometry(0.0, 0.0, 0.15 / m, m, m)
    c_true, l_true, prior, noise = 4e-4, 0.015, -0.01, 1e-7
    xy = g.cell_centers().reshape(-1, 2)
    d2 = ((xy[:, None] - xy[None]) ** 2).sum(-1)
    k = c_true * np.exp(-0.5 * d2 / l_true ** 2) + 1e-12 * np.eye(m * m)
    rng = np.random.default_rng(0)
    f = prior + np.linalg.cholesky(k) @ rng.standard_normal(m * m) + math.sqrt(noise) * rng.standard_normal(m * m)
    # the value-only GP, no search band (a GP draw is not an SDF): this checks the ML machinery
    post = fit_gpis(f.reshape(m, m), np.full((m, m), noise), np.ones((m, m), bool), g,
                    GpisParams(prior_mean=prior, search_band_cells=None, max_opt_points=600, **VALUE_ONLY))
    assert post.params.signal_variance == pytest.approx(c_true, rel=0.3)
    assert post.params.length_scale == pytest.approx(l_true, rel=0.2)
    assert post.bound_hits == ()
    # the fixed-hyperparameter path keeps the given values
    fixed = fit_gpis(f.reshape(m, m), np.full((m, m), noise), np.ones((m, m), bool), g,
                     GpisParams(prior_mean=prior, optimize_hyperparameters=False, signal_variance=1e-3,
                                length_scale=0.02, **VALUE_ONLY))
    assert (fixed.params.signal_variance, fixed.params.length_scale) == (1e-3, 0.02)
    assert not fixed.hyperparameters_optimized and fixed.hyperparameter_fit is None and fixed.bound_hits == ()
    assert post.log_marginal_likelihood > fixed.log_marginal_likelihood


def test_binding_bound_is_logged_and_exposed(caplog):
    m = 12
    g = GridGeometry(0.0, 0.0, 0.12 / m, m, m)
    obs = _joint_draw(g, 4e-4, 4.0 * g.resolution, -0.01, 1e-7, 1e-3, np.random.default_rng(3))
    tight = GpisParams(prior_mean=-0.01, length_scale_max_extent=2.0 / m)  # l <= 2 cells < 4 cells
    with caplog.at_level('WARNING', logger='gpis_grasp_ros.core.gpis'):
        fit = gp.fit_hyperparameters(g, obs, tight)
    assert fit.bound_hits == ('length_scale_upper',)
    assert fit.length_scale == pytest.approx(2.0 * g.resolution, rel=1e-6)
    assert any('length_scale_upper' in r.getMessage() for r in caplog.records)
    # and on the posterior built by fit_gpis
    sdf = signed_distance(np.hypot(*(g.cell_centers() - 0.06).transpose(2, 0, 1)) < 0.03, g.resolution)
    post = fit_gpis(sdf, np.full(g.shape, NOISE), np.ones(g.shape, bool), g,
                    GpisParams(length_scale_max_extent=1.2 / m))  # l <= 1.2 cells
    assert 'length_scale_upper' in post.bound_hits
    lo, hi = gp.hyperparameter_bounds(g, GpisParams())
    assert hi[0] == pytest.approx(g.resolution) and hi[1] == pytest.approx(0.12 / 6)


def _thin_bar_scene(m: int = 25) -> tuple[GridGeometry, np.ndarray, np.ndarray, np.ndarray]:
    """A one-cell-wide diagonal bar (like the shipped nail B) with Carmine-like noise on a 25 x 25 grid."""
    g = GridGeometry(0.0, 0.0, 0.003, m, m)
    rows, cols = np.indices(g.shape)
    bar = (np.abs(rows - cols) <= 0) & (rows > 3) & (rows < m - 4)
    sdf = signed_distance(bar, g.resolution)
    noise = np.full(g.shape, (0.0015) ** 2)
    return g, sdf, bar, noise


def test_thickness_bound_keeps_a_one_cell_wide_object():
    """l <= 3 r_in (module docstring, Thickness bound): a one-cell bar stays in the mean shape, and the
    bound is reported as binding; r_in = 0.5 cell gives l = 1.5 cells."""
    g, sdf, bar, noise = _thin_bar_scene()
    post = fit_gpis(sdf, noise, np.ones(g.shape, bool), g, GpisParams())
    assert 'length_scale_upper' in post.bound_hits
    assert post.params.length_scale == pytest.approx(1.5 * g.resolution, rel=1e-6)
    kept = np.count_nonzero((post.mean < 0) & bar) / np.count_nonzero(bar)
    assert kept > 0.9
    _, (_, hi) = gp.hyperparameter_bounds(g, GpisParams(), inscribed_radius_m=0.5 * g.resolution)
    assert hi == pytest.approx(1.5 * g.resolution)
    _, (_, hi) = gp.hyperparameter_bounds(g, GpisParams(length_scale_max_thickness=None), 0.5 * g.resolution)
    assert hi == pytest.approx(max(g.size_m) / 6)


def test_a_singular_fisher_information_stops_the_search_with_a_warning(caplog, monkeypatch):
    """No scoring direction: the search keeps the (C-stepped) start, says so, and it is still a likelihood fit."""
    m = 12
    g = GridGeometry(0.0, 0.0, 0.01, m, m)
    obs = _joint_draw(g, 4e-4, 0.02, -0.01, 1e-7, 1e-3, np.random.default_rng(4))
    params = GpisParams(prior_mean=-0.01, length_scale_max_extent=1.0)
    good = gp.fit_hyperparameters(g, obs, params)
    monkeypatch.setattr(hyperparameters, 'fisher_information', lambda *a: np.zeros((2, 2)))
    with caplog.at_level('WARNING', logger='gpis_grasp_ros.core.gpis'):
        fit = gp.fit_hyperparameters(g, obs, params)
    assert fit.ok and fit.cholesky_failures == 0 and fit.n_starts == 1
    assert fit.n_evaluations < good.n_evaluations and fit.log_likelihood < good.log_likelihood
    assert any('singular Fisher information' in r.getMessage() for r in caplog.records)


def test_cholesky_failures_in_the_search_are_flagged_and_logged(caplog, monkeypatch):
    m = 12
    g = GridGeometry(0.0, 0.0, 0.01, m, m)
    obs = _joint_draw(g, 4e-4, 0.02, -0.01, 1e-7, 1e-3, np.random.default_rng(4))
    real = gp.negative_log_marginal_likelihood

    def failing_beyond(log_theta, *args):  # K + N "not positive definite" for l > 1.8 cm (the optimum: 2 cm)
        if math.exp(log_theta[1]) > 0.018:
            raise np.linalg.LinAlgError('not positive definite')
        return real(log_theta, *args)

    monkeypatch.setattr(hyperparameters, 'negative_log_marginal_likelihood', failing_beyond)
    params = GpisParams(prior_mean=-0.01, length_scale_max_extent=1.0, n_restarts=4, seed=1)
    with caplog.at_level('WARNING', logger='gpis_grasp_ros.core.gpis'):
        fit = gp.fit_hyperparameters(g, obs, params)
    assert fit.ok and fit.cholesky_failures > 0 and fit.length_scale <= 0.018
    assert fit.n_starts == 5  # a failed factorisation: the random starts are searched too
    assert fit.failed_starts >= 1  # seed 1 draws random starts beyond 1.8 cm: they are reported, not used
    assert any('not positive definite' in r.getMessage() for r in caplog.records)
    # every evaluation fails: the start values are kept, flagged and logged as an error
    caplog.clear()
    monkeypatch.setattr(hyperparameters, 'negative_log_marginal_likelihood',
                        lambda *a: (_ for _ in ()).throw(np.linalg.LinAlgError('not positive definite')))
    with caplog.at_level('WARNING', logger='gpis_grasp_ros.core.gpis'):
        fit = gp.fit_hyperparameters(g, obs, params)
    assert not fit.ok and fit.failed_starts == fit.n_starts == 5 and math.isnan(fit.log_likelihood)
    assert fit.bound_hits == ()
    assert any(r.levelname == 'ERROR' and 'every start' in r.getMessage() for r in caplog.records)


def test_negative_log_likelihood_raises_on_singular_matrix_and_has_the_right_gradient():
    g = GridGeometry(0.0, 0.0, 0.01, 8, 8)
    obs = _joint_draw(g, 4e-4, 0.02, -0.01, 1e-7, 1e-3, np.random.default_rng(5))
    kern = _LikelihoodWorkspace(obs)
    resid = obs.y - np.where(obs.kind == 0, -0.01, 0.0)
    theta = np.log([3e-4, 0.017])
    h = 1e-6
    with gp.blas_threads(1):
        f, grad = gp.negative_log_marginal_likelihood(theta, kern, resid, obs.noise)
        fd = [(gp.negative_log_marginal_likelihood(theta + h * e, kern, resid, obs.noise)[0]
               - gp.negative_log_marginal_likelihood(theta - h * e, kern, resid, obs.noise)[0]) / (2 * h)
              for e in np.eye(2)]
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-4)
    same = _Observations.build(np.zeros((2, 2)), np.zeros(2), np.zeros(2))  # two identical noise-free points
    with pytest.raises(np.linalg.LinAlgError):
        gp.negative_log_marginal_likelihood(theta, _LikelihoodWorkspace(same), np.ones(2), np.zeros(2))


@pytest.mark.parametrize('max_exact', [2500, 0])
def test_posterior_from_data_reproduces_fit(max_exact):
    g, _, sdf = _disc_grid(m=20)
    mask = np.ones(g.shape, bool)
    mask[2:7, 11:17] = False
    noise = np.full(g.shape, NOISE)
    params = GpisParams(optimize_hyperparameters=False, max_exact_points=max_exact)
    post = fit_gpis(sdf, noise, mask, g, params)
    assert post.train_grad.size > 0
    again = posterior_from_data(g, post.params, post.train_xy, post.train_y, post.train_noise, post.jitter,
                                train_grad_xy=post.train_grad_xy, train_grad_axis=post.train_grad_axis,
                                train_grad=post.train_grad, train_grad_noise=post.train_grad_noise,
                                max_exact_points=max_exact)
    assert again.approximation == post.approximation == ('exact' if max_exact else 'reduced_rank')
    for name in ('mean', 'variance', 'gradient', 'cov_factor'):
        a, b = getattr(post, name), getattr(again, name)
        assert np.max(np.abs(a - b)) <= 1e-10 * max(1.0, np.abs(a).max()), name


def test_posterior_from_data_off_grid_training_points():
    g, _, _ = _disc_grid(m=12)
    rng = np.random.default_rng(5)
    xy = rng.uniform(-0.05, 0.05, size=(60, 2))
    y = np.hypot(xy[:, 0], xy[:, 1]) - 0.03
    noise = np.full(60, NOISE)
    kp = KernelParams(5e-4, 0.02, -0.01)
    post = posterior_from_data(g, kp, xy, y, noise, 0.0)
    mean, cov = _reference_posterior(g, kp, xy, y, noise)
    assert np.max(np.abs(post.mean - mean)) < 1e-9
    assert np.max(np.abs(post.variance - np.diag(cov).reshape(g.shape))) < 1e-12
    # Off the cell centres the basis is the Nystroem extension, which misses the part of the prior
    # at x that the grid values do not determine (the grid-conditional prior variance, ~1e-4 C for
    # l = 2 cells): the joint covariance factor is then accurate to ~1e-4 C instead of ~1e-10 C.
    assert np.max(np.abs(post.cov_factor @ post.cov_factor.T - cov)) < 1e-3 * kp.signal_variance


def test_reduced_rank_approximation_error_is_bounded():
    g, _, sdf = _disc_grid(m=40)
    mask = np.ones(g.shape, bool)
    mask[5:14, 22:34] = False
    noise = np.full(g.shape, NOISE)
    noise[25:33, 5:15] = 1e-4
    kp = dict(optimize_hyperparameters=False, signal_variance=5e-4, length_scale=0.015)
    exact = fit_gpis(sdf, noise, mask, g, GpisParams(**kp))
    approx = fit_gpis(sdf, noise, mask, g, GpisParams(**kp, max_exact_points=0))
    assert exact.approximation == 'exact' and approx.approximation == 'reduced_rank'
    assert approx.rank < g.width * g.height and approx.truncation < 1e-9
    # measured ~1e-9 m and ~1e-12 m^2; bounds leave two orders of magnitude
    assert np.max(np.abs(approx.mean - exact.mean)) < 1e-7  # m (0.1 micrometre)
    assert np.max(np.abs(approx.variance - exact.variance)) < 1e-3 * exact.variance.max()
    assert np.max(np.abs(approx.gradient - exact.gradient)) < 1e-4
    assert abs(approx.log_marginal_likelihood - exact.log_marginal_likelihood) < 1e-3 * abs(
        exact.log_marginal_likelihood)


def test_rank_capped_on_the_exact_path():
    """A short length scale keeps more modes above the tolerance than max_rank: the basis is capped on the exact
    path too (labelled reduced_rank), close to the uncapped fit in proportion to the dropped prior variance."""
    g, _, sdf = _disc_grid(m=30)
    mask = np.ones(g.shape, bool)
    mask[5:12, 16:26] = False
    noise = np.full(g.shape, NOISE)
    kp = dict(optimize_hyperparameters=False, signal_variance=5e-4, length_scale=1.5 * g.resolution)
    full = fit_gpis(sdf, noise, mask, g, GpisParams(**kp, max_rank=10 ** 6))
    assert full.approximation == 'exact' and full.rank > 1500
    capped = fit_gpis(sdf, noise, mask, g, GpisParams(**kp, max_rank=int(0.6 * full.rank)))
    assert capped.approximation == 'reduced_rank' and capped.rank == int(0.6 * full.rank)
    # measured: 8e-7 of the prior variance dropped, mean within 11 micrometres, variance within 1.1e-5 relative
    assert full.truncation < 1e-9 < capped.truncation < 1e-5
    assert np.max(np.abs(capped.mean - full.mean)) < 1e-4
    assert np.max(np.abs(capped.variance - full.variance)) < 1e-3 * full.variance.max()
    ample = fit_gpis(sdf, noise, mask, g, GpisParams(**kp, max_rank=full.rank))  # a cap that does not bind
    assert ample.approximation == 'exact' and np.array_equal(ample.mean, full.mean)


def test_posterior_from_grids_excludes_missing_cells():
    g, true, _ = _disc_grid(m=16)
    missing = np.zeros(g.shape, bool)
    missing[6:9, 6:9] = True
    occupancy = np.where(missing, -1, np.where(true < 0, 100, 0))
    noise = np.where(missing, np.nan, NOISE)
    post = posterior_from_grids(occupancy, noise, g, GpisParams(optimize_hyperparameters=False))
    assert isinstance(post, GpisPosterior)
    assert post.train_xy.shape[0] == g.width * g.height - missing.sum()
    assert np.all(post.mean[missing] < 0)


def test_invalid_inputs_raise():
    g, _, sdf = _disc_grid(m=10)
    noise = np.full(g.shape, NOISE)
    with pytest.raises(ValueError, match='grid shape'):
        fit_gpis(sdf[:-1], noise, np.ones(g.shape, bool), g)
    with pytest.raises(ValueError, match='no cell'):
        fit_gpis(sdf, noise, np.zeros(g.shape, bool), g)
    bad = noise.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match='non-finite'):
        fit_gpis(sdf, bad, np.ones(g.shape, bool), g)
    with pytest.raises(ValueError, match='noise'):
        posterior_from_data(g, KernelParams(1e-3, 0.01, -0.01), np.zeros((1, 2)), np.zeros(1), np.zeros(1), 0.0)
    with pytest.raises(ValueError, match='jitter'):
        GpisParams(jitter=-1.0)
    hand_built = GpisPosterior(g, sdf, np.zeros(g.shape), np.zeros((*g.shape, 2)), np.zeros((100, 1)),
                               KernelParams(1e-3, 0.01, -0.01))
    with pytest.raises(ValueError, match='training data'):
        hand_built.predict_mean(np.zeros((1, 2)))


# ----------------------------------------------------------------------------------------------
# noise map -> GPIS: unobserved parts are uncertain, not confidently absent

def _rendered_scene(seed: int, trans_width: float = 0.02, n_frames: int = 6, size: int = 200):
    """Top-down Carmine-like frames: an opaque box (depth + colour) with a transparent part (colour only).

    Box 5 x 4 cm, 3 cm tall, at x in [-0.04, 0.01]; transparent part ``trans_width`` x 4 cm to its right:
    the sensor sees the table through it (depth = table) and a faint tint in colour (Object A's
    dispenser). Returns frames, intrinsics and the true SDF (m) as a function of camera (x, y).
    """
    from gpis_grasp_ros.core.noise_model import axial_sigma, quantise
    from gpis_grasp_ros.core.sensing import CameraIntrinsics

    table_z, table_rgb = 0.7, np.array([120.0, 120.0, 120.0])
    rng = np.random.default_rng(seed)
    intr = CameraIntrinsics(570.0, 570.0, (size - 1) / 2, (size - 1) / 2, size, size)
    u, v = np.meshgrid(np.arange(size), np.arange(size))
    x, y = (u - intr.cx) * table_z / intr.fx, (v - intr.cy) * table_z / intr.fy
    box = (x >= -0.04) & (x < 0.01) & (np.abs(y) < 0.02)
    trans = (x >= 0.01) & (x < 0.01 + trans_width) & (np.abs(y) < 0.02)
    colour = np.broadcast_to(table_rgb, (size, size, 3)).copy()
    colour[box] = (200, 60, 50)
    colour[trans] = table_rgb + (0, 30, 40)
    z_true = np.where(box, table_z - 0.03, table_z)
    depth = np.array([quantise(z_true + rng.standard_normal(z_true.shape) * axial_sigma(z_true))
                      for _ in range(n_frames)])
    rgb = np.array([np.clip(colour + rng.normal(0.0, 3.0, colour.shape), 0, 255).astype(np.uint8)
                    for _ in range(n_frames)])

    def true_sdf(px: np.ndarray, py: np.ndarray) -> np.ndarray:  # union of two axis-aligned boxes
        def rect(x0, x1, y0, y1):
            dx = np.maximum(x0 - px, px - x1)
            dy = np.maximum(y0 - py, py - y1)
            return np.hypot(np.maximum(dx, 0), np.maximum(dy, 0)) + np.minimum(np.maximum(dx, dy), 0)
        return np.minimum(rect(-0.04, 0.01, -0.02, 0.02), rect(0.01, 0.01 + trans_width, -0.02, 0.02))

    return rgb, depth, intr, true_sdf, (0.01, 0.01 + trans_width)


def _posterior_and_truth(seed: int, **kw):
    from gpis_grasp_ros.core.pipeline import posterior_from_grids, publishable_grids
    from gpis_grasp_ros.core.sensing import SensingParams, segment_frames
    from gpis_grasp_ros.core.sensing.params import PAPER_GRID_SIZE

    rgb, depth, intr, true_sdf, trans_x = _rendered_scene(seed, **kw)
    result = segment_frames(rgb, depth, intr, SensingParams(grid_size=PAPER_GRID_SIZE))  # the thresholds' grid
    post = posterior_from_grids(*publishable_grids(result))
    p = result.geometry.to_sensor(result.geometry.cell_centers(), 0.0)  # cell centres in the camera frame
    return post, result, true_sdf(p[..., 0], p[..., 1]), p, trans_x


@pytest.mark.parametrize('seed', [0, 1])
def test_transparent_part_is_uncertain_and_covered(seed):
    """The paper's Fig. 4 case (Object A): a part seen in colour only must not be confidently free.

    Its cells are unknown (not trained, object in the SDF, section III-B), so the posterior at the
    part's true surface is uncertain (sigma >= 0.2 x the prior sigma there) and its 95 % interval
    covers the true SDF at >= 90 % of the near-surface cells of the part; the part stays in the mean
    shape.
    """
    post, result, truth, p, (x0, x1) = _posterior_and_truth(seed)
    res = post.geometry.resolution
    part = (p[..., 0] > x0 + res) & (np.abs(truth) < 2 * res)  # near the part's surface, off the box
    assert part.sum() >= 15
    assert result.uncertain[(p[..., 0] > x0 + res) & (p[..., 0] < x1 - res) & (np.abs(p[..., 1]) < 0.015)].all()
    sd = np.sqrt(post.variance)
    z = (truth - post.mean) / sd
    assert np.mean(np.abs(z[part]) < 1.96) >= 0.9
    assert np.median(sd[part]) >= 0.2 * math.sqrt(post.params.signal_variance)
    inside = (p[..., 0] > x0 + res) & (p[..., 0] < x1 - res) & (np.abs(p[..., 1]) < 0.015)
    assert np.mean(post.mean[inside] < 0) > 0.8  # the part does not vanish from the mean shape


def test_opaque_box_keeps_its_calibrated_mean_shape():
    """Without a transparent part nothing is unknown (a one-cell ring of disagreeing masks is edge noise,
    ``_extended_regions``): every cell is trained and the mean shape matches the box."""
    post, result, truth, p, _ = _posterior_and_truth(3, trans_width=0.0)
    assert result.train_mask.all()
    inside_true, inside_mean = truth < 0, post.mean < 0
    assert np.count_nonzero(inside_true & inside_mean) / np.count_nonzero(inside_true | inside_mean) > 0.85


def test_unknown_cells_are_object_and_untrained_on_both_paths():
    """The sensing result's own grids and the published ones (publishable_grids: int8 occupancy, float32 noise)
    train on the same cells and count every unknown cell as object (-1 in the published grid)."""
    from gpis_grasp_ros.core.pipeline import publishable_grids
    from gpis_grasp_ros.core.sensing import segment_frames

    rgb, depth, intr, _, _ = _rendered_scene(4)
    result = segment_frames(rgb, depth, intr)
    occ, noise, geometry = publishable_grids(result)
    unknown = ~result.train_mask
    assert unknown.sum() >= 10 and np.all(occ[unknown] == -1) and np.all(np.isnan(noise[unknown]))
    assert np.mean(result.occupancy[unknown & ~result.missing] < 0.5) > 0.75  # free in the blend, yet unknown
    fixed = GpisParams(optimize_hyperparameters=False, signal_variance=1e-4, length_scale=0.01)
    own_occ = np.where(unknown, -1, np.where(result.occupancy >= 0.5, 100, 0))
    a = posterior_from_grids(own_occ, np.where(unknown, np.nan, result.noise_variance), result.geometry, fixed)
    b = posterior_from_grids(occ, noise, geometry, fixed)
    assert a.train_y.size == b.train_y.size == int(result.train_mask.sum())
    np.testing.assert_allclose(a.mean, b.mean, atol=1e-6)
    np.testing.assert_allclose(np.sqrt(a.variance), np.sqrt(b.variance), atol=1e-6)


def test_extended_regions_drop_thin_rings_and_keep_blocks():
    from gpis_grasp_ros.core.sensing.noise_map import _extended_regions

    mask = np.zeros((20, 20), dtype=bool)
    mask[2:9, 2] = mask[2:9, 8] = mask[2, 2:9] = mask[8, 2:9] = True  # one-cell ring: edge noise
    mask[12:15, 12:18] = True  # 3 x 6 block: an unseen part
    mask[11, 11] = True  # touching the block diagonally: same component
    mask[17:19, 2:10] = True  # two-cell band: edge noise
    out = _extended_regions(mask)
    expected = np.zeros_like(mask)
    expected[12:15, 12:18] = True
    expected[11, 11] = True
    assert np.array_equal(out, expected)
    assert not _extended_regions(np.zeros((5, 5), dtype=bool)).any()


def test_foreign_missing_fraction_counts_pixels_per_cell():
    from gpis_grasp_ros.core.sensing.noise_map import _foreign_missing_fraction

    rng = np.random.default_rng(0)
    m, n = 4, 4000
    row, col = rng.integers(-1, m + 1, n).astype(float), rng.integers(-1, m + 1, n).astype(float)
    in_grid = (row >= 0) & (row < m) & (col >= 0) & (col < m)
    foreign = rng.random(n) < np.where(row == 1, 0.9, 0.1)  # row 1 of the grid is mostly no-return
    informative = in_grid & ~foreign & (rng.random(n) < 0.8)
    frac = _foreign_missing_fraction(row, col, in_grid, informative, foreign, m)
    for r in range(m):
        for c in range(m):
            cell = in_grid & (row == r) & (col == c)
            nf, ns = np.count_nonzero(cell & foreign), np.count_nonzero(cell & informative)
            assert frac[r, c] == pytest.approx(nf / (nf + ns) if nf else 0.0)
    assert np.all(frac[1] > 0.8) and np.all(np.delete(frac, 1, axis=0) < 0.3)
