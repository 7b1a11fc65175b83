"""The GPIS posterior on a grid and what the planners ask of it: samples, off-grid mean and gradient, centre of mass."""

from __future__ import annotations

import ctypes
import math
import threading
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import cython_blas

from gpis_grasp_ros.core.gpis.hyperparameters import HyperparameterFit
from gpis_grasp_ros.core.gpis.kernel import KernelParams, _cross_joint
from gpis_grasp_ros.core.gpis.observations import _Observations
from gpis_grasp_ros.core.grid import GridGeometry

_FACTOR_LOCK = threading.Lock()  # guards the float32 factor's one-time construction


def _blas_strmm() -> ctypes._CFuncPtr:
    """The BLAS ``strmm`` scipy links, called through ctypes: unlike scipy's Python wrapper, which holds
    the GIL for the whole product, a ctypes call releases it, so samples drawn on one thread do not stop the
    planner's Python on another."""
    api = ctypes.pythonapi
    api.PyCapsule_GetName.restype = ctypes.c_char_p
    api.PyCapsule_GetName.argtypes = [ctypes.py_object]
    api.PyCapsule_GetPointer.restype = ctypes.c_void_p
    api.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
    capsule = cython_blas.__pyx_capi__['strmm']
    address = api.PyCapsule_GetPointer(capsule, api.PyCapsule_GetName(capsule))
    if not address:
        raise RuntimeError('scipy.linalg.cython_blas has no strmm')
    char, int_p, ptr = ctypes.c_char_p, ctypes.POINTER(ctypes.c_int), ctypes.c_void_p
    return ctypes.CFUNCTYPE(None, char, char, char, char, int_p, int_p, ctypes.POINTER(ctypes.c_float), ptr, int_p,
                            ptr, int_p)(address)


_STRMM = _blas_strmm()


def _lower_trmm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """B := A B in place for A (m, m) lower triangular and B (m, n), both float32 in Fortran order; returns B."""
    if not (a.dtype == b.dtype == np.float32 and a.flags.f_contiguous and b.flags.f_contiguous
            and a.shape[0] == a.shape[1] == b.shape[0]):
        raise ValueError(f'TRMM needs Fortran-ordered float32 A (m, m) and B (m, n), got {a.shape} and {b.shape}')
    m, n = b.shape
    if m and n:
        _STRMM(b'L', b'L', b'N', b'N', ctypes.byref(ctypes.c_int(m)), ctypes.byref(ctypes.c_int(n)),
               ctypes.byref(ctypes.c_float(1.0)), a.ctypes.data, ctypes.byref(ctypes.c_int(m)), b.ctypes.data,
               ctypes.byref(ctypes.c_int(m)))
    return b


@dataclass
class GpisPosterior:
    """GPIS posterior on the cells of a :class:`~gpis_grasp_ros.core.grid.GridGeometry` (extend, do not rename).

    * ``mean``       (H, W) float64, posterior mean signed distance mu (m), eq. 1
    * ``variance``   (H, W) float64, posterior marginal variance sigma^2 (m^2), eq. 2
    * ``gradient``   (H, W, 2) float64, d mu / dx and d mu / dy (dimensionless): the exact gradient of the
      posterior mean (kernel derivatives), with gradient observations also the posterior mean of the SDF
      gradient
    * ``cov_factor`` (H*W, r) float64, L with joint posterior covariance Sigma ~= L L^T of the SDF values
      over the row-major flattened grid (r <= H*W); used by :meth:`sample`
    * ``params``     :class:`KernelParams` (C in m^2, l in m, constant prior mean in m)
    * value training data: ``train_xy`` (n, 2) m, ``train_y`` (n,) m, ``train_noise`` (n,) m^2
    * gradient training data: ``train_grad_xy`` (k, 2) m, ``train_grad_axis`` (k,) 0 = d/dx, 1 = d/dy,
      ``train_grad`` (k,) and ``train_grad_noise`` (k,) dimensionless
    * ``hyperparameter_fit`` / ``bound_hits``: the maximum-likelihood search and the bounds it sits on
    * ``obstacles`` (H, W) float64 or None: signed distance (m) to the other objects in the grid
    """

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
    # Extensions (defaults keep hand-built posteriors valid):
    alpha: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (K + N)^-1 (y - m): values, then gradients
    approximation: str = 'exact'  # 'exact' or 'reduced_rank' (docs/gpis-model.md, Computation)
    rank: int = 0  # columns of the weight-space basis (Kronecker modes)
    truncation: float = 0.0  # dropped share of the prior variance by the basis truncation
    log_marginal_likelihood: float = float('nan')  # log p(y, g | X, C, l, m) of all training data
    # gradient observations (section III, Solak et al.): component ``train_grad_axis`` (0 = d/dx,
    # 1 = d/dy) of the SDF gradient at ``train_grad_xy`` (m), observed value (dimensionless) and noise
    train_grad_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    train_grad_axis: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    train_grad: np.ndarray = field(default_factory=lambda: np.zeros(0))
    train_grad_noise: np.ndarray = field(default_factory=lambda: np.zeros(0))
    hyperparameter_fit: HyperparameterFit | None = None  # the ML search behind ``params`` (None: fixed)
    #: (H, W) signed distance (m) to the other objects seen in the grid, deterministic (None: none): not part of
    #: the target's shape, but the world its jaws move in (:class:`~gpis_grasp_ros.core.sdf_bank.SdfBank`)
    obstacles: np.ndarray | None = None
    #: L^T in float32 (r, H*W), made by the first float32 :meth:`sample_deviations` (``cov_factor`` is not
    #: changed after construction); for a square lower-triangular L, L itself in Fortran order (for TRMM)
    _cov_factor_t32: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)
    _cov_factor_lower: bool = field(default=False, init=False, repr=False, compare=False)

    @property
    def bound_hits(self) -> tuple[str, ...]:
        """Hyperparameter bounds the maximum-likelihood optimum sits on (empty: interior or not optimised)."""
        return () if self.hyperparameter_fit is None else self.hyperparameter_fit.bound_hits

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` joint posterior SDF samples f ~ N(mu, Sigma) on the grid, shape (n, H, W), m."""
        flat = self.sample_deviations(n, rng)
        flat += self.mean.reshape(1, -1)
        return flat.reshape((n,) + self.geometry.shape)

    def sample_deviations(self, n: int, rng: np.random.Generator, dtype: type = np.float64) -> np.ndarray:
        """Deviations f_i - mu = L eps_i (m) of ``n`` joint samples, row-major ``(n, H*W)`` of ``dtype``.

        The standard normals eps_i are drawn in float64 whatever ``dtype`` (the same random stream as
        :meth:`sample`, which adds the mean to the float64 deviations); with float32 they are rounded and
        multiplied by L in float32 (single-precision GEMM, or TRMM when L is square lower-triangular, as a
        full-rank basis gives it: about twice and four times as fast; deviations within ~1e-6 of
        their size; docs/speed.md).
        """
        eps = rng.standard_normal((n, self.cov_factor.shape[1]))
        if np.dtype(dtype) == np.float64:
            return eps @ self.cov_factor.T
        if np.dtype(dtype) != np.float32:
            raise ValueError(f'deviations are float64 or float32, not {np.dtype(dtype)}')
        with _FACTOR_LOCK:  # a planner's samples and its final P_F's may be drawn on two threads at once
            if self._cov_factor_t32 is None:
                factor = self.cov_factor
                # the factor of a full-rank basis is the square triangle of a QR factorisation (gpis.basis): the
                # triangular product (TRMM) skips the zero triangle, half the GEMM's multiplications
                self._cov_factor_lower = bool(factor.ndim == 2 and factor.shape[0] == factor.shape[1] > 0
                                              and not np.triu(factor, 1).any())
                self._cov_factor_t32 = (np.asfortranarray(factor, dtype=np.float32) if self._cov_factor_lower
                                        else np.ascontiguousarray(factor.T, dtype=np.float32))
        if self._cov_factor_lower:  # (L eps^T)^T: eps^T is eps's Fortran view, the result's transpose C-ordered
            return _lower_trmm(self._cov_factor_t32, eps.astype(np.float32).T).T
        return eps.astype(np.float32) @ self._cov_factor_t32

    def center_of_mass(self) -> np.ndarray:
        """Centre of mass (x, y) in m of the mean shape {mu < 0}, uniform density (section V)."""
        return center_of_mass(self.mean[None], self.geometry)[0]

    def com_spread(self, n: int = 1000, rng: np.random.Generator | None = None) -> float:
        """RMS distance (m) of sampled shapes' centres of mass from the mean shape's (condition 1)."""
        return com_spread(self, n, rng)

    def observations(self) -> _Observations:
        """All training observations (values first, then gradient components) as one set."""
        return _Observations.build(self.train_xy, self.train_y, self.train_noise, self.train_grad_xy,
                                   self.train_grad_axis, self.train_grad, self.train_grad_noise)

    def predict_mean(self, xy: np.ndarray) -> np.ndarray:
        """Posterior mean mu (m) at arbitrary metric points ``(..., 2)`` (eq. 1), off the grid too.

        mu(x*) = m + sum_i alpha_i cov(f(x*), L_i f): L_i is a value or a gradient component.
        """
        xy = np.asarray(xy, dtype=np.float64)
        pts = xy.reshape(-1, 2)
        obs = self._checked_observations()
        out = np.empty(pts.shape[0])
        for sl in self._point_chunks(pts.shape[0], obs.size):
            out[sl] = self.params.prior_mean + _cross_joint(pts[sl], obs, self.params, 0, 0) @ self.alpha
        return out.reshape(xy.shape[:-1])

    def predict_gradient(self, xy: np.ndarray) -> np.ndarray:
        """Gradient of the posterior mean (dimensionless) at metric points ``(..., 2)`` → ``(..., 2)``.

        d mu / d x* = sum_i alpha_i d cov(f(x*), L_i f) / d x* (derivatives of the SE kernel, section V-A).
        """
        xy = np.asarray(xy, dtype=np.float64)
        pts = xy.reshape(-1, 2)
        obs = self._checked_observations()
        out = np.empty_like(pts)
        for sl in self._point_chunks(pts.shape[0], obs.size):
            out[sl, 0] = _cross_joint(pts[sl], obs, self.params, 1, 0) @ self.alpha
            out[sl, 1] = _cross_joint(pts[sl], obs, self.params, 0, 1) @ self.alpha
        return out.reshape(xy.shape)

    def _checked_observations(self) -> _Observations:
        obs = self.observations() if self.train_xy.shape[0] else None
        if obs is None or self.alpha.shape != (obs.size,):
            raise ValueError('this posterior carries no training data / representer weights: build it with '
                             'fit_gpis or posterior_from_data to evaluate it off the grid')
        return obs

    @staticmethod
    def _point_chunks(p: int, n: int) -> list[slice]:
        step = max(1, 2_000_000 // max(n, 1))
        return [slice(i, min(i + step, p)) for i in range(0, p, step)]


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


def com_spread(posterior: GpisPosterior, n: int = 1000, rng: np.random.Generator | None = None,
               chunk: int = 250) -> float:
    """RMS distance (m) between sampled shapes' centres of mass and the mean shape's (section VI-A).

    Condition 1 of the P_F approximation asks the centre of mass z to stay within delta of
    E[z]; this returns sqrt(mean_i |z(f_i) - z(mu)|^2) over ``n`` joint samples f_i.
    """
    if n < 1:
        raise ValueError(f'need at least one sample, got {n}')
    rng = np.random.default_rng(0) if rng is None else rng
    ref = posterior.center_of_mass()
    total = 0.0
    for start in range(0, n, chunk):
        m = min(chunk, n - start)
        com = center_of_mass(posterior.sample(m, rng), posterior.geometry)
        total += float(np.sum((com - ref[None, :]) ** 2))
    return math.sqrt(total / n)
