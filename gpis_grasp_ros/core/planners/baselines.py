"""The paper's baselines (VII-B): GP-M and GP-P choose among heuristic candidates (Q_F on the mean, Monte-Carlo
P_F), GP-D and GP-U optimise P̃_F on the mean without the antipodal constraints; the -single variants run
from one initial grasp (not in the paper)."""

from __future__ import annotations

import math

import numpy as np

from gpis_grasp_ros.core.planners.context import PlanningContext, finish, stoppable
from gpis_grasp_ros.core.planners.gp_gpis_opt import optimise
from gpis_grasp_ros.core.planners.result import GraspResult, Tracker, empty_result
from gpis_grasp_ros.core.planners.sampling import sample_heuristic_grasps
from gpis_grasp_ros.core.quality import ShapeSamples, draw_shape_samples, force_closure_successes


@stoppable('gp-d')
def plan_gp_d(ctx, rngs, seed, t0, tracker) -> GraspResult:
    """GP-D: maximise P̃_F on the mean SDF by finite differences from N_g initial grasps (λ = 0)."""
    return optimise(ctx, 'gp-d', ctx.params.n_initial_grasps, 0.0, False, rngs, t0, seed, tracker=tracker)


@stoppable('gp-u')
def plan_gp_u(ctx, rngs, seed, t0, tracker) -> GraspResult:
    """GP-U: GP-D plus the uncertainty penalty λ (eq. 4), N_g initial grasps."""
    return optimise(ctx, 'gp-u', ctx.params.n_initial_grasps, ctx.params.uncertainty_penalty, False, rngs, t0,
                    seed, tracker=tracker)


@stoppable('gp-d-single')
def plan_gp_d_single(ctx, rngs, seed, t0, tracker) -> GraspResult:
    """GP-D from ONE initial grasp (extra, not in the paper: isolates what the restarts contribute)."""
    return optimise(ctx, 'gp-d-single', 1, 0.0, False, rngs, t0, seed, tracker=tracker)


@stoppable('gp-u-single')
def plan_gp_u_single(ctx, rngs, seed, t0, tracker) -> GraspResult:
    """GP-U from ONE initial grasp (extra, not in the paper)."""
    return optimise(ctx, 'gp-u-single', 1, ctx.params.uncertainty_penalty, False, rngs, t0, seed, tracker=tracker)


#: Candidates per progress chunk of GP-M.
GP_M_CHUNK = 250


@stoppable('gp-m')
def plan_gp_m(ctx, rngs, seed, t0, tracker) -> GraspResult:
    """GP-M: the heuristic candidate with the highest Q_F on the mean SDF."""
    j1, j2 = sample_heuristic_grasps(ctx, ctx.params.n_grasp_samples, rngs['candidates'])
    if j1.shape[0] == 0:
        return empty_result('gp-m', 'the mean shape has no surface on the grid', t0, seed)
    starts = range(0, j1.shape[0], GP_M_CHUNK)
    tracker.total = len(starts)
    q = np.empty(j1.shape[0])
    for s0 in starts:
        q[s0:s0 + GP_M_CHUNK] = ctx.mean_quality(j1[s0:s0 + GP_M_CHUNK], j2[s0:s0 + GP_M_CHUNK])
        tracker.step(float(np.max(q[:s0 + GP_M_CHUNK])))
    best = int(np.argmax(q))
    if not np.isfinite(q[best]):
        return empty_result('gp-m', 'no heuristic candidate is valid on the mean shape', t0, seed,
                            n_candidates=j1.shape[0])
    return finish(ctx, 'gp-m', j1[best], j2[best], float(q[best]), t0, rngs, seed, tracker=tracker,
                  n_candidates=j1.shape[0])


@stoppable('gp-p')
def plan_gp_p(ctx, rngs, seed, t0, tracker) -> GraspResult:
    """GP-P: the heuristic candidate with the highest Monte-Carlo P_F (K candidates × S shapes)."""
    p = ctx.params
    j1, j2 = sample_heuristic_grasps(ctx, p.n_grasp_samples, rngs['candidates'])
    if j1.shape[0] == 0:
        return empty_result('gp-p', 'the mean shape has no surface on the grid', t0, seed)
    samples = draw_shape_samples(ctx.posterior, p.n_shape_samples, rngs['selection'], rho=ctx.rho)
    tracker.check()
    tiebreak = ctx.mean_quality(j1, j2)
    best, p_hat = select_by_monte_carlo(ctx, j1, j2, samples, tiebreak, tracker=tracker)
    return finish(ctx, 'gp-p', j1[best], j2[best], p_hat, t0, rngs, seed, tracker=tracker, n_candidates=j1.shape[0])


def select_by_monte_carlo(ctx: PlanningContext, jaw1: np.ndarray, jaw2: np.ndarray, samples: ShapeSamples,
                          tiebreak: np.ndarray, tracker: Tracker | None = None) -> tuple[int, float]:
    """Index of the candidate with the highest Monte-Carlo P_F, and that P̂_F (full sample set).

    Successive halving when ``gp_p_adaptive`` (see docs/planning.md), else brute force.
    ``tracker`` (internal) gets one progress step per round and a stop check per sample chunk.
    """
    tracker = Tracker(None) if tracker is None else tracker
    p = ctx.params
    n_s = samples.n
    k = jaw1.shape[0]
    eta = max(2, int(p.gp_p_halving_rate))
    if p.gp_p_adaptive and n_s > p.gp_p_min_samples and k > 1:
        rounds = 1 + max(0, math.ceil(math.log(n_s / max(1, p.gp_p_min_samples), eta) - 1e-9))
        rounds = min(rounds, 1 + max(0, math.ceil(math.log(k, eta))))
    else:
        rounds = 1
    alive = np.arange(k)
    succ = np.zeros(k, dtype=np.int64)
    used = 0
    tracker.total = rounds
    for r in range(rounds):
        n_r = n_s if r == rounds - 1 else max(1, math.ceil(n_s / eta ** (rounds - 1 - r)))
        succ[alive] += force_closure_successes(jaw1[alive], jaw2[alive], samples, ctx.gripper, ctx.sigma_g,
                                               start=used, stop=n_r, checkpoint=tracker.check)
        used = n_r
        lead = float(succ[alive].max(initial=0) / max(n_r, 1))
        tracker.step(lead, lead)
        if r < rounds - 1:
            keep = max(1, math.ceil(alive.size / eta))
            order = np.lexsort((-tiebreak[alive], -succ[alive]))
            alive = alive[order[:keep]]
    order = np.lexsort((-tiebreak[alive], -succ[alive]))
    best = int(alive[order[0]])
    return best, float(succ[best] / n_s)
