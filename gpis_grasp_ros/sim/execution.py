"""Simulated execution of a planned grasp on the true shape (paper V-B): perturbed jaws closing on the true SDF,
force closure counted. Lives next to the simulator because it needs the ground truth the planners never see."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpis_grasp_ros.core.contacts import find_contacts, perturb_grasps
from gpis_grasp_ros.core.gpis import center_of_mass as sdf_center_of_mass
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.core.quality import grasp_quality, torque_scale
from gpis_grasp_ros.core.sdf_bank import SdfBank


@dataclass(frozen=True)
class ExecutionOutcome:
    """What ``trials`` simulated executions of one grasp did; every trial is counted once, in this order:
    ``too_wide`` (the commanded opening exceeds w_g: every trial), ``collision`` (a jaw starts inside the target
    or another object, or meets another object), ``missed`` (a jaw closes without meeting the target), ``slipped``
    (both jaws meet the target but the contacts are not in force closure, or a contact has no defined normal),
    ``closed`` (force closure)."""

    trials: int
    closed: int = 0
    collision: int = 0
    missed: int = 0
    slipped: int = 0
    too_wide: int = 0

    def describe(self) -> str:
        """E.g. ``12/20 in force closure (collision 5, missed 0, slipped 3)``."""
        failed = (f'commanded opening too wide: {self.too_wide}' if self.too_wide else
                  f'collision {self.collision}, missed {self.missed}, slipped {self.slipped}')
        return f'{self.closed}/{self.trials} in force closure ({failed})'


def execute_grasp_trials(true_sdf: np.ndarray, true_geometry: GridGeometry, jaw1: np.ndarray, jaw2: np.ndarray,
                         gripper: GripperParams, trials: int, rng: np.random.Generator,
                         center_of_mass: np.ndarray | None = None, obstacles: np.ndarray | None = None) -> int:
    """Number of force-closure successes of ``trials`` executions (:func:`execute_grasp_outcome`)."""
    return execute_grasp_outcome(true_sdf, true_geometry, jaw1, jaw2, gripper, trials, rng, center_of_mass,
                                 obstacles).closed


def execute_grasp_outcome(true_sdf: np.ndarray, true_geometry: GridGeometry, jaw1: np.ndarray, jaw2: np.ndarray,
                          gripper: GripperParams, trials: int, rng: np.random.Generator,
                          center_of_mass: np.ndarray | None = None,
                          obstacles: np.ndarray | None = None) -> ExecutionOutcome:
    """Outcome of ``trials`` executions of grasp (jaw1, jaw2) (m) on a true SDF.

    Each trial perturbs the jaws with σ_g (V-B), closes them on ``true_sdf`` (m, on
    ``true_geometry``, which may differ from the planning grid — everything is metric) and checks
    Q_F > 0 with normals from the true SDF's finite differences, with the same gripper, perturbation
    model and force-closure test as Monte-Carlo P_F (σ_g = ``gripper.position_noise``, m).
    ``center_of_mass`` (m) defaults to that of {true_sdf < 0}. A commanded opening above w_g
    fails every trial. ``obstacles`` (m, on ``true_geometry``): the signed distance to the other objects, which
    the jaws may neither start in nor close on (a trial that does fails), as in the planner's world.
    """
    sdf = np.asarray(true_sdf, dtype=np.float64)
    com = sdf_center_of_mass(sdf[None], true_geometry)[0] if center_of_mass is None else np.asarray(center_of_mass)
    return outcome_on_bank(SdfBank(sdf, true_geometry, obstacles=obstacles), com, torque_scale(sdf, true_geometry, com),
                           jaw1, jaw2, gripper, trials, rng)


def outcome_on_bank(bank: SdfBank, com: np.ndarray, rho: float, jaw1: np.ndarray, jaw2: np.ndarray,
                    gripper: GripperParams, trials: int, rng: np.random.Generator) -> ExecutionOutcome:
    """:func:`execute_grasp_outcome` on a prepared truth: its bank (grid 0, with the obstacles), centre of mass and
    torque scale ρ (m), built once for many grasps."""
    jaw1 = np.asarray(jaw1, dtype=np.float64).reshape(2)
    jaw2 = np.asarray(jaw2, dtype=np.float64).reshape(2)
    trials = max(int(trials), 0)
    if trials == 0:
        return ExecutionOutcome(0)
    if np.linalg.norm(jaw2 - jaw1) > gripper.max_opening * (1 + 1e-9) + 1e-12:
        return ExecutionOutcome(trials, too_wide=trials)
    eps = rng.standard_normal((trials, 2, 2))
    g1, g2 = perturb_grasps(jaw1, jaw2, eps, gripper.sigma_g)
    con = find_contacts(bank, g1, g2, gripper, check_opening=False)
    closed = grasp_quality(con, com, gripper, rho) > 0
    collision = ~closed & (con.start_inside | (con.on_obstacle if con.on_obstacle is not None else False))
    missed = ~closed & ~collision & con.no_contact
    return ExecutionOutcome(trials, closed=int(closed.sum()), collision=int(collision.sum()),
                            missed=int(missed.sum()), slipped=int((~closed & ~collision & ~missed).sum()))
