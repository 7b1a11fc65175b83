"""The planners by name (:data:`METHODS`) and :func:`plan`, which dispatches to them."""

from __future__ import annotations

from gpis_grasp_ros.core.gpis import GpisPosterior
from gpis_grasp_ros.core.planners.baselines import (
    plan_gp_d,
    plan_gp_d_single,
    plan_gp_m,
    plan_gp_p,
    plan_gp_u,
    plan_gp_u_single,
)
from gpis_grasp_ros.core.planners.gp_gpis_opt import plan_gp_gpis_opt, plan_gp_gpis_opt_reranked
from gpis_grasp_ros.core.planners.params import PlannerParams
from gpis_grasp_ros.core.planners.result import GraspResult, PlanControl
from gpis_grasp_ros.core.planners.warm_start import WARM_METHODS, WarmStart

_PLANNERS = {
    'gp-gpis-opt': plan_gp_gpis_opt,
    'gp-gpis-opt-reranked': plan_gp_gpis_opt_reranked,
    'gp-p': plan_gp_p,
    'gp-m': plan_gp_m,
    'gp-d': plan_gp_d,
    'gp-u': plan_gp_u,
    'gp-d-single': plan_gp_d_single,
    'gp-u-single': plan_gp_u_single,
}
#: Planner names :func:`plan` accepts.
METHODS = tuple(_PLANNERS)


def plan(method: str, posterior: GpisPosterior, params: PlannerParams | None = None,
         seed: int | None = None, control: PlanControl | None = None,
         warm_start: WarmStart | None = None) -> GraspResult:
    """Plan a grasp with the named method (one of :data:`METHODS`; ValueError otherwise).

    ``control`` (optional) makes the plan cooperatively cancellable and reports progress (see
    :class:`PlanControl`); ``None`` runs to the end without callbacks. ``warm_start`` (the SCP planners of
    :data:`~gpis_grasp_ros.core.planners.warm_start.WARM_METHODS` only; ValueError otherwise) starts SCP at a
    previous plan's optima (:class:`~gpis_grasp_ros.core.planners.warm_start.WarmStart`).
    """
    planner = _PLANNERS.get(method)
    if planner is None:
        raise ValueError(f'unknown grasp planner {method!r}; valid names: {", ".join(METHODS)}')
    if warm_start is not None and method not in WARM_METHODS:
        raise ValueError(f'{method} samples its candidates and takes no warm start; the SCP planners do: '
                         f'{", ".join(WARM_METHODS)}')
    return planner(posterior, params, seed, control, warm_start)
