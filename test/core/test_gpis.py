"""GPIS regression (gpis_grasp_ros.core.gpis): eqs. 1-2, hyperparameters, sampling, gradients, approximation."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from gpis_grasp_ros.core.gpis import (
    GpisParams,
    GpisPosterior,
    KernelParams,
    build_gpis,
    com_spread,
    fit_gpis,
    posterior_from_data,
)
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.sdf import signed_distance

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
    assert post.hyperparameters_optimized and post.approximation == 'exact'
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
                        length_scale=kp.length_scale, prior_mean=kp.prior_mean, jitter=0.0)
    post = fit_gpis(sdf, noise, mask, g, params)
    mean, cov = _reference_posterior(g, kp, g.cell_centers()[mask], sdf[mask], noise[mask])
    assert np.max(np.abs(post.mean - mean)) < 1e-9
    assert np.max(np.abs(post.variance - np.diag(cov).reshape(g.shape))) < 1e-12
    # joint covariance factor: Sigma ~= L L^T up to the basis truncation (1e-10 of C)
    lcov = post.cov_factor @ post.cov_factor.T
    assert np.max(np.abs(lcov - cov)) < 1e-9 * kp.signal_variance


def test_joint_samples_match_posterior_covariance():
    g, _, sdf = _disc_grid(m=12)
    mask = np.ones(g.shape, bool)
    mask[1:5, 6:11] = False  # missing block: strongly correlated, high-variance cells
    kp = KernelParams(5e-4, 0.018, -0.01)
    post = fit_gpis(sdf, np.full(g.shape, NOISE), mask, g, GpisParams(
        optimize_hyperparameters=False, signal_variance=kp.signal_variance, length_scale=kp.length_scale, jitter=0.0))
    mean, cov = _reference_posterior(g, kp, g.cell_centers()[mask], sdf[mask], np.full(mask.sum(), NOISE))
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


def test_hyperparameters_recovered_from_a_known_gp():
    m = 24
    g = GridGeometry(0.0, 0.0, 0.15 / m, m, m)
    c_true, l_true, prior, noise = 4e-4, 0.015, -0.01, 1e-7
    xy = g.cell_centers().reshape(-1, 2)
    d2 = ((xy[:, None] - xy[None]) ** 2).sum(-1)
    k = c_true * np.exp(-0.5 * d2 / l_true ** 2) + 1e-12 * np.eye(m * m)
    rng = np.random.default_rng(0)
    f = prior + np.linalg.cholesky(k) @ rng.standard_normal(m * m) + math.sqrt(noise) * rng.standard_normal(m * m)
    # generous bounds: this checks the maximum-likelihood machinery, not the default cap l <= E/12
    post = fit_gpis(f.reshape(m, m), np.full((m, m), noise), np.ones((m, m), bool), g,
                    GpisParams(prior_mean=prior, length_scale_bounds=(1 / 50, 1.0)))
    assert post.params.signal_variance == pytest.approx(c_true, rel=0.3)
    assert post.params.length_scale == pytest.approx(l_true, rel=0.3)
    # the fixed-hyperparameter path keeps the given values
    fixed = fit_gpis(f.reshape(m, m), np.full((m, m), noise), np.ones((m, m), bool), g,
                     GpisParams(prior_mean=prior, optimize_hyperparameters=False, signal_variance=1e-3,
                                length_scale=0.02))
    assert (fixed.params.signal_variance, fixed.params.length_scale) == (1e-3, 0.02)
    assert not fixed.hyperparameters_optimized
    assert post.log_marginal_likelihood > fixed.log_marginal_likelihood
    capped = fit_gpis(f.reshape(m, m), np.full((m, m), noise), np.ones((m, m), bool), g, GpisParams(prior_mean=prior))
    assert capped.params.length_scale == pytest.approx(0.15 / 12, rel=1e-6)  # default cap E/12 < 15 mm binds


@pytest.mark.parametrize('max_exact', [2500, 0])
def test_posterior_from_data_reproduces_fit(max_exact):
    g, _, sdf = _disc_grid(m=20)
    mask = np.ones(g.shape, bool)
    mask[2:7, 11:17] = False
    noise = np.full(g.shape, NOISE)
    params = GpisParams(optimize_hyperparameters=False, max_exact_points=max_exact)
    post = fit_gpis(sdf, noise, mask, g, params)
    again = posterior_from_data(g, post.params, post.train_xy, post.train_y, post.train_noise, post.jitter,
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


def test_build_gpis_from_sensing_result_excludes_missing_cells():
    g, true, _ = _disc_grid(m=16)
    occupancy = (true < 0).astype(float)
    missing = np.zeros(g.shape, bool)
    missing[6:9, 6:9] = True
    occupancy[missing] = 1.0
    res = SimpleNamespace(occupancy=occupancy, noise_variance=np.full(g.shape, NOISE), missing=missing,
                          train_mask=~missing, geometry=g)
    post = build_gpis(res, GpisParams(optimize_hyperparameters=False))
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
