"""GP-GPIS-OPT (Algorithm 1): N_g valid heuristic initial grasps, each refined by SCP on eq. 6, best
objective wins; the re-ranked variant picks among the local optima by Monte-Carlo P_F. :func:`optimise` is
also the body of GP-D and GP-U (:mod:`baselines`)."""

from __future__ import annotations

import numpy as np

from gpis_grasp_ros.core.planners.context import PlanningContext, finish, stoppable
from gpis_grasp_ros.core.planners.objective import SCP_UNIT_M, MeanGraspObjective
from gpis_grasp_ros.core.planners.params import PlannerParams
from gpis_grasp_ros.core.planners.result import GraspResult, RestartInfo, Tracker, empty_result
from gpis_grasp_ros.core.planners.warm_start import initial_grasps
from gpis_grasp_ros.core.quality import draw_shape_samples, probability_force_closure
from gpis_grasp_ros.core.scp import ScpProgress, ScpResult, ScpSettings, scp_minimize

#: Points per batch of eq. 6 evaluations inside an SCP iteration (a stop check between batches:
#: 128 points = 32 restarts' finite differences, tens of ms on a 25 x 25 grid; the values do not
#: depend on the batching).
SCP_EVAL_CHUNK = 128


def _scp_settings(params: PlannerParams) -> ScpSettings:
    u = SCP_UNIT_M  # lengths in metres -> SCP units
    return ScpSettings(fd_step=params.fd_step_m / u, trust_radius_init=params.trust_radius_m / u,
                       trust_radius_min=params.trust_radius_min_m / u,
                       trust_radius_max=params.trust_radius_max_m / u, max_iterations=params.max_scp_iterations,
                       constraint_tol=params.constraint_tol, penalty_init=10.0, penalty_factor=10.0,
                       penalty_max=1e3, improve_tol=params.scp_model_tol, step_tol=params.scp_step_tol_m / u,
                       objective_tol=params.scp_objective_tol, accept_ratio=0.1, trust_shrink=0.3, trust_expand=2.0,
                       prox=1e-8, prox_rel=0.1, osqp_eps=1e-4, osqp_max_iter=4000,
                       trust_expand_from_step=True, prox_penalty_weight=0.01,
                       osqp_rho=0.1, osqp_rho_interval=25, eval_chunk=SCP_EVAL_CHUNK)


def optimise(ctx: PlanningContext, method: str, n_starts: int, penalty: float, antipodal: bool,
             rngs: dict[str, np.random.Generator], t_start: float, seed: int | None,
             rerank: bool = False, tracker: Tracker | None = None) -> GraspResult:
    """Shared body of GP-D, GP-U, GP-GPIS-OPT (and its re-ranked variant)."""
    params = ctx.params
    tracker = Tracker(None) if tracker is None else tracker
    tracker.check()
    # the warm starts (if any) come first, with the penalty their run ended with
    j1, j2, mu0, n_warm = initial_grasps(ctx, n_starts, rngs['candidates'], ctx.warm_start, checkpoint=tracker.check)
    if j1.shape[0] == 0:
        return empty_result(method, 'no valid initial grasp found on the mean shape', t_start, seed)
    tracker.total = j1.shape[0]
    g = ctx.geometry
    x0 = MeanGraspObjective.variables(j1, j2)
    eps = rngs['perturbations'].standard_normal((params.n_perturbations, 2, 2))
    objective = MeanGraspObjective(ctx, eps, penalty, antipodal)
    pad = ctx.mean_bank.pad  # jaws may start up to the bank's padding beyond the outer cell centres
    lo, hi = g.to_metric(np.array([-float(pad)] * 2)), g.to_metric(np.array([g.width - 1 + pad, g.height - 1 + pad]))
    lower, upper = np.tile(lo, 2) / SCP_UNIT_M, np.tile(hi, 2) / SCP_UNIT_M
    monitor = _ScpMonitor(objective, tracker, x0.shape[0], params.constraint_tol)
    poll = tracker.check if tracker.control is not None else None
    settings = _scp_settings(params)
    res: ScpResult = scp_minimize(objective, x0, settings, lower=lower, upper=upper, monitor=monitor, poll=poll,
                                  penalty0=np.where(np.isfinite(mu0), mu0, settings.penalty_init))
    feasible0 = _chunked_details(objective, x0, tracker)['constraints'].max(axis=1) <= params.constraint_tol
    # The opening constraint holds to constraint_tol; make it exact (a grasp wider than w_g is not
    # in the candidate set and would fail every Monte-Carlo trial): shrink about the centre.
    x_opt = res.x.copy()
    a, b = x_opt[:, 0:2], x_opt[:, 2:4]
    width = np.linalg.norm(b - a, axis=1)
    w_max = ctx.gripper.max_opening / SCP_UNIT_M
    shrink = np.where(width > w_max, w_max / np.maximum(width, 1e-12), 1.0)[:, None]
    centre = 0.5 * (a + b)
    x_opt = np.concatenate([centre + (a - centre) * shrink, centre + (b - centre) * shrink], axis=1)
    det = _chunked_details(objective, x_opt, tracker)
    value = -det['objective']  # eq. 6 is a maximisation
    feasible = (det['constraints'].max(axis=1) <= params.constraint_tol) & det['valid_nominal']
    o1, o2 = objective.jaws(x_opt)
    restarts = [RestartInfo(initial_jaw1=j1[i], initial_jaw2=j2[i], jaw1=o1[i], jaw2=o2[i], objective=float(value[i]),
                            pf_smoothed=float(det['pf_smoothed'][i]), feasible=bool(feasible[i]),
                            converged=bool(res.converged[i]), reason=res.reason[i], iterations=int(res.iterations[i]),
                            evaluations=int(res.evaluations[i]), objective_history=-res.objective_history[i],
                            qp_failures=int(res.qp_failures[i]), qp_status=res.qp_status[i],
                            initial_feasible=bool(feasible0[i]), warm=i < n_warm, penalty=float(res.penalty[i]))
                for i in range(res.x.shape[0])]
    # Algorithm 1: keep the best objective; feasible local optima take precedence.
    rank_value = np.where(feasible, value, value - 1e6)
    best = int(np.argmax(rank_value))
    chosen_value = float(value[best])
    infeasible_note = 'no restart satisfied all constraints; returning the best objective'
    message = '' if feasible[best] else infeasible_note
    if rerank:
        samples = draw_shape_samples(ctx.posterior, params.n_shape_samples, rngs['selection'], rho=ctx.rho)
        est = probability_force_closure(o1, o2, samples, ctx.gripper, ctx.sigma_g, checkpoint=tracker.check)
        for i, info in enumerate(restarts):
            info.p_f = float(est.p[i])
        # Feasible local optima still take precedence (as in Algorithm 1), then MC P_F, then eq. 6.
        best = int(np.lexsort((value, est.p, feasible))[-1])
        chosen_value = float(est.p[best])
        message = '' if feasible[best] else infeasible_note
    if restarts[best].qp_failures and not restarts[best].converged:
        note = f'chosen restart {restarts[best].reason}: {restarts[best].qp_failures} QP subproblem(s) failed'
        message = f'{message}; {note}' if message else note
    return finish(ctx, method, o1[best], o2[best], chosen_value, t_start, rngs, seed, message, tracker=tracker,
                  iterations=int(res.iterations.sum()), converged=bool(res.converged[best]),
                  feasible=bool(feasible[best]), n_candidates=res.x.shape[0], restarts=restarts)


def _chunked_details(objective: MeanGraspObjective, x: np.ndarray, tracker: Tracker) -> dict[str, np.ndarray]:
    """:meth:`MeanGraspObjective.details` in batches of :data:`SCP_EVAL_CHUNK` rows, a stop check before each."""
    parts = []
    for start in range(0, x.shape[0], SCP_EVAL_CHUNK):
        tracker.check()
        parts.append(objective.details(x[start:start + SCP_EVAL_CHUNK]))
    if len(parts) == 1:
        return parts[0]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


class _ScpMonitor:
    """Turns SCP iterations into PlanControl progress (one call per finished restart) and stop checks."""

    def __init__(self, objective: MeanGraspObjective, tracker: Tracker, n: int, tol: float) -> None:
        self.objective = objective
        self.tracker = tracker
        self.tol = tol
        self.running = np.ones(n, dtype=bool)
        self.best_rank = -np.inf

    def __call__(self, prog: ScpProgress) -> None:
        tr = self.tracker
        finished = np.flatnonzero(self.running & ~prog.active)
        self.running = prog.active.copy()
        for i in finished:
            value = -float(prog.fun[i])
            rank = value if np.max(prog.constraints[i], initial=-np.inf) <= self.tol else value - 1e6
            if rank > self.best_rank:
                self.best_rank = rank
                pf = float(self.objective.details(prog.x[i:i + 1])['pf_smoothed'][0]) \
                    if tr.control is not None and tr.control.on_progress is not None else float('nan')
                tr.step(value, pf)
            else:
                tr.step()
        tr.heartbeat()


@stoppable('gp-gpis-opt')
def plan_gp_gpis_opt(ctx, rngs, seed, t0, tracker) -> GraspResult:
    """GP-GPIS-OPT (Algorithm 1): N_g SCP runs on eq. 6 with the antipodal constraints."""
    return optimise(ctx, 'gp-gpis-opt', ctx.params.n_initial_grasps, ctx.params.uncertainty_penalty, True, rngs,
                    t0, seed, tracker=tracker)


@stoppable('gp-gpis-opt-reranked')
def plan_gp_gpis_opt_reranked(ctx, rngs, seed, t0, tracker) -> GraspResult:
    """GP-GPIS-OPT whose N_g local optima are re-scored by Monte-Carlo P_F (beyond the paper)."""
    return optimise(ctx, 'gp-gpis-opt-reranked', ctx.params.n_initial_grasps, ctx.params.uncertainty_penalty, True,
                    rngs, t0, seed, rerank=True, tracker=tracker)

