"""Calibration study: is the predicted probability of force closure a probability?

For every object, a set of grasps — every grasp planned in the Table I run plus
``calibration_candidates`` candidate grasps chosen to span low to high P_F — is
given three *predictions* of its success probability and an *outcome*:

* ``p_tilde_hard`` — P̃_F from GP-M's quality: the fraction of jaw perturbations (σ_g, section
  V-B) for which Q_F > 0 on the GPIS **mean** shape (``calibration_perturbations`` draws). This is
  what a planner that trusts the mean shape (GP-M) implicitly predicts.
* ``p_tilde_smooth`` — P̃_F exactly as GP-GPIS-OPT optimises it (section VI-A):
  :class:`~gpis_grasp_ros.core.planners.MeanGraspObjective`'s sigmoid-smoothed mean of Q_F over
  K_p common-random-number perturbations on the mean shape.
* ``p_f`` — Monte-Carlo P_F (eq. 3) on S joint shape samples and perturbations, the planners'
  own estimator, on a sample set independent of the one used to pick the candidates.

The outcome is the success rate of ``calibration_trials`` (≥ 50 in the study) simulated
executions on the bag's ground-truth shape
(:func:`~gpis_grasp_ros.sim.execution.execute_grasp_trials`, σ_g = 0.5 planning cell, the
simulated gripper of ``gripper_sim_node``).

**Candidate choice.** K/2 heuristic candidates (GP-P's generator,
:func:`~gpis_grasp_ros.core.planners.sample_heuristic_grasps`) plus K/2 random grasps around the
object (:func:`random_grasps`; on some objects every heuristic candidate has P_F > 0.9, and a
calibration study needs the whole range) are screened by P_F on a *screening* set of 250 samples; for
each of ``n`` target values evenly spaced in [0, 1] the unused candidate with the nearest
screening P_F is taken. The predictions use other samples, so the
choice does not bias them (no winner's curse).

**Metrics** (:func:`expected_calibration_error`, :func:`brier_score`): ECE with 10 equal-width
bins of the prediction, ``Σ_b (n_b / N) |mean prediction_b − observed success rate_b|`` (every grasp
weighs the same; all grasps have the same number of executions); the Brier score per execution,
``mean over executions of (p − y)²`` = ``mean over grasps of (p − r)² + r (1 − r)`` with r the
grasp's success rate. A finite number of executions makes even a perfect predictor show a
positive ECE; :func:`null_ece` gives that floor (ECE of outcomes drawn from the predictions).

**Diagnostics** (why P_F is or is not calibrated), per object:

* ``p_true_grid`` — the same Monte-Carlo P_F with the shape *known*: the true SDF resampled on
  the planning grid as the only "sample". Its miscalibration against the executions is due to the
  grid and the contact model alone (no GP); the remainder of P_F's is due to the GPIS.
* GP z-scores of the true SDF at the planning cells, ``(sdf_true − μ) / σ``: RMS ≈ 1 and 95 % of
  |z| < 1.96 for a calibrated GP; RMS > 1 is over-confidence (variance too small), < 1
  under-confidence. Reported over all cells and near the true surface (|sdf_true| < 2 cells).
* ``p_f_inflated`` — P_F with every shape sample's deviation from the mean scaled by the RMS z near
  the surface (clipped to [1, 20]): if GP over-confidence is the cause, this P_F is better calibrated;
  if the mean shape itself is wrong where σ is small (e.g. a transparent part seen as free table
  with a low noise value), inflating σ helps little.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from gpis_grasp_ros.core.contacts import find_contacts, perturb_grasps
from gpis_grasp_ros.core.gpis import GpisPosterior, center_of_mass
from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.core.planners import (
    MeanGraspObjective,
    PlannerParams,
    PlanningContext,
    sample_heuristic_grasps,
)
from gpis_grasp_ros.core.quality import ShapeSamples, draw_shape_samples, grasp_quality, probability_force_closure
from gpis_grasp_ros.core.sdf_bank import SdfBank

#: The three predictors: column of the calibration rows, label for tables and figures.
PREDICTORS: tuple[tuple[str, str], ...] = (
    ('p_tilde_hard', "P̃_F of GP-M's Q_F (mean shape, 1[Q_F > 0])"),
    ('p_tilde_smooth', 'P̃_F as GP-G optimises it (mean shape, smoothed)'),
    ('p_f', 'P_F (Monte Carlo over shape samples)'),
)
#: Diagnostic predictors (not the planners'): P_F with the true shape, P_F with σ inflated.
DIAGNOSTICS: dict[str, str] = {'p_true_grid': 'P_F with the true shape on the planning grid (diagnostic)',
                               'p_f_inflated': 'P_F with σ inflated by the z RMS (diagnostic)'}
N_BINS = 10
#: Shape samples of the screening P_F that only places candidates along [0, 1] (s.e. ≤ 0.032).
SCREEN_SAMPLES = 250


# ------------------------------------------------------------------------------------------
# Metrics
# ------------------------------------------------------------------------------------------


@dataclass
class Reliability:
    """Reliability-diagram data for ``N_BINS`` equal-width bins of the prediction.

    ``count`` grasps per bin, ``mean_pred`` mean prediction, ``observed`` mean success rate
    (NaN for empty bins), ``executions`` executions per bin.
    """

    edges: np.ndarray
    count: np.ndarray
    mean_pred: np.ndarray
    observed: np.ndarray
    executions: np.ndarray


def _rates(pred: Sequence[float], successes: Sequence[float], trials: Sequence[float] | float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    p = np.asarray(pred, dtype=np.float64).reshape(-1)
    s = np.asarray(successes, dtype=np.float64).reshape(-1)
    n = np.broadcast_to(np.asarray(trials, dtype=np.float64), p.shape).astype(np.float64)
    if s.shape != p.shape:
        raise ValueError(f'{p.size} predictions but {s.size} success counts')
    if np.any(~np.isfinite(p)) or np.any((p < 0) | (p > 1)):
        raise ValueError('predictions must be probabilities in [0, 1]')
    if np.any(n <= 0) or np.any((s < 0) | (s > n)):
        raise ValueError('need 0 <= successes <= trials and trials > 0 for every grasp')
    return p, s, n


def reliability(pred: Sequence[float], successes: Sequence[float], trials: Sequence[float] | float,
                n_bins: int = N_BINS) -> Reliability:
    """Bin grasps by prediction (``n_bins`` equal-width bins on [0, 1], 1.0 in the last bin)."""
    p, s, n = _rates(pred, successes, trials)
    edges = np.linspace(0.0, 1.0, n_bins + 1)
    b = np.clip(np.floor(p * n_bins).astype(int), 0, n_bins - 1)
    count = np.bincount(b, minlength=n_bins).astype(np.float64)
    with np.errstate(invalid='ignore', divide='ignore'):
        mean_pred = np.bincount(b, weights=p, minlength=n_bins) / count
        observed = np.bincount(b, weights=s / n, minlength=n_bins) / count
    return Reliability(edges, count.astype(int), mean_pred, observed, np.bincount(b, weights=n, minlength=n_bins))


def expected_calibration_error(pred: Sequence[float], successes: Sequence[float], trials: Sequence[float] | float,
                               n_bins: int = N_BINS) -> float:
    """ECE = Σ_b (n_b / N) |mean prediction_b − mean success rate_b| over equal-width bins."""
    r = reliability(pred, successes, trials, n_bins)
    ok = r.count > 0
    if not ok.any():
        return float('nan')
    return float(np.sum(r.count[ok] * np.abs(r.mean_pred[ok] - r.observed[ok])) / r.count.sum())


def brier_score(pred: Sequence[float], successes: Sequence[float], trials: Sequence[float] | float) -> float:
    """Mean over all executions of (p − y)², y ∈ {0, 1} the execution's outcome."""
    p, s, n = _rates(pred, successes, trials)
    if p.size == 0:
        return float('nan')
    r = s / n
    return float(np.sum(n * ((p - r) ** 2 + r * (1.0 - r))) / n.sum())


def null_ece(pred: Sequence[float], trials: Sequence[float] | float, rng: np.random.Generator,
             repeats: int = 200, n_bins: int = N_BINS) -> tuple[float, float]:
    """Mean and 95th percentile of the ECE of a *perfectly calibrated* predictor with these predictions.

    Outcomes are drawn as Binomial(trials, pred): the ECE floor set by the finite number of
    executions (what a measured ECE must be compared with).
    """
    p = np.asarray(pred, dtype=np.float64).reshape(-1)
    n = np.broadcast_to(np.asarray(trials), p.shape).astype(np.int64)
    if p.size == 0:
        return float('nan'), float('nan')
    vals = np.array([expected_calibration_error(p, rng.binomial(n, p), n, n_bins) for _ in range(repeats)])
    return float(vals.mean()), float(np.percentile(vals, 95))


def summarise(rows: Sequence[dict[str, Any]], rng: np.random.Generator | None = None,
              null_repeats: int = 200) -> dict[str, dict[str, float]]:
    """ECE, Brier score, mean bias (prediction − outcome) and the null ECE for every predictor."""
    out: dict[str, dict[str, float]] = {}
    if not rows:
        return out
    s = np.array([r['sim_successes'] for r in rows], dtype=np.float64)
    n = np.array([r['sim_trials'] for r in rows], dtype=np.float64)
    rng = np.random.default_rng(0) if rng is None else rng
    keys = [k for k, _ in PREDICTORS] + [k for k in DIAGNOSTICS if all(k in r for r in rows)]
    for key in keys:
        p = np.array([r[key] for r in rows], dtype=np.float64)
        null_mean, null_p95 = null_ece(p, n, rng, null_repeats)
        out[key] = {'ece': expected_calibration_error(p, s, n), 'brier': brier_score(p, s, n),
                    'bias': float(np.mean(p - s / n)), 'null_ece_mean': null_mean, 'null_ece_p95': null_p95,
                    'n_grasps': int(p.size)}
    return out


# ------------------------------------------------------------------------------------------
# One object
# ------------------------------------------------------------------------------------------


def random_grasps(ctx: PlanningContext, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` grasps with centres uniform over the mean shape's bounding box (grown by 2 cells), uniform
    closing directions and the full opening w_g: many miss or barely touch the object (low P_F)."""
    inside = np.asarray(ctx.posterior.mean) < 0
    g = ctx.geometry
    pts = g.cell_centers()[inside] if inside.any() else g.cell_centers().reshape(-1, 2)
    lo, hi = pts.min(axis=0) - 2 * g.resolution, pts.max(axis=0) + 2 * g.resolution
    centre = rng.uniform(lo, hi, (n, 2))
    theta = rng.uniform(0.0, np.pi, n)
    u = np.stack([np.cos(theta), np.sin(theta)], axis=1) * 0.5 * ctx.gripper.max_opening
    return centre - u, centre + u


def candidate_pool(ctx: PlanningContext, k: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """GP-P's ``k`` heuristic candidates plus ``k`` :func:`random_grasps` (so the pool reaches low P_F
    even where every heuristic candidate is good)."""
    h1, h2 = sample_heuristic_grasps(ctx, k, rng)
    r1, r2 = random_grasps(ctx, k, rng)
    return np.concatenate([h1, r1]), np.concatenate([h2, r2])


def spread_by_value(values: np.ndarray, n: int) -> np.ndarray:
    """Indices of ``n`` distinct entries whose values are nearest to ``n`` targets evenly spaced in [0, 1]."""
    values = np.asarray(values, dtype=np.float64)
    n = min(int(n), values.size)
    free = np.ones(values.size, dtype=bool)
    chosen = []
    for t in np.linspace(0.0, 1.0, n):
        cand = np.flatnonzero(free)
        k = int(cand[np.argmin(np.abs(values[cand] - t))])
        chosen.append(k)
        free[k] = False
    return np.array(chosen, dtype=int)


def perturbation_pf(ctx: PlanningContext, bank: SdfBank, jaw1: np.ndarray, jaw2: np.ndarray, eps: np.ndarray,
                    chunk_trials: int = 1 << 13) -> np.ndarray:
    """Fraction of perturbations ``eps (K, 2, 2)`` (σ_g) with Q_F > 0 on the single shape of ``bank``, per grasp.

    With ``ctx.mean_bank`` this is P̃_F with the hard indicator (GP-M's Q_F); with the true SDF
    resampled on the planning grid it is P_F of a known shape. Openings above w_g give 0.
    """
    out = np.zeros(jaw1.shape[0])
    step = max(1, chunk_trials // max(eps.shape[0], 1))
    for g0 in range(0, jaw1.shape[0], step):
        j1, j2 = jaw1[g0:g0 + step], jaw2[g0:g0 + step]
        g1, g2 = perturb_grasps(j1[:, None], j2[:, None], eps[None], ctx.sigma_g)
        con = find_contacts(bank, g1, g2, ctx.gripper, check_opening=False)
        q = grasp_quality(con, ctx.com, ctx.gripper, ctx.rho)
        width_ok = np.linalg.norm(j2 - j1, axis=1) <= ctx.gripper.max_opening * (1 + 1e-9)
        out[g0:g0 + step] = np.where(width_ok, np.mean(q > 0, axis=1), 0.0)
    return out


def true_shape_bank(truth: Any, geometry: Any) -> SdfBank:
    """The true SDF (m) bilinearly resampled at the planning grid's cell centres, as a one-grid bank."""
    return SdfBank(truth.values_at(geometry.cell_centers())[None], geometry)


def inflated_shape_samples(posterior: GpisPosterior, n: int, factor: float, rng: np.random.Generator,
                           rho: float) -> ShapeSamples:
    """``n`` joint samples with their deviations from the mean scaled by ``factor`` (σ × factor), for P_F."""
    mean = np.asarray(posterior.mean, dtype=np.float64)
    sdfs = mean[None] + factor * (posterior.sample(n, rng) - mean[None])
    eps = rng.standard_normal((n, 2, 2))
    return ShapeSamples(SdfBank(sdfs, posterior.geometry), center_of_mass(sdfs, posterior.geometry), eps, rho)


def gp_z_scores(posterior: GpisPosterior, true_shape: Any) -> dict[str, float]:
    """RMS of z = (sdf_true − μ) / σ at the planning cells, all cells and near the true surface, and 95 % coverage.

    ``true_shape`` provides ``values_at(xy)``: the true SDF (m) at planning-grid points.
    """
    g = posterior.geometry
    truth = true_shape.values_at(g.cell_centers())
    sd = np.sqrt(np.maximum(np.asarray(posterior.variance, dtype=np.float64), 1e-30))
    z = (truth - np.asarray(posterior.mean)) / sd
    near = np.abs(truth) < 2.0 * g.resolution
    return {'gp_z_rms': float(np.sqrt(np.mean(z ** 2))),
            'gp_z_rms_near_surface': float(np.sqrt(np.mean(z[near] ** 2))) if near.any() else float('nan'),
            'gp_coverage95': float(np.mean(np.abs(z) < 1.959964)),
            'gp_coverage95_near_surface': float(np.mean(np.abs(z[near]) < 1.959964)) if near.any() else float('nan'),
            # Mean error μ − sdf_true (cells; < 0: the mean shape bulges out) and mean σ (cells) near the surface.
            'gp_bias_near_surface_cells': float(np.mean(np.asarray(posterior.mean)[near] - truth[near]) / g.resolution)
            if near.any() else float('nan'),
            'gp_sd_near_surface_cells': float(np.mean(sd[near]) / g.resolution) if near.any() else float('nan')}


def calibrate_object(posterior: GpisPosterior, truth: Any, planned: Sequence[dict[str, Any]], params: PlannerParams,
                     n_candidates: int, trials: int, n_perturbations: int, seed: int,
                     object_name: str = '') -> tuple[list[dict[str, Any]], dict[str, float]]:
    """Predictions and simulated outcomes of the planned grasps and ``n_candidates`` candidate grasps.

    ``truth``: the ground truth (:class:`~gpis_grasp_ros.tools.evaluation.truth.TrueShape`:
    ``values_at(xy)`` true SDF at planning-grid points, ``execute(jaw1, jaw2, gripper, trials, rng)``
    simulated executions of a planning-grid grasp). ``planned``: dicts with ``method``, ``seed``,
    ``jaw1``, ``jaw2`` (m) and ``p_f`` (the planner's reported P_F). Returns the rows (one per
    grasp) and the object's GP z-score diagnostics.
    """
    if trials < 1:
        raise ValueError('the calibration study needs at least one execution per grasp')
    ctx = PlanningContext(posterior, params)
    streams = [np.random.default_rng(c) for c in np.random.SeedSequence(seed).spawn(8)]
    rng_cand, rng_screen, rng_pred, rng_tilde, rng_smooth, rng_exec, rng_true, rng_inflate = streams
    j1c, j2c = candidate_pool(ctx, max(n_candidates, params.n_grasp_samples // 2), rng_cand)
    screen_p = np.zeros(0)
    if n_candidates > 0 and j1c.shape[0]:
        screen = draw_shape_samples(posterior, min(params.n_shape_samples, SCREEN_SAMPLES), rng_screen, rho=ctx.rho)
        screen_p = probability_force_closure(j1c, j2c, screen, ctx.gripper, ctx.sigma_g).p
        pick = spread_by_value(screen_p, n_candidates)
        j1c, j2c, screen_p = j1c[pick], j2c[pick], screen_p[pick]
    else:
        j1c, j2c = j1c[:0], j2c[:0]
    kinds = [('candidate', -1, float('nan'))] * j1c.shape[0]
    pj1 = [np.asarray(p['jaw1'], dtype=np.float64) for p in planned]
    pj2 = [np.asarray(p['jaw2'], dtype=np.float64) for p in planned]
    kinds += [(str(p['method']), int(p['seed']), float(p['p_f'])) for p in planned]
    jaw1 = np.concatenate([j1c, np.reshape(pj1, (-1, 2))])
    jaw2 = np.concatenate([j2c, np.reshape(pj2, (-1, 2))])
    screen_all = np.concatenate([screen_p, np.full(len(planned), np.nan)])

    pred_samples = draw_shape_samples(posterior, params.n_shape_samples, rng_pred, rho=ctx.rho)
    pf = probability_force_closure(jaw1, jaw2, pred_samples, ctx.gripper, ctx.sigma_g)
    eps_hard = rng_tilde.standard_normal((n_perturbations, 2, 2))
    p_hard = perturbation_pf(ctx, ctx.mean_bank, jaw1, jaw2, eps_hard)
    eps_smooth = rng_smooth.standard_normal((params.n_perturbations, 2, 2))
    objective = MeanGraspObjective(ctx, eps_smooth, 0.0, False)
    g = ctx.geometry
    x = MeanGraspObjective.variables(jaw1, jaw2)
    p_smooth = np.asarray(objective.details(x)['pf_smoothed'], dtype=np.float64) if x.shape[0] else np.zeros(0)
    z_info = gp_z_scores(posterior, truth)
    inflation = float(np.clip(z_info['gp_z_rms_near_surface'], 1.0, 20.0)) if math.isfinite(
        z_info['gp_z_rms_near_surface']) else 1.0
    z_info['sigma_inflation'] = inflation
    p_inflated = probability_force_closure(
        jaw1, jaw2, inflated_shape_samples(posterior, params.n_shape_samples, inflation, rng_inflate, ctx.rho),
        ctx.gripper, ctx.sigma_g).p
    eps_true = rng_true.standard_normal((n_perturbations, 2, 2))
    p_true = perturbation_pf(ctx, true_shape_bank(truth, g), jaw1, jaw2, eps_true)
    q_mean = ctx.mean_quality(jaw1, jaw2)

    exec_gripper: GripperParams = params.gripper
    exec_seeds = rng_exec.integers(0, 2 ** 63 - 1, size=jaw1.shape[0])
    rows = []
    for i in range(jaw1.shape[0]):
        succ = truth.execute(jaw1[i], jaw2[i], exec_gripper, trials, np.random.default_rng(int(exec_seeds[i])))
        kind, seed_i, reported = kinds[i]
        rows.append({
            'object': object_name, 'kind': 'candidate' if kind == 'candidate' else 'planned', 'method': kind,
            'seed': seed_i, 'jaw1_x': float(jaw1[i, 0]), 'jaw1_y': float(jaw1[i, 1]),
            'jaw2_x': float(jaw2[i, 0]), 'jaw2_y': float(jaw2[i, 1]),
            'screen_p_f': float(screen_all[i]), 'p_f': float(pf.p[i]), 'p_f_std_error': float(pf.std_error[i]),
            'reported_p_f': reported, 'p_tilde_hard': float(p_hard[i]), 'p_tilde_smooth': float(p_smooth[i]),
            'p_true_grid': float(p_true[i]), 'p_f_inflated': float(p_inflated[i]),
            'q_f_mean': float(q_mean[i]) if math.isfinite(q_mean[i]) else float('nan'),
            'sim_successes': int(succ), 'sim_trials': int(trials), 'sim_success_rate': succ / trials,
        })
    return rows, z_info
