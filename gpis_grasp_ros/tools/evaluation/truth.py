"""The ground truth of a scene prepared for evaluation, and the planning-grid → true-grid transform."""

from __future__ import annotations

import math

import cv2
import numpy as np

from gpis_grasp_ros.core.contacts import find_contacts
from gpis_grasp_ros.core.gpis import center_of_mass
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.core.quality import ferrari_canny_l1, torque_scale
from gpis_grasp_ros.core.sdf_bank import SdfBank, bilinear
from gpis_grasp_ros.sim.execution import ExecutionOutcome, outcome_on_bank


class TrueShape:
    """Ground truth of a bag prepared for evaluation: SDF bank (m), centre of mass (m) and ρ (m).

    **Frames.** The true SDF lives on its own grid (``geometry``, 1 mm, in the table frame of the
    simulator), the planner's jaws on the planning grid (``plan_geometry``, the table frame fitted
    by segmentation). With a tilted head camera the two differ by a rigid motion, so every point
    goes planning grid → sensor frame → true grid (:meth:`to_true`), as ``gripper_sim_node`` does;
    for the top-down bags this is the identity to ~1e-5 m. The centre of mass is that of
    {sdf_true < 0} in the true grid's frame (uniform density; the bag's
    ``ground_truth/center_of_mass`` message is in the camera frame).

    ``obstacles`` (on ``geometry``, m): the signed distance to the other objects of the scene; executions and
    Q_N close the jaws in ``min(sdf, obstacles)`` and fail on a contact with one (the planner's world).
    """

    def __init__(self, sdf: np.ndarray, geometry: GridGeometry, plan_geometry: GridGeometry | None = None,
                 obstacles: np.ndarray | None = None) -> None:
        self.sdf = np.asarray(sdf, dtype=np.float64)
        self.geometry = geometry
        self.plan_geometry = plan_geometry
        self.obstacles = None if obstacles is None else np.asarray(obstacles, dtype=np.float64)
        self.com = center_of_mass(self.sdf[None], geometry)[0]
        self.rho = torque_scale(self.sdf, geometry, self.com)
        self.bank = SdfBank(self.sdf, geometry, obstacles=self.obstacles)

    def aligned(self) -> bool:
        """Whether the planning grid's table frame is the true grid's (same rotation, same height)."""
        p = self.plan_geometry
        return p is None or (np.allclose(p.rotation_matrix, self.geometry.rotation_matrix)
                             and math.isclose(p.z, self.geometry.z))

    def to_true(self, xy: np.ndarray, snap_aligned: bool = False) -> np.ndarray:
        """Planning-grid points ``(..., 2)`` (m) → the true grid's (x, y) (m), through the sensor frame.

        ``snap_aligned``: the identity map when the two table frames coincide (:meth:`aligned`), as the
        dataset evaluation does; otherwise every point goes through the sensor frame."""
        xy = np.asarray(xy, dtype=np.float64)
        if self.plan_geometry is None or (snap_aligned and self.aligned()):
            return xy
        return self.geometry.from_sensor(self.plan_geometry.to_sensor(xy, 0.0))[0]

    def to_plan(self, xy: np.ndarray) -> np.ndarray:
        """True-grid points ``(..., 2)`` (m) → planning-grid (x, y) (m)."""
        xy = np.asarray(xy, dtype=np.float64)
        if self.plan_geometry is None:
            return xy
        return self.plan_geometry.from_sensor(self.geometry.to_sensor(xy, 0.0))[0]

    def values_at(self, xy_plan: np.ndarray) -> np.ndarray:
        """True SDF (m) at planning-grid points ``(..., 2)``."""
        return bilinear(self.sdf, self.geometry, self.to_true(xy_plan))

    def obstacles_at(self, xy_plan: np.ndarray) -> np.ndarray | None:
        """The truth's obstacle distance (m) at planning-grid points ``(..., 2)``; None without obstacles."""
        if self.obstacles is None:
            return None
        return bilinear(self.obstacles, self.geometry, self.to_true(xy_plan))

    def nominal_quality(self, jaw1: np.ndarray, jaw2: np.ndarray, gripper: GripperParams) -> tuple[float, str]:
        """Q_N: Ferrari–Canny L1 of the unperturbed grasp (planning-grid m) on the true shape, and a status.

        Status 'ok' (Q_N may still be <= 0: no force closure), else 'no_contact', 'start_inside',
        'opening_exceeded' or 'on_obstacle' (a jaw meets another object) with Q_N = NaN.
        """
        j1 = np.asarray(jaw1, dtype=np.float64).reshape(1, 2)
        j2 = np.asarray(jaw2, dtype=np.float64).reshape(1, 2)
        if not (np.all(np.isfinite(j1)) and np.all(np.isfinite(j2))):
            return float('nan'), 'no_grasp'
        con = find_contacts(self.bank, self.to_true(j1), self.to_true(j2), gripper)
        for name in ('opening_exceeded', 'start_inside', 'no_contact', 'on_obstacle'):
            if bool(getattr(con, name)[0]):
                return float('nan'), name
        q = ferrari_canny_l1(con.c1, con.c2, con.n1, con.n2, self.com, gripper.friction_coef, self.rho)
        return float(q[0]), 'ok'

    def execute(self, jaw1: np.ndarray, jaw2: np.ndarray, gripper: GripperParams, trials: int,
                rng: np.random.Generator, center_of_mass: np.ndarray | None = None,
                snap_aligned: bool = False) -> int:
        """Successes of ``trials`` simulated executions of a planning-grid grasp (:meth:`execute_outcome`)."""
        return self.execute_outcome(jaw1, jaw2, gripper, trials, rng, center_of_mass, snap_aligned).closed

    def execute_outcome(self, jaw1: np.ndarray, jaw2: np.ndarray, gripper: GripperParams, trials: int,
                        rng: np.random.Generator, center_of_mass: np.ndarray | None = None,
                        snap_aligned: bool = False) -> ExecutionOutcome:
        """What ``trials`` simulated executions (:func:`execute_grasp_outcome`) of a planning-grid grasp did.

        ``center_of_mass`` (true grid, m) replaces that of {sdf < 0} (e.g. the scene's recorded one);
        ``snap_aligned`` as in :meth:`to_true`."""
        com = self.com if center_of_mass is None else np.asarray(center_of_mass, dtype=np.float64)
        rho = self.rho if center_of_mass is None else torque_scale(self.sdf, self.geometry, com)
        return outcome_on_bank(self.bank, com, rho, self.to_true(jaw1, snap_aligned),
                               self.to_true(jaw2, snap_aligned), gripper, trials, rng)

    def outline(self) -> list[np.ndarray]:
        """Boundary polylines of {sdf < 0} in planning-grid metres (outer outlines and holes)."""
        mask = (self.sdf < 0).astype(np.uint8)
        contours, _ = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
        return [self.to_plan(self.geometry.to_metric(c.reshape(-1, 2).astype(np.float64)))
                for c in contours if len(c) >= 3]

    def iou_on(self, geometry: GridGeometry, mean_sdf: np.ndarray) -> float:
        """IoU of {mean_sdf < 0} with the true shape sampled at the cell centres of ``geometry``."""
        true_inside = self.values_at(geometry.cell_centers()) < 0
        mean_inside = np.asarray(mean_sdf) < 0
        union = np.count_nonzero(true_inside | mean_inside)
        return float(np.count_nonzero(true_inside & mean_inside) / union) if union else float('nan')

    def iou_fine(self, geometry: GridGeometry, mean_sdf: np.ndarray) -> float:
        """IoU of {mean_sdf < 0} with the true shape on the *true* grid's cells (1 mm for the bags).

        ``mean_sdf`` (on ``geometry``, the planning grid) is interpolated bilinearly at every true cell's centre;
        true cells beyond the planning grid's outer cell centres are free. Unlike :meth:`iou_on` this counts the
        parts of the object the planning grid does not cover, and does not quantise a shape narrower than a
        planning cell into whole cells."""
        xy = self.to_plan(self.geometry.cell_centers())
        lo = np.array([geometry.origin_x, geometry.origin_y]) + 0.5 * geometry.resolution
        hi = lo + (np.array(geometry.shape[::-1]) - 1) * geometry.resolution
        covered = np.all((xy >= lo) & (xy <= hi), axis=-1)
        mean_inside = np.zeros(covered.shape, dtype=bool)
        mean_inside[covered] = bilinear(np.asarray(mean_sdf, dtype=np.float64), geometry, xy[covered]) < 0
        true_inside = self.sdf < 0
        union = np.count_nonzero(true_inside | mean_inside)
        return float(np.count_nonzero(true_inside & mean_inside) / union) if union else float('nan')
