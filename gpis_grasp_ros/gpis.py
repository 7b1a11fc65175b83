"""Gaussian process implicit surfaces (paper sections III-A and V-A).

CONTRACT (other modules rely on it; extend, do not rename):

``GpisPosterior`` holds a GPIS posterior on the cells of a :class:`~gpis_grasp_ros.grid.GridGeometry`:

* ``mean``       (H, W) float64, posterior mean signed distance mu (m), eq. 1
* ``variance``   (H, W) float64, posterior marginal variance sigma^2 (m^2), eq. 2
* ``gradient``   (H, W, 2) float64, d mu / dx and d mu / dy (dimensionless), kernel derivative
* ``cov_factor`` (H*W, r) float64, L with joint posterior covariance Sigma ~= L L^T over the
  row-major flattened grid; used by :meth:`GpisPosterior.sample`
* ``params``     :class:`KernelParams` (C in m^2, l in m, constant prior mean in m)
* training data: ``train_xy`` (n, 2) m, ``train_y`` (n,) m, ``train_noise`` (n,) m^2
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .grid import GridGeometry


@dataclass(frozen=True)
class KernelParams:
    """Squared-exponential kernel k = C exp(-|xi - xj|^2 / (2 l^2)) and constant prior mean."""

    signal_variance: float  # C, m^2
    length_scale: float  # l, m
    prior_mean: float  # m (negative: unobserved space leans to "object")


@dataclass
class GpisPosterior:
    """GPIS posterior on a metric grid (see the module docstring for the contract)."""

    geometry: GridGeometry
    mean: np.ndarray
    variance: np.ndarray
    gradient: np.ndarray
    cov_factor: np.ndarray
    params: KernelParams
    train_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    train_y: np.ndarray = field(default_factory=lambda: np.zeros(0))
    train_noise: np.ndarray = field(default_factory=lambda: np.zeros(0))
    jitter: float = 0.0
    hyperparameters_optimized: bool = False

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` joint posterior SDF samples f ~ N(mu, Sigma) on the grid, shape (n, H, W), m."""
        h, w = self.geometry.shape
        eps = rng.standard_normal((self.cov_factor.shape[1], n))
        flat = (self.cov_factor @ eps).T + self.mean.reshape(1, -1)
        return flat.reshape(n, h, w)

    def center_of_mass(self) -> np.ndarray:
        """Centre of mass (x, y) in m of the mean shape {mu < 0}, uniform density (section V)."""
        return center_of_mass(self.mean[None], self.geometry)[0]


def center_of_mass(sdfs: np.ndarray, geometry: GridGeometry) -> np.ndarray:
    """Centres of mass (m) of the shapes {f < 0} of SDFs ``(n, H, W)`` → ``(n, 2)``.

    Uniform mass density over interior cells; an SDF with no interior cell gets the grid centre.
    """
    inside = (np.asarray(sdfs) < 0).astype(np.float64)
    centers = geometry.cell_centers()
    mass = inside.sum(axis=(1, 2))
    safe = np.where(mass > 0, mass, 1.0)
    com = np.einsum('nij,ijk->nk', inside, centers) / safe[:, None]
    grid_center = centers.reshape(-1, 2).mean(axis=0)
    return np.where(mass[:, None] > 0, com, grid_center[None, :])
