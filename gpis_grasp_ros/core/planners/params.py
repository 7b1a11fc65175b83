"""Settings of the grasp planners (:class:`PlannerParams`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from gpis_grasp_ros.core.gripper import GripperParams

#: Default λ of eq. 4/6, per m² of SDF variance at the two contacts (= 0.05 per mm²): chosen by cross-validation
#: with ``gpis-grasp tune`` (docs/planning.md, "Resolution and λ"). In physical units, so the penalty of a grasp
#: does not change when the planning grid is refined.
UNCERTAINTY_PENALTY = 5.0e4


@dataclass(frozen=True)
class PlannerParams:
    """Planner settings. Lengths in metres: nothing here depends on the planning grid."""

    gripper: GripperParams = field(default_factory=GripperParams)
    n_initial_grasps: int = 20  # N_g (restarts of GP-GPIS-OPT, GP-D and GP-U)
    n_grasp_samples: int = 1000  # K heuristic candidates of GP-M / GP-P
    n_shape_samples: int = 1000  # S shape samples for Monte-Carlo P_F
    uncertainty_penalty: float = UNCERTAINTY_PENALTY  # λ, per m² of SDF variance (eq. 4)
    antipodal_alpha: float = 0.5  # α of eq. 5
    antipodal_beta: float | None = None  # β of eq. 5; None -> cos(arctan γ)
    n_perturbations: int = 32  # K_p common-random-number perturbations for P̃_F (see docs/planning.md)
    smoothing_scale: float = 0.02  # Q_F scale of the sigmoid replacing 1[Q_F > 0] in P̃_F
    fd_step_m: float = 0.001  # finite-difference step of the SCP (m; P̃_F is smooth on the scale σ_g)
    trust_radius_m: float = 0.005  # initial SCP trust box half-width (m)
    trust_radius_min_m: float = 0.00025  # step tolerance: no improving step above it -> converged
    trust_radius_max_m: float = 0.015
    max_scp_iterations: int = 100  # QP solves per restart (a cap; runs stop at the convergence test)
    scp_step_tol_m: float = 0.00025  # step tolerance of the convergence test (∞-norm, m)
    scp_objective_tol: float = 1e-4  # objective tolerance: merit change of an accepted step
    scp_model_tol: float = 1e-5  # predicted merit improvement below which the model is stationary
    constraint_tol: float = 1e-3
    gp_p_adaptive: bool = True  # successive halving for GP-P
    gp_p_halving_rate: int = 4  # η
    gp_p_min_samples: int = 16  # samples per candidate in the first round
    max_sampling_rounds: int = 20  # heuristic batches tried when looking for valid initial grasps
    seed: int | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.uncertainty_penalty) and self.uncertainty_penalty >= 0):
            raise ValueError(f'uncertainty penalty λ must be a finite number >= 0 (per m² of SDF variance), '
                             f'got {self.uncertainty_penalty}')

    @property
    def beta(self) -> float:
        """β of eq. 5 (default cos(arctan γ))."""
        return self.gripper.beta if self.antipodal_beta is None else float(self.antipodal_beta)
