"""GPIS benchmark: fit, joint sampling and GPIS-Blur timings vs scikit-learn (``python -m gpis_grasp_ros.bench gpis``).

Synthetic object on a 14 cm square grid (the same metric scene at every M): a 4 cm disc with a
handle, a specular tip (missing cells, excluded from training) and a transparent strip (SDF
noise 1e-4 m^2); elsewhere the 10-frame Carmine noise (0.45 mm)^2.

The GP is trained on SDF values and SDF gradient components (derivative observations, ~3 observations
per training cell), as :func:`~gpis_grasp_ros.core.gpis.fit_gpis` does by default.

Columns (times are the best of a few repeats, ms):

* fit fixed:  :func:`~gpis_grasp_ros.core.gpis.fit_gpis` with C and l fixed (mean, variance, gradient
  and the joint covariance factor), the default path (exact up to 2500 training cells).
* fit ML:     the same with the maximum-likelihood hyperparameter search.
* 1000 smp:   1000 joint posterior samples (:meth:`GpisPosterior.sample`).
* blur:       GPIS-Blur with 1000 samples.
* value-only: ``fit fixed`` for a GP trained on the SDF values only (``gradient_observations=False``).
* sklearn:    ``GaussianProcessRegressor`` with the same fixed kernel and per-point ``alpha`` on the
  values only (it has no derivative observations), ``fit`` + ``predict(return_std=True)`` on all
  cells, after a warm-up call; speed-up = sklearn / value-only. Every timed call (ours and
  scikit-learn's) runs with the same BLAS thread count (``--blas-threads``, default 1, the fit's own
  default; see :func:`gpis.blas_threads`).
* err:        max |mu - mu_ref| (m) and max |var - var_ref| / max var of our default path and of the
  reduced-rank path (forced with ``max_exact_points=0`` where the default is exact) against a dense
  function-space GP with the joint value/gradient kernel (Cholesky of the 3n x 3n matrix, up to
  ``--dense-max`` observations, i.e. M = 25); above that the reduced-rank path is compared with the
  exact Kronecker path where that is the default (M = 50; the exact path itself matches the dense
  reference to ~1e-12 in ``test_gpis``), and not at all at M = 100.

Second table, the maximum-likelihood fit (min and median ms of ``--ml-repeats`` calls, each
``time.perf_counter`` around the call, ``evals`` = likelihood evaluations):

* cold:       :func:`fit_gpis` with the multi-start search (no previous fit).
* warm:       the same with ``warm_start`` = the cold fit of this scene (a static scene at camera
  rate: the score test keeps the previous C and l, one evaluation).
* drifted:    ``warm_start`` = the cold fit with C x 1.5 and l x 0.85 (the test rejects it and
  the search runs from there alone).
* search:     the search alone (:func:`fit_hyperparameters`), cold / warm.
* sklearn ML: ``GaussianProcessRegressor(...).fit`` with its L-BFGS-B optimiser
  (``n_restarts_optimizer`` = ours, the same bounds and start) on the SDF values of
  ``max_opt_points`` training cells drawn from the same search band: scikit-learn's value-only ML
  fit on a Gram matrix of the size of ours (it has no derivative observations).

``--bags`` adds a table over every shipped bag (bags/*.mcap, bags/head/*.mcap): the cold fit's log
likelihood, warm fits from perturbed previous fits (small: C x 1.05, l x 0.97; large: C x 1.5,
l x 0.85) and the GP-GPIS-OPT P_F (seed 0) on the cold and the warm posteriors, and the reference cold search
(:func:`reference_search`: L-BFGS-B from three starts, the same subset and bounds).
"""

from __future__ import annotations

import argparse
import glob
import logging
import math
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from gpis_grasp_ros.core.blur import gpis_blur
from gpis_grasp_ros.core.gpis import GpisParams, GpisPosterior, HyperparameterFit, blas_threads, fit_gpis
from gpis_grasp_ros.core.gpis.hyperparameters import fit_hyperparameters, hyperparameter_bounds, reference_search
from gpis_grasp_ros.core.gpis.kernel import _cross_joint, _DenseKernel
from gpis_grasp_ros.core.gpis.observations import VALUE, _observations_from, gradient_observations
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.sdf import signed_distance

EXTENT_M = 0.14
BASE_NOISE = (0.45e-3) ** 2
STRIP_NOISE = 1e-4


def synthetic_object(m: int) -> tuple[GridGeometry, np.ndarray, np.ndarray, np.ndarray]:
    """(geometry, sdf, noise, train_mask) of the benchmark object on an m x m grid."""
    g = GridGeometry(-EXTENT_M / 2, -EXTENT_M / 2, EXTENT_M / m, m, m, z=0.7, frame_id='bench')
    c = g.cell_centers()
    x, y = c[..., 0], c[..., 1]
    disc = np.hypot(x + 0.01, y) < 0.04
    handle = (np.abs(y) < 0.008) & (x > 0.0) & (x < 0.05)
    tip = (np.abs(y) < 0.008) & (x >= 0.035) & (x < 0.05)  # specular end of the handle: no depth
    strip = (x < -0.02) & (x > -0.06) & (y > 0.025) & (y < 0.045)  # transparent rim: masks disagree
    occupancy = disc | handle
    noise = np.full(g.shape, BASE_NOISE)
    noise[strip] = STRIP_NOISE
    return g, signed_distance(occupancy, g.resolution), noise, ~tip


def best_of(fn: Callable[[], object], repeats: int) -> tuple[float, object]:
    """Best wall time (ms) of ``repeats`` calls and the last result."""
    best, out = math.inf, None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3, out


def timed(fn: Callable[[], object], repeats: int) -> tuple[float, float, object]:
    """(min ms, median ms, last result) of ``repeats`` calls, ``time.perf_counter`` around each."""
    times, out = [], None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times) * 1e3, float(np.median(times)) * 1e3, out


def drifted(fit: HyperparameterFit, c_factor: float = 1.5, l_factor: float = 0.85) -> HyperparameterFit:
    """A previous fit whose C and l are off by the given factors (the warm start of a drifted scene)."""
    return replace(fit, signal_variance=fit.signal_variance * c_factor, length_scale=fit.length_scale * l_factor)


def sklearn_ml_fit(g: GridGeometry, sdf: np.ndarray, noise: np.ndarray, mask: np.ndarray,
                   params: GpisParams) -> Callable[[], object]:
    """scikit-learn's value-only ML fit on ``max_opt_points`` band cells, same bounds, start and restarts."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel

    (c_lo, c_hi), (l_lo, l_hi) = hyperparameter_bounds(g, params, max(0.0, -float(sdf.min())))
    band = np.flatnonzero(np.abs(sdf[mask]) <= params.search_band_cells * g.resolution)
    rng = np.random.default_rng(params.seed)
    cells = rng.choice(band, min(band.size, params.max_opt_points), replace=False)
    x, y = g.cell_centers()[mask][cells], sdf[mask][cells] - params.prior_mean
    alpha = noise[mask][cells] + params.jitter
    c0 = float(np.clip(np.mean(y ** 2), c_lo, c_hi))
    l0 = float(np.clip(max(g.size_m) / 12.0, l_lo, l_hi))
    kernel = ConstantKernel(c0, (c_lo, c_hi)) * RBF(l0, (l_lo, l_hi))

    def fit() -> object:
        return GaussianProcessRegressor(kernel=kernel, alpha=alpha, n_restarts_optimizer=params.n_restarts,
                                        random_state=params.seed).fit(x, y)
    return fit


def bench_ml(m: int, repeats: int, with_sklearn: bool = True, seed: int = 0) -> dict:
    """One row of the ML-fit table for an m x m grid."""
    g, sdf, noise, mask = synthetic_object(m)
    params = GpisParams(seed=seed)
    fit_gpis(sdf, noise, mask, g, params)  # warm-up (compiled kernels)
    cold = timed(lambda: fit_gpis(sdf, noise, mask, g, params), repeats)
    prev = cold[2].hyperparameter_fit
    warm = timed(lambda: fit_gpis(sdf, noise, mask, g, params, warm_start=prev), repeats)
    drift = timed(lambda: fit_gpis(sdf, noise, mask, g, params, warm_start=drifted(prev)), repeats)
    obs = _observations_from(g.cell_centers()[mask], sdf[mask], noise[mask],
                             gradient_observations(sdf, noise, mask, g, params.gradient_noise_variance))
    eligible = np.abs(sdf[mask]) <= params.search_band_cells * g.resolution
    r_in = max(0.0, -float(sdf.min()))
    s_cold = timed(lambda: fit_hyperparameters(g, obs, params, eligible, r_in), repeats)
    s_warm = timed(lambda: fit_hyperparameters(g, obs, params, eligible, r_in, warm_start=prev), repeats)
    row = dict(m=m, n_obs=prev.n_observations, cold=cold, warm=warm, drift=drift, s_cold=s_cold, s_warm=s_warm,
               sk=(math.nan, math.nan, None))
    if with_sklearn:
        fit = sklearn_ml_fit(g, sdf, noise, mask, params)
        fit()
        row['sk'] = timed(fit, repeats)
    return row


ML_HEADER = (f"{'M':>4} {'sub':>4} | {'cold min/med':>13} {'ev':>3} | {'warm min/med':>13} {'ev':>3} | "
             f"{'drifted min/med':>15} {'ev':>3} | {'search cold':>11} {'warm':>6} | {'sklearn ML min/med':>18}")


def print_ml_row(r: dict) -> None:
    def mm(t: tuple) -> str:
        return f'{t[0]:.0f}/{t[1]:.0f}'
    ev = {k: r[k][2].hyperparameter_fit.n_evaluations for k in ('cold', 'warm', 'drift')}
    print(f"{r['m']:>4} {r['n_obs']:>4} | {mm(r['cold']):>13} {ev['cold']:>3} | {mm(r['warm']):>13} {ev['warm']:>3} | "
          f"{mm(r['drift']):>15} {ev['drift']:>3} | {mm(r['s_cold']):>11} {mm(r['s_warm']):>6} | "
          f"{mm(r['sk']):>18}", flush=True)


def likelihood_throughput(m: int = 25, repeats: int = 20) -> tuple[int, float, float, float]:
    """(n, ms per likelihood evaluation, its GFLOP/s, one-thread dgemm GFLOP/s) on the search subset at M = m.

    An evaluation's floating-point work is dominated by the Cholesky factorisation (n^3 / 3) and
    the inverse from it (2 n^3 / 3); the O(n^2) kernel and trace passes are not counted.
    """
    from gpis_grasp_ros.core.gpis.hyperparameters import _search_subset
    from gpis_grasp_ros.core.gpis.likelihood import _LikelihoodWorkspace, negative_log_marginal_likelihood

    g, sdf, noise, mask = synthetic_object(m)
    params = GpisParams()
    obs = _observations_from(g.cell_centers()[mask], sdf[mask], noise[mask],
                             gradient_observations(sdf, noise, mask, g, params.gradient_noise_variance))
    eligible = np.abs(sdf[mask]) <= params.search_band_cells * g.resolution
    sub = _search_subset(obs, params.max_opt_points, np.random.default_rng(params.seed), eligible)
    ws = _LikelihoodWorkspace(sub)
    resid = sub.y - np.where(sub.kind == VALUE, params.prior_mean, 0.0)
    theta = np.log([1.5e-4, 0.014])
    t_eval = timed(lambda: negative_log_marginal_likelihood(theta, ws, resid, sub.noise + params.jitter), repeats)[0]
    a = np.random.default_rng(0).standard_normal((1000, 1000))
    t_gemm = timed(lambda: a @ a, 5)[0]
    n = sub.size
    return n, t_eval, n ** 3 / t_eval / 1e6, 2e9 / t_gemm / 1e6


def search_inputs(occ: np.ndarray, noise: np.ndarray, geometry: GridGeometry, params: GpisParams = GpisParams()):
    """What ``posterior_from_grids`` hands the hyperparameter search: (observations, band cells, inscribed radius m)."""
    from gpis_grasp_ros.core.sdf import signed_distance

    train = (occ >= 0) & np.isfinite(noise)
    sdf, var = signed_distance((occ >= 50) | (occ < 0), geometry.resolution), np.where(train, noise, 0.0)
    grads = gradient_observations(sdf, var, train, geometry, params.gradient_noise_variance) \
        if params.gradient_observations else None
    obs = _observations_from(geometry.cell_centers()[train], sdf[train], var[train], grads)
    return obs, np.abs(sdf[train]) <= params.search_band_cells * geometry.resolution, max(0.0, -float(sdf.min()))


def bench_bags(paths: list[str]) -> list[dict]:
    """Cold vs warm-from-perturbed fits on shipped bags: log likelihoods and GP-GPIS-OPT P_F (seed 0)."""
    from gpis_grasp_ros.core.pipeline import posterior_from_grids, publishable_grids
    from gpis_grasp_ros.core.planners import plan
    from gpis_grasp_ros.core.sensing import SensingParams, segment_frames
    from gpis_grasp_ros.data.bags import load_bag

    print(f"{'bag':<26} {'sub':>4} {'cold LL':>9} {'ev':>3} {'sqrt(C) mm':>10} {'l mm':>6} | "
          f"{'small: LL':>10} {'ev':>3} | {'large: LL':>10} {'ev':>3} | {'P_F cold':>8} {'small':>6} {'large':>6} | "
          f"{'L-BFGS-B: LL':>12} {'ev':>3}")
    rows = []
    for path in paths:
        scene = load_bag(path)
        result = segment_frames(scene.rgb_frames, scene.depth_frames, scene.intrinsics, SensingParams(),
                                frame_id=scene.frame_id)
        occ, noise, geometry = publishable_grids(result)
        cold = posterior_from_grids(occ, noise, geometry)
        fc = cold.hyperparameter_fit
        small = posterior_from_grids(occ, noise, geometry, warm_start=drifted(fc, 1.05, 0.97))
        large = posterior_from_grids(occ, noise, geometry, warm_start=drifted(fc))
        pf = [plan('gp-gpis-opt', p, seed=0).p_f for p in (cold, small, large)]
        name = str(Path(path).relative_to(Path(path).parents[1] if 'head' in Path(path).parts else Path(path).parent))
        fs, fl = small.hyperparameter_fit, large.hyperparameter_fit
        obs, band, r_in = search_inputs(occ, noise, geometry)
        ff = reference_search(geometry, obs, GpisParams(), band, r_in)  # three-start L-BFGS-B
        rows.append(dict(bag=name, cold=fc, small=fs, large=fl, pf=pf, reference=ff))
        print(f'{name:<26} {fc.n_observations:>4} {fc.log_likelihood:>9.3f} {fc.n_evaluations:>3} '
              f'{math.sqrt(fc.signal_variance) * 1e3:>10.2f} {fc.length_scale * 1e3:>6.2f} | '
              f'{fs.log_likelihood:>10.3f} {fs.n_evaluations:>3} | {fl.log_likelihood:>10.3f} {fl.n_evaluations:>3} | '
              f'{pf[0]:>8.3f} {pf[1]:>6.3f} {pf[2]:>6.3f} | {ff.log_likelihood:>12.3f} {ff.n_evaluations:>3}',
              flush=True)
    return rows


def sklearn_reference(g: GridGeometry, sdf: np.ndarray, noise: np.ndarray, mask: np.ndarray, c: float, ell: float,
                      prior: float, jitter: float, repeats: int = 1) -> tuple[float, np.ndarray, np.ndarray]:
    """scikit-learn GPR at equal settings → (ms, mean (H, W), variance (H, W))."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel

    xy = g.cell_centers()
    x_train, y_train = xy[mask], sdf[mask] - prior
    kernel = ConstantKernel(c, constant_value_bounds='fixed') * RBF(ell, length_scale_bounds='fixed')

    def fit_predict() -> tuple[np.ndarray, np.ndarray]:
        gpr = GaussianProcessRegressor(kernel=kernel, alpha=noise[mask] + jitter, optimizer=None, normalize_y=False)
        gpr.fit(x_train, y_train)
        return gpr.predict(xy.reshape(-1, 2), return_std=True)

    ms, (mean, std) = best_of(fit_predict, repeats)
    return ms, mean.reshape(g.shape) + prior, (std ** 2).reshape(g.shape)


def dense_joint_reference(post: GpisPosterior) -> tuple[np.ndarray, np.ndarray]:
    """Dense function-space GP on all of ``post``'s observations (values + gradients) → (mean, variance) on the grid."""
    kp = post.params
    obs = post.observations()
    a = kp.signal_variance * _DenseKernel(obs)(kp.length_scale)[0]
    a[np.diag_indices_from(a)] += obs.noise + post.jitter
    chol = np.linalg.cholesky(a)
    resid = obs.y - np.where(obs.kind == VALUE, kp.prior_mean, 0.0)
    cells = post.geometry.cell_centers().reshape(-1, 2)
    k_star = _cross_joint(cells, obs, kp, 0, 0)  # (cells, N)
    alpha = np.linalg.solve(chol.T, np.linalg.solve(chol, resid))
    v = np.linalg.solve(chol, k_star.T)
    shape = post.geometry.shape
    return (kp.prior_mean + k_star @ alpha).reshape(shape), (kp.signal_variance - np.sum(v * v, axis=0)).reshape(shape)


def bench_size(m: int, with_sklearn: bool = True, seed: int = 0, dense_max: int = 4000) -> dict:
    """One table row for an m x m grid."""
    g, sdf, noise, mask = synthetic_object(m)
    reps = 5 if m <= 25 else (3 if m <= 50 else 2)
    t_ml, post_ml = best_of(lambda: fit_gpis(sdf, noise, mask, g, GpisParams(seed=seed)), 1 if m > 25 else 2)
    kp = post_ml.params
    fixed = GpisParams(optimize_hyperparameters=False, signal_variance=kp.signal_variance, length_scale=kp.length_scale)
    t_fit, post = best_of(lambda: fit_gpis(sdf, noise, mask, g, fixed), reps)
    t_vo, _ = best_of(lambda: fit_gpis(sdf, noise, mask, g, replace(fixed, gradient_observations=False)), reps)
    rng = np.random.default_rng(seed)
    t_smp, _ = best_of(lambda: post.sample(1000, rng), 3)
    t_blur, _ = best_of(lambda: gpis_blur(post, 1000, np.random.default_rng(seed)), 3 if m <= 50 else 2)
    row = dict(m=m, n=int(mask.sum()), n_obs=int(mask.sum() + post.train_grad.size), rank=post.rank,
               path=post.approximation, fit=t_fit, fit_ml=t_ml, sample=t_smp, blur=t_blur, value_only=t_vo,
               c=kp.signal_variance, ell=kp.length_scale, res=g.resolution, bound_hits=post_ml.bound_hits,
               sk=math.nan, speedup=math.nan, err_mu=math.nan, err_var=math.nan, rr_mu=math.nan, rr_var=math.nan)
    if with_sklearn:
        t_sk, _, _ = sklearn_reference(g, sdf, noise, mask, kp.signal_variance, kp.length_scale, kp.prior_mean,
                                       fixed.jitter, 3 if m <= 50 else 1)
        row.update(sk=t_sk, speedup=t_sk / t_vo)
    rr = post if post.approximation != 'exact' else fit_gpis(sdf, noise, mask, g, replace(fixed, max_exact_points=0))
    if row['n_obs'] <= dense_max:
        mu_ref, var_ref = dense_joint_reference(post)
        row.update(err_mu=float(np.abs(post.mean - mu_ref).max()),
                   err_var=float(np.abs(post.variance - var_ref).max() / float(var_ref.max())))
    elif post.approximation == 'exact':  # too large for the dense reference: the exact Kronecker path is the reference
        mu_ref, var_ref = post.mean, post.variance
    else:
        return row
    vmax = float(var_ref.max())
    row.update(rr_mu=float(np.abs(rr.mean - mu_ref).max()), rr_var=float(np.abs(rr.variance - var_ref).max() / vmax))
    return row


def run(sizes: list[int], with_sklearn: bool = True, seed: int = 0, dense_max: int = 4000) -> list[dict]:
    """Print and return one row per grid size."""
    if with_sklearn:  # warm-up: the first GaussianProcessRegressor call pays imports and set-up
        g, sdf, noise, mask = synthetic_object(8)
        sklearn_reference(g, sdf, noise, mask, 1e-4, 0.02, -0.01, 1e-10)
    rows = []
    for m in sizes:
        rows.append(bench_size(m, with_sklearn, seed, dense_max))
        print_row(rows[-1])
    return rows


HEADER = (f"{'M':>4} {'cells':>6} {'obs':>6} {'path':>12} {'rank':>5} {'fit fixed':>10} {'fit ML':>9} "
          f"{'1000 smp':>9} {'blur':>8} {'value-only':>10} {'sklearn':>9} {'speed-up':>9} {'err mu':>9} {'err var':>9} "
          f"{'rr err mu':>10} {'rr err var':>10}   ML hyperparameters")


def print_row(r: dict) -> None:
    hits = f" (bound: {', '.join(r['bound_hits'])})" if r['bound_hits'] else ''
    print(f"{r['m']:>4} {r['n']:>6} {r['n_obs']:>6} {r['path']:>12} {r['rank']:>5} {r['fit']:>10.1f} "
          f"{r['fit_ml']:>9.0f} {r['sample']:>9.1f} {r['blur']:>8.1f} {r['value_only']:>10.1f} {r['sk']:>9.0f} "
          f"{r['speedup']:>8.1f}x "
          f"{r['err_mu']:>9.1e} {r['err_var']:>9.1e} {r['rr_mu']:>10.1e} {r['rr_var']:>10.1e}   "
          f"sqrt(C) {math.sqrt(r['c']) * 1e3:.1f} mm, l {r['ell'] * 1e3:.1f} mm = {r['ell'] / r['res']:.1f} cells"
          f"{hits}", flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m gpis_grasp_ros.bench gpis', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--sizes', type=int, nargs='+', default=[25, 50, 100], help='grid sizes M')
    parser.add_argument('--no-sklearn', action='store_true', help='skip the scikit-learn reference')
    parser.add_argument('--dense-max', type=int, default=4000,
                        help='largest observation count checked against the dense joint reference')
    parser.add_argument('--ml-repeats', type=int, default=7, help='calls per timing of the ML-fit table')
    parser.add_argument('--no-fit-table', action='store_true', help='only the ML-fit table (and --bags)')
    parser.add_argument('--bags', action='store_true',
                        help='also the cold vs warm table over every shipped bag (bags/*.mcap, bags/head/*.mcap)')
    parser.add_argument('--blas-threads', type=int, default=1,
                        help='BLAS threads for every timed call, ours and scikit-learn alike (0 = library default)')
    args = parser.parse_args(argv)
    with blas_threads(args.blas_threads):
        if not args.no_fit_table:
            print(f'GPIS benchmark: times in ms (best of repeats), BLAS threads: {args.blas_threads or "default"}; '
                  'err = max deviation from the dense joint value/gradient GP; rr = reduced-rank path')
            print(HEADER, flush=True)
            run(args.sizes, with_sklearn=not args.no_sklearn, dense_max=args.dense_max)
        n, t_eval, gflops, peak = likelihood_throughput()
        print(f'\nlikelihood evaluation at n = {n}: {t_eval:.2f} ms, {gflops:.1f} GFLOP/s '
              f'({100 * gflops / peak:.0f} % of this machine\'s one-thread dgemm, {peak:.1f} GFLOP/s)')
        print(f'ML fit: ms (min/median of {args.ml_repeats}), ev = likelihood evaluations, sub = search subset size')
        print(ML_HEADER, flush=True)
        for m in args.sizes:
            print_ml_row(bench_ml(m, args.ml_repeats, with_sklearn=not args.no_sklearn))
        if args.bags:
            logging.getLogger('gpis_grasp_ros').setLevel(logging.ERROR)  # binding bounds are in the table
            root = Path(__file__).resolve().parents[2] / 'bags'
            print('\nShipped bags: cold vs warm-started fits (LL = log likelihood on the search subset, nats)')
            bench_bags(sorted(glob.glob(str(root / '*.mcap'))) + sorted(glob.glob(str(root / 'head' / '*.mcap'))))
    return 0
