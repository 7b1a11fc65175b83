"""The training observations of a GPIS: SDF values and SDF gradient components (derivative observations).

One set holds both kinds, values first, so that the kernel, the hyperparameter search and the
conditioning see a single list of linear functionals L_i f of the same GP (Solak et al.).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.sdf import sdf_gradient

# Observation types: a value f(x) or a gradient component d f / d x, d f / d y (Solak et al.)
VALUE, GRAD_X, GRAD_Y = 0, 1, 2


@dataclass(frozen=True)
class _Observations:
    """Training observations of f: values and gradient components, values first.

    ``kind`` is VALUE, GRAD_X or GRAD_Y; ``px`` / ``py`` the derivative order in x / y (0 or 1).
    """

    xy: np.ndarray  # (N, 2) m
    kind: np.ndarray  # (N,) int
    y: np.ndarray  # (N,) m for values, dimensionless for gradients
    noise: np.ndarray  # (N,) without jitter
    n_values: int

    @staticmethod
    def build(train_xy: np.ndarray, train_y: np.ndarray, train_noise: np.ndarray, grad_xy: np.ndarray | None = None,
              grad_axis: np.ndarray | None = None, grad_y: np.ndarray | None = None,
              grad_noise: np.ndarray | None = None) -> _Observations:
        train_xy = np.asarray(train_xy, dtype=np.float64).reshape(-1, 2)
        n = train_xy.shape[0]
        grad_xy = np.zeros((0, 2)) if grad_xy is None else np.asarray(grad_xy, dtype=np.float64).reshape(-1, 2)
        k = grad_xy.shape[0]
        grad_axis = np.zeros(0, dtype=np.int64) if grad_axis is None else np.asarray(grad_axis).ravel()
        grad_y = np.zeros(0) if grad_y is None else np.asarray(grad_y, dtype=np.float64).ravel()
        grad_noise = np.zeros(0) if grad_noise is None else np.asarray(grad_noise, dtype=np.float64).ravel()
        if grad_axis.shape != (k,) or grad_y.shape != (k,) or grad_noise.shape != (k,):
            raise ValueError(f'gradient observations disagree: {k} positions, {grad_axis.size} axes, '
                             f'{grad_y.size} values, {grad_noise.size} noise variances')
        if k and not np.all((grad_axis == 0) | (grad_axis == 1)):
            raise ValueError('gradient observation axes must be 0 (d/dx) or 1 (d/dy)')
        kind = np.concatenate([np.full(n, VALUE), np.where(grad_axis == 0, GRAD_X, GRAD_Y)]).astype(np.int64)
        return _Observations(np.ascontiguousarray(np.vstack([train_xy, grad_xy])), kind,
                             np.concatenate([np.asarray(train_y, dtype=np.float64).ravel(), grad_y]),
                             np.concatenate([np.asarray(train_noise, dtype=np.float64).ravel(), grad_noise]), n)

    @property
    def size(self) -> int:
        return self.kind.size

    @property
    def px(self) -> np.ndarray:
        return (self.kind == GRAD_X).astype(np.int64)

    @property
    def py(self) -> np.ndarray:
        return (self.kind == GRAD_Y).astype(np.int64)

    @property
    def has_gradients(self) -> bool:
        return self.size > self.n_values

    def subset(self, idx: np.ndarray) -> _Observations:
        idx = np.sort(idx)
        return _Observations(self.xy[idx], self.kind[idx], self.y[idx], self.noise[idx],
                             int(np.sum(self.kind[idx] == VALUE)))


def _validate_training(obs: _Observations) -> None:
    if obs.n_values == 0:
        raise ValueError('no training data: every cell is missing, the GPIS would be the prior only')
    if not (np.all(np.isfinite(obs.xy)) and np.all(np.isfinite(obs.y)) and np.all(np.isfinite(obs.noise))):
        raise ValueError('training data contain non-finite values')
    if np.any(obs.noise < 0):
        raise ValueError('training noise variances must be >= 0 (m^2 for values, 1 for gradients)')


def _observations_from(train_xy: np.ndarray, train_y: np.ndarray, train_noise: np.ndarray,
                       gradients: tuple | None) -> _Observations:
    train_xy = np.asarray(train_xy, dtype=np.float64)
    if train_xy.ndim != 2 or train_xy.shape[1] != 2:
        raise ValueError(f'train_xy must have shape (n, 2), got {train_xy.shape}')
    n = train_xy.shape[0]
    train_y, train_noise = np.asarray(train_y, dtype=np.float64), np.asarray(train_noise, dtype=np.float64)
    if train_y.shape != (n,) or train_noise.shape != (n,):
        raise ValueError(f'train_y and train_noise must have shape ({n},), got {train_y.shape} and '
                         f'{train_noise.shape}')
    obs = _Observations.build(train_xy, train_y, train_noise, *(gradients or ()))
    _validate_training(obs)
    return obs


def gradient_observations(sdf_m: np.ndarray, noise_variance_m2: np.ndarray, train_mask: np.ndarray,
                          geometry: GridGeometry, base_variance: float = 0.01
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """SDF gradient observations for the GPIS (section III, derivative observations) and their noise.

    Each component is the central difference of the grid SDF (:func:`~gpis_grasp_ros.core.sdf.sdf_gradient`)
    at a training cell whose two neighbours along that axis are training cells too. Its noise
    variance (dimensionless) is the sum of three independent errors:

    * ``base_variance`` g0: the discretisation error of an EDT gradient component away from kinks
      (default 0.01, docs/gpis-model.md, Gradient observations).
    * (1 - |g|)^2 with |g| the central-difference gradient's norm (both components defined): an SDF
      has |grad f| = 1 wherever it is differentiable, so a norm far from 1 marks a kink (medial
      axis, corners) where the gradient is not defined and the difference is unreliable.
    * (s_-^2 + s_+^2) / (4 res^2): the sensing noise of the two SDF values in the difference.

    Returns:
        ``(xy (k, 2) m, axis (k,) 0 = d/dx 1 = d/dy, gradient (k,), noise variance (k,))``.
    """
    res = geometry.resolution
    grad, defined = sdf_gradient(sdf_m, res, train_mask)
    noise = np.asarray(noise_variance_m2, dtype=np.float64)
    both = defined.all(axis=-1)
    kink = np.where(both, (1.0 - np.linalg.norm(grad, axis=-1)) ** 2, 0.0)
    prop = np.zeros(grad.shape)
    prop[:, 1:-1, 0] = (noise[:, :-2] + noise[:, 2:]) / (4.0 * res * res)
    prop[1:-1, :, 1] = (noise[:-2, :] + noise[2:, :]) / (4.0 * res * res)
    var = base_variance + kink[..., None] + prop
    rows, cols, axis = np.nonzero(defined)
    centers = geometry.cell_centers()
    return centers[rows, cols], axis.astype(np.int64), grad[rows, cols, axis], var[rows, cols, axis]
