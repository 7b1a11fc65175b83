"""Parallel-jaw gripper parameters (paper section V-B): jaw width, opening, friction, σ_g, face lines.

Some lengths default to cells of the planning grid (σ_g, the contact-patch tolerance); :meth:`GripperParams.resolved`
fixes them in metres before the gripper closes on another grid (e.g. the 1 mm ground truth).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry


@dataclass(frozen=True)
class GripperParams:
    """Parallel-jaw gripper (paper V-B). Lengths in metres.

    ``friction_coef`` γ = 0.5 is a typical rubber-pad-on-plastic/cardboard value (the paper
    assumes a known constant γ without giving it); β = cos(arctan γ) of eq. 5 follows from it.
    ``position_noise`` σ_g (m) defaults to ``None``: then ``position_noise_cells`` × the grid
    resolution is used, i.e. the paper's σ_g² = 0.25 cells² (σ_g = 0.5 cell), which can only be
    resolved once the planning grid is known (see :meth:`sigma_g` and :meth:`resolved`).
    """

    jaw_width: float = 0.01  # w_j, m
    max_opening: float = 0.09  # w_g, m (about a PR2 gripper)
    friction_coef: float = 0.5  # γ, dimensionless
    position_noise: float | None = None  # σ_g, m; None -> position_noise_cells * resolution
    position_noise_cells: float = 0.5  # σ_g in cells of the planning grid (paper: σ_g² = 0.25)
    march_step_cells: float = 1.0  # sampling step of the sampled march (off-grid lines / exact_crossings=False)
    face_line_spacing_cells: float = 0.25  # max spacing of the face lines across a jaw face, cells
    contact_patch_cells: float = 0.5  # lines touching within this distance of the first touch form the patch
    contact_patch: float | None = None  # the same tolerance in m; None -> contact_patch_cells * resolution
    exact_crossings: bool = True  # exact zero crossings of the bilinear SDF (False: sampled march, step above)

    def __post_init__(self) -> None:
        if not self.jaw_width >= 0:
            raise ValueError(f'jaw width must be >= 0 m, got {self.jaw_width}')
        if not self.max_opening > 0:
            raise ValueError(f'max opening must be > 0 m, got {self.max_opening}')
        if not self.friction_coef > 0:
            raise ValueError(f'friction coefficient must be > 0, got {self.friction_coef}')
        if self.position_noise is not None and not self.position_noise >= 0:
            raise ValueError(f'position noise must be >= 0 m, got {self.position_noise}')
        if self.contact_patch is not None and not self.contact_patch > 0:
            raise ValueError(f'contact patch tolerance must be > 0 m, got {self.contact_patch}')
        if not (self.march_step_cells > 0 and self.face_line_spacing_cells > 0):
            raise ValueError('march step and face line spacing must be positive')

    @property
    def beta(self) -> float:
        """β = cos(arctan γ) of the antipodal constraints (eq. 5)."""
        return float(math.cos(math.atan(self.friction_coef)))

    @staticmethod
    def position_noise_from_cells(sigma_cells: float, geometry: GridGeometry) -> float:
        """σ_g in metres from σ_g in cells of ``geometry`` (paper: σ_g² = 0.25 cells² → 0.5)."""
        return float(sigma_cells) * geometry.resolution

    def sigma_g(self, geometry: GridGeometry) -> float:
        """Jaw positioning noise σ_g (m) for planning on ``geometry``."""
        if self.position_noise is not None:
            return float(self.position_noise)
        return self.position_noise_from_cells(self.position_noise_cells, geometry)

    def patch_cells(self, geometry: GridGeometry) -> float:
        """Contact-patch tolerance in cells of ``geometry`` (the grid the jaws close on)."""
        if self.contact_patch is not None:
            return float(self.contact_patch) / geometry.resolution
        return float(self.contact_patch_cells)

    def resolved(self, geometry: GridGeometry) -> GripperParams:
        """Copy with ``position_noise`` and ``contact_patch`` fixed in metres on the planning grid
        ``geometry`` (use before executing on another grid, e.g. the 1 mm ground truth)."""
        return replace(self, position_noise=self.sigma_g(geometry),
                       contact_patch=self.patch_cells(geometry) * geometry.resolution)

    def face_offsets(self, geometry: GridGeometry) -> np.ndarray:
        """Lateral offsets (m) of the march lines across a jaw face, centred on the jaw."""
        spacing = self.face_line_spacing_cells * geometry.resolution
        n = 1 if self.jaw_width <= 0 else int(math.ceil(self.jaw_width / spacing - 1e-9)) + 1
        if n == 1:
            return np.zeros(1)
        return np.linspace(-0.5 * self.jaw_width, 0.5 * self.jaw_width, n)

