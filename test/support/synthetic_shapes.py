"""Analytic shapes and hand-built GPIS posteriors for the contact, quality and planner tests.

SDFs are in metres on a :class:`GridGeometry`; a posterior's joint covariance is
``Σ = D C D`` with ``D = diag(std)`` a spatially varying standard deviation (m) and ``C`` a
squared-exponential correlation over the grid, so samples are spatially correlated like those of
a real GPIS; ``cov_factor = D V sqrt(Λ)`` from the eigendecomposition ``C = V Λ Vᵀ`` (robust where
a Cholesky factorisation of a smooth kernel matrix would need jitter).
"""

from __future__ import annotations

import numpy as np

from gpis_grasp_ros.core.gpis import GpisPosterior, KernelParams
from gpis_grasp_ros.core.grid import GridGeometry


def make_geometry(n: int = 25, resolution: float = 0.005, origin: tuple[float, float] = (0.0, 0.0)) -> GridGeometry:
    """``n x n`` grid of ``resolution`` m cells with its corner at ``origin`` (m)."""
    return GridGeometry(origin[0], origin[1], resolution, n, n)


def disc_sdf(geometry: GridGeometry, center: tuple[float, float], radius: float) -> np.ndarray:
    """Exact SDF (m) of a disc."""
    p = geometry.cell_centers()
    return np.hypot(p[..., 0] - center[0], p[..., 1] - center[1]) - radius


def rectangle_sdf(geometry: GridGeometry, center: tuple[float, float], half_size: tuple[float, float],
                  angle: float = 0.0) -> np.ndarray:
    """Exact SDF (m) of a rectangle with half extents ``half_size`` rotated by ``angle`` (rad)."""
    p = geometry.cell_centers() - np.asarray(center)
    c, s = np.cos(angle), np.sin(angle)
    local = np.stack([c * p[..., 0] + s * p[..., 1], -s * p[..., 0] + c * p[..., 1]], axis=-1)
    q = np.abs(local) - np.asarray(half_size)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    inside = np.minimum(np.max(q, axis=-1), 0.0)
    return outside + inside


def union(*sdfs: np.ndarray) -> np.ndarray:
    """Union of shapes (min of SDFs; exact outside, a lower bound of the distance inside)."""
    return np.minimum.reduce(sdfs)


def subtract(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Shape ``a`` minus shape ``b`` (max(a, −b))."""
    return np.maximum(a, -b)


def notched_rectangle_sdf(geometry: GridGeometry, center: tuple[float, float], half_size: tuple[float, float],
                          notch_center: tuple[float, float], notch_half: tuple[float, float]) -> np.ndarray:
    """Rectangle with a rectangular notch cut out of it."""
    return subtract(rectangle_sdf(geometry, center, half_size), rectangle_sdf(geometry, notch_center, notch_half))


def gradient_of(sdf: np.ndarray, geometry: GridGeometry) -> np.ndarray:
    """(H, W, 2) gradient (d/dx, d/dy) of a grid by central differences."""
    gy, gx = np.gradient(sdf, geometry.resolution)
    return np.stack([gx, gy], axis=-1)


def correlation_factor(geometry: GridGeometry, length_scale: float, rel_tol: float = 1e-9) -> np.ndarray:
    """Factor F (H*W, r) with F Fᵀ ≈ SE correlation exp(−d²/(2 l²)) over the cell centres."""
    p = geometry.cell_centers().reshape(-1, 2)
    d2 = np.sum((p[:, None, :] - p[None, :, :]) ** 2, axis=-1)
    corr = np.exp(-0.5 * d2 / length_scale ** 2)
    lam, vec = np.linalg.eigh(corr)
    keep = lam > rel_tol * lam.max()
    return vec[:, keep] * np.sqrt(lam[keep])


def smooth_region_weight(region_sdf: np.ndarray, width: float) -> np.ndarray:
    """≈1 inside a region (its SDF < 0), ≈0 farther than ``width`` (m) outside, smooth in between."""
    return 1.0 / (1.0 + np.exp(np.clip(4.0 * region_sdf / width, -50, 50)))


def make_posterior(mean: np.ndarray, geometry: GridGeometry, std: np.ndarray | float,
                   length_scale: float | None = None, gradient: np.ndarray | None = None) -> GpisPosterior:
    """GpisPosterior with the given mean (m), marginal std (m) and SE-correlated joint covariance."""
    std = np.broadcast_to(np.asarray(std, dtype=np.float64), geometry.shape)
    if length_scale is None:
        length_scale = 3.0 * geometry.resolution
    factor = std.reshape(-1, 1) * correlation_factor(geometry, length_scale)
    variance = np.sum(factor ** 2, axis=1).reshape(geometry.shape)
    grad = gradient_of(mean, geometry) if gradient is None else gradient
    params = KernelParams(signal_variance=float(np.max(std) ** 2), length_scale=length_scale,
                          prior_mean=-float(geometry.resolution))
    return GpisPosterior(geometry=geometry, mean=np.asarray(mean, dtype=np.float64), variance=variance,
                         gradient=grad, cov_factor=factor, params=params)


def certain_rectangle_posterior(geometry: GridGeometry | None = None, std_cells: float = 0.1) -> GpisPosterior:
    """A well-observed 30 mm x 20 mm rectangle in the middle of a 25 x 25 grid (low variance everywhere)."""
    g = make_geometry() if geometry is None else geometry
    cx, cy = g.origin_x + g.size_m[0] / 2, g.origin_y + g.size_m[1] / 2
    mean = rectangle_sdf(g, (cx, cy), (0.015, 0.01))
    return make_posterior(mean, g, std_cells * g.resolution)


def transparent_part_posterior(geometry: GridGeometry | None = None, low_std_cells: float = 0.1,
                               high_std_cells: float = 3.0) -> tuple[GpisPosterior, np.ndarray]:
    """Object A-like scene: a certain body plus a large "transparent" part seen by neither sensor.

    The mean SDF includes the transparent part (a GPIS with a negative prior mean leans to
    "object" where nothing was measured, paper III-B) but its variance there is high. Returns the
    posterior and the boolean (H, W) mask of the uncertain part (for assertions).
    """
    g = make_geometry() if geometry is None else geometry
    ox, oy = g.origin_x, g.origin_y
    body = rectangle_sdf(g, (ox + 0.040, oy + 0.0625), (0.012, 0.008))
    part = rectangle_sdf(g, (ox + 0.078, oy + 0.0625), (0.028, 0.030))
    mean = union(body, part)
    weight = smooth_region_weight(part - 0.002, 2 * g.resolution) * (body > 0.004)
    std = g.resolution * (low_std_cells + (high_std_cells - low_std_cells) * weight)
    return make_posterior(mean, g, std), (part < 0) & (body > 0)
