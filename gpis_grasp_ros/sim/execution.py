"""Simulated execution of a planned grasp on the true shape (paper V-B): perturbed jaws closing on the true SDF,
force closure counted. Lives next to the simulator because it needs the ground truth the planners never see."""

from __future__ import annotations

import numpy as np

from gpis_grasp_ros.core.contacts import find_contacts, perturb_grasps
from gpis_grasp_ros.core.gpis import center_of_mass as sdf_center_of_mass
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.core.quality import grasp_quality, torque_scale
from gpis_grasp_ros.core.sdf_bank import SdfBank


def execute_grasp_trials(true_sdf: np.ndarray, true_geometry: GridGeometry, jaw1: np.ndarray, jaw2: np.ndarray,
                         gripper: GripperParams, trials: int, rng: np.random.Generator,
                         center_of_mass: np.ndarray | None = None, obstacles: np.ndarray | None = None) -> int:
    """Number of force-closure successes of ``trials`` executions of grasp (jaw1, jaw2) (m) on a true SDF.

    Each trial perturbs the jaws with σ_g (V-B), closes them on ``true_sdf`` (m, on
    ``true_geometry``, which may differ from the planning grid — everything is metric) and checks
    Q_F > 0 with normals from the true SDF's finite differences, with the same gripper, perturbation
    model and force-closure test as Monte-Carlo P_F (σ_g = ``gripper.position_noise``, m).
    ``center_of_mass`` (m) defaults to that of {true_sdf < 0}. A commanded opening above w_g
    fails every trial. ``obstacles`` (m, on ``true_geometry``): the signed distance to the other objects, which
    the jaws may neither start in nor close on (a trial that does fails), as in the planner's world.
    """
    jaw1 = np.asarray(jaw1, dtype=np.float64).reshape(2)
    jaw2 = np.asarray(jaw2, dtype=np.float64).reshape(2)
    if trials <= 0 or np.linalg.norm(jaw2 - jaw1) > gripper.max_opening * (1 + 1e-9) + 1e-12:
        return 0
    sdf = np.asarray(true_sdf, dtype=np.float64)
    bank = SdfBank(sdf, true_geometry, obstacles=obstacles)
    com = sdf_center_of_mass(sdf[None], true_geometry)[0] if center_of_mass is None else np.asarray(center_of_mass)
    rho = torque_scale(sdf, true_geometry, com)
    eps = rng.standard_normal((int(trials), 2, 2))
    g1, g2 = perturb_grasps(jaw1, jaw2, eps, gripper.sigma_g)
    con = find_contacts(bank, g1, g2, gripper, check_opening=False)
    q = grasp_quality(con, com, gripper, rho)
    return int(np.count_nonzero(q > 0))
