"""Parallel-jaw gripper parameters (paper section V-B): jaw width, opening, friction, σ_g, contact patch.

The one execution model: every physical length is in metres, so the gripper closes the same way on the planning
grid (Monte-Carlo P_F), on the 1 mm ground truth (simulated execution) and in the nodes. Only the numerical
discretisation of the march (step, face-line spacing) is in cells of the grid being closed on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry


@dataclass(frozen=True)
class GripperParams:
    """Parallel-jaw gripper (paper V-B). Lengths in metres.

    ``friction_coef`` γ = 0.5 is a typical rubber-pad-on-plastic/cardboard value (the paper
    assumes a known constant γ without giving it); β = cos(arctan γ) of eq. 5 follows from it.
    ``position_noise`` σ_g = 3 mm per axis and jaw: the absolute accuracy of a commanded pose on
    the table (arm accuracy 1–2 mm plus a camera-to-arm calibration error of 2–3 mm, root-sum-square),
    not the paper's 0.5 planning cell, which tied the gripper to the grid. The relative draw of the
    second jaw (:func:`~gpis_grasp_ros.core.contacts.perturb_grasps`) also rotates the jaw axis by
    about σ_g / width: that is the orientation noise. ``contact_patch`` = 2 mm: the pad compliance
    within which the face lines touching after the first form one contact patch (docs/planning.md).
    """

    jaw_width: float = 0.01  # w_j, m
    max_opening: float = 0.09  # w_g, m (about a PR2 gripper)
    friction_coef: float = 0.5  # γ, dimensionless
    position_noise: float = 0.003  # σ_g, m per axis (jaw placement error on the table)
    march_step_cells: float = 1.0  # sampling step of the sampled march (off-grid lines / exact_crossings=False)
    face_line_spacing_cells: float = 0.25  # max spacing of the face lines across a jaw face, cells
    contact_patch: float = 0.002  # m: lines touching within this distance of the first touch form the patch
    exact_crossings: bool = True  # exact zero crossings of the bilinear SDF (False: sampled march, step above)

    def __post_init__(self) -> None:
        if not self.jaw_width >= 0:
            raise ValueError(f'jaw width must be >= 0 m, got {self.jaw_width}')
        if not self.max_opening > 0:
            raise ValueError(f'max opening must be > 0 m, got {self.max_opening}')
        if not self.friction_coef > 0:
            raise ValueError(f'friction coefficient must be > 0, got {self.friction_coef}')
        if not (math.isfinite(self.position_noise) and self.position_noise >= 0):
            raise ValueError(f'position noise must be >= 0 m, got {self.position_noise}')
        if not (math.isfinite(self.contact_patch) and self.contact_patch > 0):
            raise ValueError(f'contact patch tolerance must be > 0 m, got {self.contact_patch}')
        if not (self.march_step_cells > 0 and self.face_line_spacing_cells > 0):
            raise ValueError('march step and face line spacing must be positive')

    @property
    def beta(self) -> float:
        """β = cos(arctan γ) of the antipodal constraints (eq. 5)."""
        return float(math.cos(math.atan(self.friction_coef)))

    @property
    def sigma_g(self) -> float:
        """Jaw positioning noise σ_g (m), the same on every grid."""
        return float(self.position_noise)

    def patch_cells(self, geometry: GridGeometry) -> float:
        """Contact-patch tolerance in cells of ``geometry`` (the grid the jaws close on)."""
        return float(self.contact_patch) / geometry.resolution

    def face_offsets(self, geometry: GridGeometry) -> np.ndarray:
        """Lateral offsets (m) of the march lines across a jaw face, centred on the jaw."""
        spacing = self.face_line_spacing_cells * geometry.resolution
        n = 1 if self.jaw_width <= 0 else int(math.ceil(self.jaw_width / spacing - 1e-9)) + 1
        if n == 1:
            return np.zeros(1)
        return np.linspace(-0.5 * self.jaw_width, 0.5 * self.jaw_width, n)

