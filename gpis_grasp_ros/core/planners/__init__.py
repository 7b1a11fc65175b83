"""Grasp planners on a GPIS posterior (paper sections VI and VII-B); :func:`plan` runs one by name.

* ``'gp-m'`` GP-M: best Q_F on the mean SDF among K heuristic candidates.
* ``'gp-p'`` GP-P: best Monte-Carlo P_F among the K candidates (successive halving by default).
* ``'gp-d'`` / ``'gp-u'`` GP-D / GP-U: P̃_F on the mean maximised by SCP, without / with the uncertainty penalty.
* ``'gp-gpis-opt'`` GP-GPIS-OPT, Algorithm 1: SCP on eq. 6 with the antipodal constraints from N_g starts.
* ``'gp-gpis-opt-reranked'`` (beyond the paper): GP-GPIS-OPT's local optima re-scored by Monte-Carlo P_F.
* ``'gp-d-single'`` / ``'gp-u-single'`` (beyond the paper): GP-D / GP-U from one initial grasp.

Replanning: the SCP planners take a previous plan's optima as starts (:class:`WarmStart`).

The design decisions where the paper is silent are in ``docs/planning.md``.
"""

from gpis_grasp_ros.core.planners.baselines import (
    plan_gp_d,
    plan_gp_d_single,
    plan_gp_m,
    plan_gp_p,
    plan_gp_u,
    plan_gp_u_single,
    select_by_monte_carlo,
)
from gpis_grasp_ros.core.planners.context import PlanningContext, evaluation_samples
from gpis_grasp_ros.core.planners.gp_gpis_opt import SCP_EVAL_CHUNK, plan_gp_gpis_opt, plan_gp_gpis_opt_reranked
from gpis_grasp_ros.core.planners.objective import MeanGraspObjective
from gpis_grasp_ros.core.planners.params import PlannerParams
from gpis_grasp_ros.core.planners.registry import METHODS, plan
from gpis_grasp_ros.core.planners.result import GraspResult, PlanControl, PlanProgress, RestartInfo
from gpis_grasp_ros.core.planners.sampling import mean_surface_points, sample_heuristic_grasps, sample_valid_grasps
from gpis_grasp_ros.core.planners.warm_start import WARM_METHODS, WarmStart

__all__ = [
    'METHODS', 'SCP_EVAL_CHUNK', 'WARM_METHODS', 'WarmStart', 'GraspResult', 'MeanGraspObjective', 'PlanControl',
    'PlanProgress', 'PlannerParams', 'PlanningContext', 'RestartInfo', 'evaluation_samples', 'mean_surface_points',
    'plan', 'plan_gp_d', 'plan_gp_d_single', 'plan_gp_gpis_opt', 'plan_gp_gpis_opt_reranked', 'plan_gp_m',
    'plan_gp_p', 'plan_gp_u', 'plan_gp_u_single', 'sample_heuristic_grasps', 'sample_valid_grasps',
    'select_by_monte_carlo',
]
