"""What every planner precomputes from a posterior (:class:`PlanningContext`), its random streams, the shared
evaluation of the chosen grasp (:func:`finish`) and the entry-point wrapper that adds :class:`PlanControl`."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from gpis_grasp_ros.core.background import Background
from gpis_grasp_ros.core.contacts import find_contacts
from gpis_grasp_ros.core.gpis import GpisPosterior
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.planners.params import PlannerParams
from gpis_grasp_ros.core.planners.result import GraspResult, PlanControl, Stopped, Tracker, empty_result
from gpis_grasp_ros.core.planners.sampling import mean_surface_points
from gpis_grasp_ros.core.quality import (
    ShapeSamples,
    draw_shape_samples,
    grasp_quality,
    probability_force_closure,
    torque_scale,
)
from gpis_grasp_ros.core.sdf_bank import SdfBank

if TYPE_CHECKING:
    from gpis_grasp_ros.core.planners.warm_start import WarmStart


class PlanningContext:
    """Everything the planners precompute from a posterior (mean-shape bank, COM, ρ, σ_g, surface).

    ``mean_bank`` is the world the jaws close in (the mean shape and the posterior's obstacles);
    ``shape_bank`` the mean shape alone, on which candidates are placed; ``warm_start`` a previous plan's
    optima for the SCP planners' starts (None: fresh heuristic grasps only)."""

    def __init__(self, posterior: GpisPosterior, params: PlannerParams, warm_start: WarmStart | None = None) -> None:
        self.posterior = posterior
        self.params = params
        self.warm_start = warm_start
        self.geometry: GridGeometry = posterior.geometry
        self.res = self.geometry.resolution
        self.gripper = params.gripper
        self.sigma_g = self.gripper.sigma_g
        self.mean_bank = SdfBank(posterior.mean, self.geometry, gradients=posterior.gradient,
                                 obstacles=posterior.obstacles)
        self.shape_bank = self.mean_bank if posterior.obstacles is None else SdfBank(
            posterior.mean, self.geometry, gradients=posterior.gradient)
        self.com = posterior.center_of_mass()
        self.rho = torque_scale(posterior.mean, self.geometry, self.com)
        self.variance = np.asarray(posterior.variance, dtype=np.float64)  # m²
        self.max_variance = float(np.max(self.variance))
        self.surface = mean_surface_points(posterior.mean, self.geometry)
        #: the final P_F's :func:`evaluation_samples`, drawn on the other core during the search (see _prepare)
        self.prefetch: Background[ShapeSamples] | None = None

    # -- evaluation on the mean shape -------------------------------------------------------
    def mean_quality(self, jaw1: np.ndarray, jaw2: np.ndarray) -> np.ndarray:
        """Q_F on the mean SDF of unperturbed grasps ``(..., 2)``; −inf when degenerate."""
        con = find_contacts(self.mean_bank, jaw1, jaw2, self.gripper)
        return grasp_quality(con, self.com, self.gripper, self.rho)


    def valid_on_mean(self, jaw1: np.ndarray, jaw2: np.ndarray) -> np.ndarray:
        """Whether grasps ``(..., 2)`` are executable on the mean SDF (contacts, jaws in free space, opening)."""
        return find_contacts(self.mean_bank, jaw1, jaw2, self.gripper).valid


def streams(seed: int | None) -> dict[str, np.random.Generator]:
    names = ('candidates', 'perturbations', 'selection', 'evaluation')
    children = np.random.SeedSequence(seed).spawn(len(names))
    return {k: np.random.default_rng(c) for k, c in zip(names, children, strict=True)}


def finish(ctx: PlanningContext, method: str, jaw1: np.ndarray, jaw2: np.ndarray, objective: float,
           t_start: float, rngs: dict[str, np.random.Generator], seed: int | None, message: str = '',
           tracker: Tracker | None = None, **kw) -> GraspResult:
    """Fill a GraspResult: geometry of the grasp, Q_F on the mean, evaluation P_F."""
    planning_time = time.perf_counter() - t_start
    planning_cpu_time = float('nan') if tracker is None else time.process_time() - tracker.cpu_start
    jaw1 = np.asarray(jaw1, dtype=np.float64).reshape(2)
    jaw2 = np.asarray(jaw2, dtype=np.float64).reshape(2)
    width = float(np.linalg.norm(jaw2 - jaw1))
    axis = (jaw2 - jaw1) / width if width > 0 else np.array([1.0, 0.0])
    if tracker is not None and ctx.prefetch is not None:  # the sampler's CPU time is not the search's
        planning_cpu_time -= ctx.prefetch.cpu_time()
    q = float(ctx.mean_quality(jaw1, jaw2))
    t_eval = time.perf_counter()
    samples = ctx.prefetch.result() if ctx.prefetch is not None else evaluation_samples(ctx, rngs['evaluation'])
    est = probability_force_closure(jaw1[None], jaw2[None], samples, ctx.gripper, ctx.sigma_g,
                                    checkpoint=None if tracker is None else tracker.check)
    valid = bool(ctx.valid_on_mean(jaw1, jaw2))
    # Success: the grasp is executable on the mean shape, or (GP-P) it closes on some shape samples.
    success = valid or bool(est.p[0] > 0)
    if not valid:
        note = 'grasp is degenerate on the mean shape (no contact, jaw in collision or opening > w_g)'
        message = f'{message}; {note}' if message else note
    return GraspResult(method=method, success=success, message=message or 'ok', jaw1=jaw1, jaw2=jaw2,
                       center=0.5 * (jaw1 + jaw2), axis=axis, width=width,
                       q_mean=q if np.isfinite(q) else float('nan'), p_f=float(est.p[0]),
                       p_f_std_error=float(est.std_error[0]), objective=float(objective),
                       planning_time=planning_time, evaluation_time=time.perf_counter() - t_eval, seed=seed,
                       planning_cpu_time=planning_cpu_time, **kw)


def evaluation_samples(ctx: PlanningContext, rng: np.random.Generator) -> ShapeSamples:
    """The S shape samples (and perturbation draws) on which every method's final P_F is estimated."""
    return draw_shape_samples(ctx.posterior, ctx.params.n_shape_samples, rng, rho=ctx.rho)


def _prepare(posterior: GpisPosterior, params: PlannerParams | None, seed: int | None,
             warm_start: WarmStart | None = None):
    params = PlannerParams() if params is None else params
    seed = params.seed if seed is None else seed
    ctx, rngs = PlanningContext(posterior, params, warm_start), streams(seed)
    # the final P_F's samples depend on the posterior and their own stream only: drawn while the planner searches
    ctx.prefetch = Background(evaluation_samples, ctx, rngs['evaluation'], name='pf-samples')
    return ctx, rngs, seed


def stoppable(method: str):
    """Decorator: a planner body ``f(ctx, rngs, seed, t0, tracker)`` → public planner with PlanControl."""

    def wrap(body):
        def planner(posterior: GpisPosterior, params: PlannerParams | None = None, seed: int | None = None,
                    control: PlanControl | None = None, warm_start: WarmStart | None = None) -> GraspResult:
            t0 = time.perf_counter()
            tracker = Tracker(control)
            try:
                tracker.check()
                ctx, rngs, seed_used = _prepare(posterior, params, seed, warm_start)
                return body(ctx, rngs, seed_used, t0, tracker)
            except Stopped as stop:
                seed_used = (PlannerParams() if params is None else params).seed if seed is None else seed
                return empty_result(method, f'stopped: {stop.reason}', t0, seed_used, stopped=stop.reason)

        planner.__name__ = body.__name__.lstrip('_')
        planner.__qualname__ = planner.__name__
        planner.__doc__ = body.__doc__
        return planner

    return wrap
