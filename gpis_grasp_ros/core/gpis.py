"""Gaussian process implicit surfaces with derivative observations (paper sections III-A, III-B and V-A).

CONTRACT (other modules rely on it; extend, do not rename):

``GpisPosterior`` holds a GPIS posterior on the cells of a :class:`~gpis_grasp_ros.core.grid.GridGeometry`:

* ``mean``       (H, W) float64, posterior mean signed distance mu (m), eq. 1
* ``variance``   (H, W) float64, posterior marginal variance sigma^2 (m^2), eq. 2
* ``gradient``   (H, W, 2) float64, d mu / dx and d mu / dy (dimensionless): the exact gradient of the
  posterior mean (kernel derivatives), which with gradient observations is also the posterior mean
  of the SDF gradient
* ``cov_factor`` (H*W, r) float64, L with joint posterior covariance Sigma ~= L L^T of the SDF values
  over the row-major flattened grid (r <= H*W); used by :meth:`GpisPosterior.sample`
* ``params``     :class:`KernelParams` (C in m^2, l in m, constant prior mean in m)
* value training data: ``train_xy`` (n, 2) m, ``train_y`` (n,) m, ``train_noise`` (n,) m^2
* gradient training data: ``train_grad_xy`` (k, 2) m, ``train_grad_axis`` (k,) 0 = d/dx, 1 = d/dy,
  ``train_grad`` (k,) and ``train_grad_noise`` (k,) dimensionless
* ``hyperparameter_fit`` / ``bound_hits``: the maximum-likelihood search and the bounds it sits on

Model (section III-A). f ~ GP(m, k), k(xi, xj) = C exp(-|xi - xj|^2 / (2 l^2)). Section III builds
a GPIS "augmented to predict the gradient of the SDF" (Solak et al., derivative observations): the
GP is trained on SDF values y_i = f(x_i) + e_i, e_i ~ N(0, s_i^2) (s_i^2 = ``train_noise[i]``, the
sensing noise map) AND on gradient components g_j = d f(z_j) / d x_a + e'_j, whose covariances are
kernel derivatives: cov(f(x), d f(x') / d x'_a) = k (x_a - x'_a) / l^2 and cov(d f(x) / d x_a,
d f(x') / d x'_b) = k (delta_ab / l^2 - (x_a - x'_a)(x_b - x'_b) / l^4). ``jitter`` is added to every
noise variance. The prior mean m is a constant, *negative* so that space without data leans to
"object" (section III-B); its gradient is 0. Default m = -0.01 m (interior depth of a ~2 cm wide
tabletop object; metres, independent of M).

Gradient observations (:func:`gradient_observations`, ``GpisParams.gradient_observations``): central
differences of the EDT SDF at training cells whose two neighbours along the axis are training cells
too (a missing neighbour has no measured distance). Noise variance per component (dimensionless):
g0 + (1 - |g|)^2 + (s_-^2 + s_+^2) / (4 res^2) - g0 = 0.01 is the measured RMS error (~0.1) of
central-difference EDT gradients of rasterised discs against the analytic gradient; (1 - |g|)^2 marks
kinks (medial axis, corners), where an SDF has no gradient and |g| departs from 1; the last term is
the sensing noise of the two differenced values.

Computation. On the grid the prior of the values is the Kronecker product C (K_y (x) K_x) of two 1-D
SE matrices (the SE kernel is separable). With gradient observations each axis uses the 1-D *joint*
prior of values and scaled derivatives [f(x_i), l f'(x_i)] (2W x 2W, both blocks O(1)); its
eigenpairs give mode values and mode derivatives at the cell centres, and products of the y and x
modes represent values, d/dx (x derivative rows) and d/dy (y derivative rows) with the exact joint
covariance. The prior is f = m + G w, w ~ N(0, I), over the r product modes above ``tol`` x the
largest eigenvalue; conditioning on all N = n + k observations is done in weight space:

    P = I + G_X^T N^-1 G_X  (r x r, P >= I),   w_mean = P^-1 G_X^T N^-1 (y - m),
    alpha = (K + N)^-1 (y - m) = N^-1 (y - m - G_X w_mean),
    mu(x*) = m + sum_i alpha_i cov(f(x*), L_i f)  (eq. 1),  grad mu(x*) = its kernel derivative,
    Sigma = G P^-1 G^T = F F^T,  F = G L_P^-T  (``cov_factor``),   sigma^2 = diag(F F^T)  (eq. 2)

with mu and grad mu as separable products (H x N)(N x W). P is assembled per observation type from
the Kronecker structure in O(H W |B|^2 + H |A|^2 |B|^2) (A, B: row / column modes in use), F by two
GEMMs; when r > H W (the joint basis on the exact path) F is compressed to H W columns by a QR
factorisation (F F^T = R^T R), so sampling costs what it did without gradients.

* **exact** (n <= ``max_exact_points`` training cells, default 2500): every mode above 1e-15 of the
  largest is kept, so this is exact GP regression to rounding (checked against a dense textbook
  joint value/gradient GP to <= 1e-8 in ``test_gpis``, ~1e-12 measured). Training inputs off the
  cell centres (possible in :func:`posterior_from_data`) use a function-space Cholesky of K + N
  for mean and variance.
* **reduced_rank** (n > ``max_exact_points``): the same algorithm with ``rank_tolerance`` (1e-10)
  and at most ``max_rank`` modes - a truncated Karhunen-Loeve GP; ``truncation`` reports the
  dropped share of the prior variance, ``bench_gpis`` its error.

Hyperparameters (section III-A: "set using maximum-likelihood estimation"). The negative log
marginal likelihood of the joint observations and its analytic gradient in (log C, log l) are
minimised with L-BFGS-B from a data-driven start (C = mean (y - m)^2, l = E/12) plus ``n_restarts``
seeded log-uniform starts, on a seeded subset of at most ``max_opt_points`` observations (a random
set of training cells with all their gradient components). Choices, each a documented default:

* Search band: only training cells with |SDF| <= ``search_band_cells`` (3) cells enter the search.
  The shape lives there; the far-field EDT is a smooth cone/plane that makes up most of the grid and,
  fitted with the rest, drove l to 4-21 cells on the shipped recordings (object-scale smoothing that
  erased the nail B and the transparent knob F from the mean shape).
* Bounds: l in [``length_scale_min_cells`` = 1 cell, ``length_scale_max_extent`` x E = E/6] and
  sqrt(C) in [1e-3 E, 10 E] (E: grid extent). Below one cell the grid cannot resolve the length
  scale. The upper bound E/6 (~4 cells at M = 25) keeps the paper's "missing = object" mechanism
  (section III-B) working: inside an unobserved region the mean reverts to the negative prior
  mean only over distances beyond ~l, and the shipped transparent knob F (an unobserved 4 x 5-cell
  region) vanished from the mean shape at ML's unbounded l = 9.5 cells. It binds on A and F of
  the 8 shipped bags (ML is interior on the other six). Being relative to E, the bounds do not
  change with M. Since the sensing noise map leaves every *unknown* cell untrained and object in the
  SDF (missing, extended RGB/depth disagreement, no-return pixels split from the target; sensing
  module, "Unknown cells"), whole unseen parts (A's dispenser arm, F's crystal body, G's bottle)
  are such regions; the bound still keeps them in the mean shape (after that change it binds on A and E).
* Thickness bound: l <= ``length_scale_max_thickness`` (3) x r_in as well, r_in the largest
  inscribed radius of the observed object (max of -SDF; missing cells count as object). An SE
  kernel whose l exceeds ~1.5 times the object's width correlates both sides of it with the free
  space around it, and the mean smooths the object away: the shipped nail B (one cell wide,
  r_in = 0.5 cell) vanished at ML's l = 2.5 cells (0 object cells in the mean) and stays at
  l = 1.5 cells (15 cells for 11 occupied). The bound is a property of the data, not a tuned
  number; it binds only on thin objects (B and G of the shipped bags). Limitation: r_in is the
  object's *thickest* part, so a thin handle on a thick body is not protected by it.
* A bound that binds is logged (warning, logger ``gpis_grasp_ros.core.gpis``) and listed in
  ``posterior.bound_hits``. A likelihood evaluation whose K + N cannot be factorised is counted
  (``HyperparameterFit.cholesky_failures``) and logged; L-BFGS-B sees a wall there (1e25), a start
  without a likelihood is skipped and counted (``failed_starts``), and if every start fails the
  start values are kept with ``ok = False`` and an error log.

``optimize_hyperparameters=False`` uses the given values or the same data-driven start.
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.linalg import cho_factor, cho_solve, eigh, qr, solve_triangular
from scipy.linalg.lapack import dpotri, dtrtri
from scipy.optimize import minimize

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.sdf import sdf_gradient, signed_distance

if TYPE_CHECKING:  # pragma: no cover
    from gpis_grasp_ros.core.sensing import SensingResult

LOG_2PI = math.log(2.0 * math.pi)
_BLAS_CONTROLLER: list = []  # lazily created threadpoolctl.ThreadpoolController (or None if unavailable)
logger = logging.getLogger('gpis_grasp_ros.core.gpis')

# Observation types: a value f(x) or a gradient component d f / d x, d f / d y (Solak et al.)
VALUE, GRAD_X, GRAD_Y = 0, 1, 2


@contextlib.contextmanager
def blas_threads(n: int | None) -> Iterator[None]:
    """Limit BLAS/LAPACK to ``n`` threads inside the block (``None`` or 0: leave the default).

    The fits are many mid-sized LAPACK calls (r, n ~ 10^2 - 10^3). On a 2-core robot computer
    that also runs other ROS nodes, multi-threaded OpenBLAS collapses when its threads wait for
    a busy core (measured: 30x slower hyperparameter searches under load); one thread is
    predictable and barely slower on an idle machine. Uses threadpoolctl when installed.
    """
    if not n:
        yield
        return
    if not _BLAS_CONTROLLER:
        try:
            from threadpoolctl import ThreadpoolController
            _BLAS_CONTROLLER.append(ThreadpoolController())
        except ImportError:  # pragma: no cover - optional dependency
            _BLAS_CONTROLLER.append(None)
    controller = _BLAS_CONTROLLER[0]
    if controller is None:  # pragma: no cover
        yield
        return
    with controller.limit(limits=int(n), user_api='blas'):
        yield


@dataclass(frozen=True)
class KernelParams:
    """Squared-exponential kernel k = C exp(-|xi - xj|^2 / (2 l^2)) and constant prior mean."""

    signal_variance: float  # C, m^2
    length_scale: float  # l, m
    prior_mean: float  # m (negative: unobserved space leans to "object")


@dataclass(frozen=True)
class GpisParams:
    """Settings of :func:`fit_gpis` (lengths in metres, variances in m^2, gradients dimensionless)."""

    prior_mean: float = -0.01  # constant prior mean m (m), negative = "object" (section III-B)
    optimize_hyperparameters: bool = True  # maximise the log marginal likelihood over C and l
    signal_variance: float | None = None  # C (m^2): fixed value, or start of the search; None = data-driven
    length_scale: float | None = None  # l (m): fixed value, or start of the search; None = extent / 12
    n_restarts: int = 2  # extra random starts of L-BFGS-B
    seed: int = 0  # seeds restarts and the model-selection subset
    jitter: float = 1e-10  # added to every noise variance (diagonal of K + N), m^2 for values, 1 for gradients
    gradient_observations: bool = True  # also train on the SDF gradient (section III, derivative observations)
    gradient_noise_variance: float = 0.01  # g0: discretisation noise of one central-difference gradient component
    max_exact_points: int = 2500  # above this many training cells use the reduced-rank path
    search_band_cells: float | None = 3.0  # hyperparameter search on training cells with |SDF| <= this many cells
    max_opt_points: int = 450  # observations (values + gradient components) in the hyperparameter search subset
    rank_tolerance: float = 1e-10  # relative eigenvalue cut-off of the Kronecker basis
    max_rank: int = 2000  # cap on the basis size r (memory H*W*r*8 bytes)
    blas_threads: int | None = 1  # BLAS threads during the fit (None = library default), see blas_threads()
    length_scale_min_cells: float = 1.0  # lower bound on l in grid cells (module docstring: Hyperparameters)
    length_scale_max_extent: float = 1.0 / 6.0  # upper bound on l as a multiple of the grid extent E
    length_scale_max_thickness: float | None = 3.0  # upper bound on l as a multiple of the inscribed radius r_in
    signal_std_bounds: tuple[float, float] = (1e-3, 10.0)  # sqrt(C) x grid extent

    def __post_init__(self) -> None:
        if self.jitter < 0 or not math.isfinite(self.jitter):
            raise ValueError(f'jitter must be a non-negative number of m^2, got {self.jitter}')
        for name in ('signal_variance', 'length_scale'):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f'{name} must be positive, got {value}')
        if not (math.isfinite(self.gradient_noise_variance) and self.gradient_noise_variance >= 0):
            raise ValueError(f'gradient_noise_variance must be >= 0, got {self.gradient_noise_variance}')
        if self.max_rank < 1 or not (0 <= self.rank_tolerance < 1):
            raise ValueError('max_rank must be >= 1 and rank_tolerance in [0, 1)')
        if self.length_scale_max_thickness is not None and not (0 < self.length_scale_max_thickness < math.inf):
            raise ValueError('length_scale_max_thickness must be positive or None, got '
                             f'{self.length_scale_max_thickness}')
        if not (0 < self.length_scale_min_cells and 0 < self.length_scale_max_extent < math.inf):
            raise ValueError('length_scale_min_cells and length_scale_max_extent must be positive, got '
                             f'{self.length_scale_min_cells}, {self.length_scale_max_extent}')
        lo, hi = self.signal_std_bounds
        if not (0 < lo < hi and math.isfinite(hi)):
            raise ValueError(f'signal_std_bounds must satisfy 0 < low < high, got {self.signal_std_bounds}')


@dataclass(frozen=True)
class HyperparameterFit:
    """Outcome of the maximum-likelihood search (:func:`fit_hyperparameters`).

    ``bound_hits`` names every bound the optimum sits on (``'length_scale_lower'``,
    ``'length_scale_upper'``, ``'signal_variance_lower'``, ``'signal_variance_upper'``): the
    likelihood would rise beyond it, the value is the bound's, not the data's. Every binding
    bound is also logged (warning, logger ``gpis_grasp_ros.core.gpis``). ``cholesky_failures``
    counts likelihood evaluations whose K + N was not numerically positive definite (L-BFGS-B
    treats them as a wall; logged); ``failed_starts`` counts starts at which the factorisation
    failed, so that L-BFGS-B could not move from them. ``ok`` is False when no start produced a
    finite likelihood: the search then keeps the start values (logged as an error).
    """

    signal_variance: float  # C, m^2
    length_scale: float  # l, m
    log_likelihood: float  # on the search subset (nats)
    bounds: tuple[tuple[float, float], tuple[float, float]]  # (C_lo, C_hi) m^2, (l_lo, l_hi) m
    bound_hits: tuple[str, ...] = ()
    cholesky_failures: int = 0
    failed_starts: int = 0
    n_starts: int = 1
    n_observations: int = 0  # size of the search subset (values + gradient components)
    ok: bool = True


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
    # Extensions (defaults keep hand-built posteriors valid):
    alpha: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (K + N)^-1 (y - m): values, then gradients
    approximation: str = 'exact'  # 'exact' or 'reduced_rank' (see module docstring)
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

    @property
    def bound_hits(self) -> tuple[str, ...]:
        """Hyperparameter bounds the maximum-likelihood optimum sits on (empty: interior or not optimised)."""
        return () if self.hyperparameter_fit is None else self.hyperparameter_fit.bound_hits

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` joint posterior SDF samples f ~ N(mu, Sigma) on the grid, shape (n, H, W), m."""
        h, w = self.geometry.shape
        eps = rng.standard_normal((n, self.cov_factor.shape[1]))
        flat = eps @ self.cov_factor.T  # (n, H*W): rows f_i - mu = L eps_i
        flat += self.mean.reshape(1, -1)
        return flat.reshape(n, h, w)

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


# ----------------------------------------------------------------------------------------------
# kernel helpers: SE kernel and its derivatives (derivative observations, Solak et al.)

def _pair_factor(d: np.ndarray, p: np.ndarray | int, q: np.ndarray | int, ell2: float,
                 with_dlog: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """Per-axis factor of d^(p+q) / d a^p d b^q exp(-(a - b)^2 / (2 l^2)) divided by the exponential.

    ``d`` = a - b, p, q in {0, 1} (broadcastable integer arrays): 1, d / l^2 (q = 1), -d / l^2 (p = 1),
    1 / l^2 - d^2 / l^4 (p = q = 1). With ``with_dlog`` also its derivative in log l.
    """
    pq = np.broadcast_to(2 * np.asarray(p) + np.asarray(q), d.shape)
    f = np.ones_like(d)
    df = np.zeros_like(d) if with_dlog else None
    ell4 = ell2 * ell2
    for code, fn, dfn in ((1, lambda x: x / ell2, lambda x: -2.0 * x / ell2),
                          (2, lambda x: -x / ell2, lambda x: 2.0 * x / ell2),
                          (3, lambda x: 1.0 / ell2 - x * x / ell4, lambda x: -2.0 / ell2 + 4.0 * x * x / ell4)):
        sel = pq == code
        if sel.any():
            f[sel] = fn(d[sel])
            if with_dlog:
                df[sel] = dfn(d[sel])
    return f, df


def _se_1d(a: np.ndarray, b: np.ndarray, ell: float, p: int = 0, q: np.ndarray | int = 0) -> np.ndarray:
    """d^(p+q) / d a^p d b^q of the unit 1-D SE factor exp(-(a_i - b_j)^2 / (2 l^2)), shape (len(a), len(b)).

    ``q`` may be an array over ``b`` (one derivative order per column).
    """
    d = a[:, None] - b[None, :]
    s = np.exp(-0.5 * (d / ell) ** 2)
    if p == 0 and np.all(np.asarray(q) == 0):
        return s
    return s * _pair_factor(d, p, np.asarray(q)[None, ...] if np.ndim(q) else q, ell * ell)[0]


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


def _cross_joint(pts: np.ndarray, obs: _Observations, kp: KernelParams, dx: int, dy: int) -> np.ndarray:
    """d^(dx+dy) / d x*^dx d y*^dy cov(f(x*), L_i f) for points (p, 2) and observations i → (p, N)."""
    ell2 = kp.length_scale ** 2
    ddx = pts[:, None, 0] - obs.xy[None, :, 0]
    ddy = pts[:, None, 1] - obs.xy[None, :, 1]
    base = kp.signal_variance * np.exp(-0.5 * (ddx * ddx + ddy * ddy) / ell2)
    return base * _pair_factor(ddx, dx, obs.px[None, :], ell2)[0] * _pair_factor(ddy, dy, obs.py[None, :], ell2)[0]


class _DenseKernel:
    """Unit-amplitude joint value/gradient SE Gram matrix of a fixed observation set, as a function of l.

    Per axis the factor of :func:`_pair_factor` is w00 + (s d + w11) / l^2 - w11 d^2 / l^4 with
    w00 = [p = q = 0], w11 = [p = q = 1], s = [q = 1] - [p = 1] (p, q: derivative orders of the
    row and column observation), precomputed once so that each likelihood evaluation is a few
    element-wise passes.
    """

    def __init__(self, obs: _Observations) -> None:
        self.r2 = _sq_dists(obs.xy)
        self.plain = not obs.has_gradients
        self.axes = []
        if not self.plain:
            for dim, orders in ((0, obs.px), (1, obs.py)):
                p, q = orders[:, None].astype(np.float64), orders[None, :].astype(np.float64)
                d = obs.xy[:, dim][:, None] - obs.xy[:, dim][None, :]
                w11 = p * q
                self.axes.append(((1.0 - p) * (1.0 - q), (q - p) * d + w11, w11 * d * d))

    def __call__(self, ell: float, with_dlog: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """k0 = K / C and, with ``with_dlog``, d k0 / d log l."""
        ell2 = ell * ell
        s = np.exp(-0.5 / ell2 * self.r2)
        if self.plain:
            return s, (s * self.r2 / ell2 if with_dlog else None)
        (w0x, ax, bx), (w0y, ay, by) = self.axes
        fx = w0x + ax / ell2 - bx / (ell2 * ell2)
        fy = w0y + ay / ell2 - by / (ell2 * ell2)
        k0 = s * fx * fy
        if not with_dlog:
            return k0, None
        dfx = -2.0 / ell2 * ax + 4.0 / (ell2 * ell2) * bx
        dfy = -2.0 / ell2 * ay + 4.0 / (ell2 * ell2) * by
        return k0, k0 * (self.r2 / ell2) + s * (dfx * fy + fx * dfy)


def _sq_dists(xy: np.ndarray) -> np.ndarray:
    """Pairwise squared distances (m^2) of points (n, 2)."""
    d2 = np.zeros((xy.shape[0], xy.shape[0]))
    for dim in range(xy.shape[1]):
        d = xy[:, dim][:, None] - xy[:, dim][None, :]
        d2 += d * d
    return d2


def _grid_axes(geometry: GridGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Metric x of the columns (W,) and y of the rows (H,) of the grid's cell centres."""
    res = geometry.resolution
    xs = geometry.origin_x + (np.arange(geometry.width) + 0.5) * res
    ys = geometry.origin_y + (np.arange(geometry.height) + 0.5) * res
    return xs, ys


# ----------------------------------------------------------------------------------------------
# Kronecker (Karhunen-Loeve) basis of the prior on the grid

@dataclass
class _AxisModes:
    """Eigenpairs of one axis' prior: of K (values) or of the joint [[K, l K_01], [l K_10, l^2 K_11]]."""

    u: np.ndarray  # (W, q) or (2W, q) eigenvectors, descending eigenvalues
    lam: np.ndarray  # (q,)
    val: np.ndarray  # (W, q) sqrt(lambda) u: mode values at the cell centres
    der: np.ndarray | None  # (W, q) mode derivatives (1/m) at the cell centres (joint basis only)
    coords: np.ndarray  # (W,) m
    ell: float

    @property
    def joint(self) -> bool:
        return self.der is not None

    def rows_at(self, coords: np.ndarray, idx: np.ndarray, on_grid: np.ndarray, modes: np.ndarray,
                deriv: bool) -> np.ndarray:
        """Mode values (or derivatives) at 1-D ``coords``: exact on cell centres, Nystroem elsewhere."""
        table = self.der if deriv else self.val
        if table is None:  # value-only basis: derivative rows by differentiating the Nystroem extension
            table = (_se_1d(self.coords, self.coords, self.ell, 1) @ self.u) / np.sqrt(np.where(
                self.lam > 0, self.lam, np.inf))[None, :]
        f = table[:, modes]
        if np.all(on_grid):
            return f[idx]
        out = np.empty((coords.size, modes.size))
        out[on_grid] = f[idx[on_grid]]
        off = ~on_grid
        p = int(deriv)
        cov = _se_1d(coords[off], self.coords, self.ell, p)  # cov(L f(x), f(axis))
        if self.joint:  # and cov(L f(x), l f'(axis))
            cov = np.hstack([cov, self.ell * _se_1d(coords[off], self.coords, self.ell, p, 1)])
        # u(x) = cov(x, axis) u / lambda  =>  sqrt(lambda) u(x) = cov(x, axis) u / sqrt(lambda)
        out[off] = (cov @ self.u[:, modes]) / np.sqrt(self.lam[modes])[None, :]
        return out


def _eig_desc(k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    lam, u = eigh(k)
    return np.clip(lam[::-1], 0.0, None), u[:, ::-1]


def _axis_modes(coords: np.ndarray, ell: float, joint: bool) -> _AxisModes:
    k = _se_1d(coords, coords, ell)
    if not joint:
        lam, u = _eig_desc(k)
        return _AxisModes(u, lam, u * np.sqrt(lam), None, coords, ell)
    n = coords.size
    k1 = np.empty((2 * n, 2 * n))
    k1[:n, :n] = k
    k1[:n, n:] = ell * _se_1d(coords, coords, ell, 0, 1)  # cov(f(a), l f'(b))
    k1[n:, :n] = k1[:n, n:].T
    k1[n:, n:] = ell * ell * _se_1d(coords, coords, ell, 1, 1)  # cov(l f'(a), l f'(b))
    lam, u = _eig_desc(k1)
    root = np.sqrt(lam)
    return _AxisModes(u, lam, u[:n] * root, u[n:] * root / ell, coords, ell)


@dataclass
class _Basis:
    """Selected product modes (a_k, b_k) of the 1-D eigenpairs of the y and x axes (unit amplitude)."""

    y: _AxisModes
    x: _AxisModes
    a: np.ndarray  # (r,) row-mode index of each selected product mode
    b: np.ndarray  # (r,) column-mode index
    truncation: float  # dropped share of the prior variance

    @property
    def rank(self) -> int:
        return self.a.size

    def rows(self, kind: int) -> tuple[np.ndarray, np.ndarray]:
        """(y factor (H, qy), x factor (W, qx)) of observation type ``kind`` at the cell centres."""
        return (self.y.der if kind == GRAD_Y else self.y.val), (self.x.der if kind == GRAD_X else self.x.val)


def _kronecker_basis(geometry: GridGeometry, ell: float, tol: float, max_rank: int | None, joint: bool) -> _Basis:
    """Product eigenpairs of the y and x axis priors above ``tol`` x the largest, at most ``max_rank``."""
    xs, ys = _grid_axes(geometry)
    mx, my = _axis_modes(xs, ell, joint), _axis_modes(ys, ell, joint)
    flat = np.outer(my.lam, mx.lam).ravel()
    keep = np.flatnonzero(flat >= tol * flat.max())
    keep = keep[np.argsort(-flat[keep], kind='stable')][:max_rank]
    keep = keep[flat[keep] > 0]
    a, b = np.divmod(keep, mx.lam.size)
    total = flat.sum()
    truncation = float(max(total - flat[keep].sum(), 0.0) / total)
    return _Basis(my, mx, a, b, truncation)


def _axis_index(coords: np.ndarray, axis: np.ndarray, res: float) -> tuple[np.ndarray, np.ndarray]:
    """Cell index of 1-D metric coordinates and whether each lies on a cell centre (to 1e-6 cell)."""
    idx_f = (coords - axis[0]) / res
    idx = np.rint(idx_f).astype(np.int64)
    on_grid = (np.abs(idx_f - idx) < 1e-6) & (idx >= 0) & (idx < axis.size)
    return np.where(on_grid, idx, 0), on_grid


def _precision_on_grid(basis: _Basis, sqrt_c: float, weights: dict[int, np.ndarray],
                       max_entries: int = 20_000_000) -> np.ndarray | None:
    """G_X^T N^-1 G_X (r x r) for training inputs on cell centres, from the Kronecker structure.

    ``weights[kind]`` (H, W) holds sum 1/noise of the observations of that type in each cell.
    With the row / column modes A, B in use, the entry ((a, b), (a', b')) of one type is
    sum_i Fy[i, a] Fy[i, a'] sum_j w_ij Fx[j, b] Fx[j, b'] (F: mode values or derivatives):
    O(H W |B|^2 + H |A|^2 |B|^2) per type instead of O(N r^2).
    Returns None when the |A|^2 |B|^2 intermediate would exceed ``max_entries``.
    """
    ua, ia = np.unique(basis.a, return_inverse=True)
    ub, ib = np.unique(basis.b, return_inverse=True)
    if ua.size ** 2 * ub.size ** 2 > max_entries:
        return None
    p4 = np.zeros((ua.size ** 2, ub.size ** 2))
    for kind, wgt in weights.items():
        fy_all, fx_all = basis.rows(kind)
        fy = sqrt_c * fy_all[:, ua]  # (H, |A|)
        fx = fx_all[:, ub]  # (W, |B|)
        t = np.matmul(np.swapaxes(wgt[:, :, None] * fx[None, :, :], 1, 2), fx)  # (H, |B|, |B|)
        u = (fy[:, :, None] * fy[:, None, :]).reshape(fy.shape[0], -1)  # (H, |A|^2)
        p4 += u.T @ t.reshape(t.shape[0], -1)
    p4 = p4.reshape(ua.size, ua.size, ub.size, ub.size)
    full = p4.transpose(0, 2, 1, 3).reshape(ua.size * ub.size, ua.size * ub.size)  # ((a, b), (a', b'))
    idx = ia * ub.size + ib
    return full.take(idx, axis=0).take(idx, axis=1)


# ----------------------------------------------------------------------------------------------
# conditioning (shared by fit_gpis and posterior_from_data so both give identical posteriors)

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


EXACT_RANK_TOLERANCE = 1e-15  # product eigenvalues below this x the largest are at the rounding level


def _condition(geometry: GridGeometry, kp: KernelParams, obs: _Observations, jitter: float, max_exact_points: int,
               rank_tolerance: float, max_rank: int, hyperparameters_optimized: bool,
               fit: HyperparameterFit | None = None) -> GpisPosterior:
    """GPIS posterior on ``geometry`` from values and gradient observations (eqs. 1, 2, kernel derivatives)."""
    c, ell, m = float(kp.signal_variance), float(kp.length_scale), float(kp.prior_mean)
    if not (c > 0 and ell > 0 and math.isfinite(c) and math.isfinite(ell) and math.isfinite(m)):
        raise ValueError(f'invalid kernel parameters {kp}')
    noise = obs.noise + jitter
    if np.any(noise <= 0):
        raise ValueError('noise variance + jitter must be > 0 m^2 for every training point')
    n = obs.size
    h, w = geometry.shape
    resid = obs.y - np.where(obs.kind == VALUE, m, 0.0)  # the constant prior mean has zero gradient
    xs, ys = _grid_axes(geometry)
    cols, col_on = _axis_index(obs.xy[:, 0], xs, geometry.resolution)
    rows, row_on = _axis_index(obs.xy[:, 1], ys, geometry.resolution)
    on_grid = bool(np.all(col_on) and np.all(row_on))
    exact = obs.n_values <= max_exact_points
    approximation = 'exact' if exact else 'reduced_rank'
    joint = obs.has_gradients
    basis = _kronecker_basis(geometry, ell, EXACT_RANK_TOLERANCE if exact else rank_tolerance,
                             None if exact else max_rank, joint)
    sqrt_c = math.sqrt(c)
    kinds = [k for k in (VALUE, GRAD_X, GRAD_Y) if np.any(obs.kind == k)]
    sel = {k: obs.kind == k for k in kinds}
    rows_sel = {}
    for k in kinds:  # (H, r), (W, r): observation type k on the grid is sum_k w_k fy[:, k] fx[:, k]^T
        fy_all, fx_all = basis.rows(k)
        rows_sel[k] = (sqrt_c * fy_all[:, basis.a], fx_all[:, basis.b])

    # weight-space precision P = I + G_X^T N^-1 G_X and G_X^T N^-1 (y - m)
    precision = None
    if on_grid:
        weights, rhs = {}, {}
        for k in kinds:
            weights[k] = np.zeros((h, w))
            np.add.at(weights[k], (rows[sel[k]], cols[sel[k]]), 1.0 / noise[sel[k]])
            rhs[k] = np.zeros((h, w))
            np.add.at(rhs[k], (rows[sel[k]], cols[sel[k]]), resid[sel[k]] / noise[sel[k]])
        precision = _precision_on_grid(basis, sqrt_c, weights)
        g_rhs = sum(np.einsum('ik,ij,jk->k', rows_sel[k][0], rhs[k], rows_sel[k][1]) for k in kinds)
    g_train = None
    if precision is None:
        g_train = np.empty((n, basis.rank))
        for k in kinds:
            s = sel[k]
            fx_tr = basis.x.rows_at(obs.xy[s, 0], cols[s], col_on[s], basis.b, k == GRAD_X)
            fy_tr = basis.y.rows_at(obs.xy[s, 1], rows[s], row_on[s], basis.a, k == GRAD_Y)
            g_train[s] = sqrt_c * fy_tr * fx_tr  # (n_k, r) basis functionals at the training inputs
        g_scaled = g_train / noise[:, None]
        precision = g_train.T @ g_scaled
        g_rhs = g_scaled.T @ resid
    precision[np.diag_indices_from(precision)] += 1.0
    chol_p = np.linalg.cholesky(precision)  # P >= I: always positive definite, no jitter needed

    # cross-covariance columns of the grid values with every observation: cov(f(x*), L_i f) / C
    kx_star = _se_1d(xs, obs.xy[:, 0], ell, 0, obs.px)  # (W, N)
    ky_star = _se_1d(ys, obs.xy[:, 1], ell, 0, obs.py)  # (H, N)
    variance = None
    if on_grid or not exact:
        # representer weights from the weight-space posterior mean (Woodbury):
        # alpha = (K + N)^-1 (y - m) = N^-1 (y - m - G_X w),  w = P^-1 G_X^T N^-1 (y - m)
        w_mean = cho_solve((chol_p, True), g_rhs, check_finite=False)
        if g_train is not None:
            f_train = g_train @ w_mean
        else:
            f_train = np.empty(n)
            for k in kinds:
                fy_k, fx_k = rows_sel[k]
                f_train[sel[k]] = ((fy_k * w_mean[None, :]) @ fx_k.T)[rows[sel[k]], cols[sel[k]]]
        alpha = (resid - f_train) / noise
        logdet = 2.0 * float(np.sum(np.log(np.diag(chol_p)))) + float(np.sum(np.log(noise)))
        lml = -0.5 * float(resid @ alpha) - 0.5 * logdet - 0.5 * n * LOG_2PI
    else:  # exact with inputs off the grid: function-space Cholesky (the basis only serves sampling)
        k_xx = c * _DenseKernel(obs)(ell)[0]
        k_xx[np.diag_indices_from(k_xx)] += noise
        cf = cho_factor(k_xx, lower=True, check_finite=False)
        alpha = cho_solve(cf, resid, check_finite=False)
        lml = -0.5 * float(resid @ alpha) - float(np.sum(np.log(np.diag(cf[0])))) - 0.5 * n * LOG_2PI
        variance = _exact_variance(cf[0], c, kx_star, ky_star)

    # Sigma = G P^-1 G^T = (G L_P^-T)(G L_P^-T)^T over the grid values; its diagonal is eq. 2
    cov_factor = _covariance_factor(basis, sqrt_c, chol_p, h, w)
    if variance is None:
        variance = np.einsum('ij,ij->i', cov_factor, cov_factor)

    # eq. 1 and its gradient: separable products (H x N)(N x W) of the kernel and its derivatives
    weighted = ky_star * (c * alpha)[None, :]  # (H, N)
    mean = m + weighted @ kx_star.T
    grad_x = weighted @ _se_1d(xs, obs.xy[:, 0], ell, 1, obs.px).T
    grad_y = (_se_1d(ys, obs.xy[:, 1], ell, 1, obs.py) * (c * alpha)[None, :]) @ kx_star.T
    nv = obs.n_values
    return GpisPosterior(
        geometry=geometry, mean=mean, variance=np.clip(variance.reshape(h, w), 0.0, None),
        gradient=np.stack([grad_x, grad_y], axis=-1), cov_factor=cov_factor, params=kp,
        train_xy=obs.xy[:nv], train_y=obs.y[:nv], train_noise=obs.noise[:nv], jitter=float(jitter),
        hyperparameters_optimized=hyperparameters_optimized, alpha=alpha, approximation=approximation,
        rank=basis.rank, truncation=basis.truncation, log_marginal_likelihood=lml,
        train_grad_xy=obs.xy[nv:], train_grad_axis=(obs.kind[nv:] == GRAD_Y).astype(np.int64),
        train_grad=obs.y[nv:], train_grad_noise=obs.noise[nv:], hyperparameter_fit=fit)


def _covariance_factor(basis: _Basis, sqrt_c: float, chol_p: np.ndarray, h: int, w: int) -> np.ndarray:
    """F with Sigma = F F^T over the grid values (row-major), at most H*W columns.

    F = G L_P^-T: L_P^-T is the factor of the weight-space posterior covariance P^-1
    (w = w_mean + L_P^-T xi), formed once (LAPACK trtri, r^3 / 3). G L_P^-T is then two GEMMs
    through the row / column modes, O(r |A| W (|B| + H)) instead of O(H W r^2). With more modes
    than cells (the joint value/gradient basis of the exact path) F is compressed to H*W columns
    by a QR factorisation, F F^T = R^T R, so sampling costs O(H W) per sample and mode.
    """
    r = basis.rank
    inv_l, info = dtrtri(chol_p, lower=1)
    if info != 0:  # pragma: no cover - P >= I is never singular
        raise np.linalg.LinAlgError(f'trtri failed with info={info}')
    factor_w = np.triu(inv_l.T)  # (r, r) = L_P^-T
    ua, ia = np.unique(basis.a, return_inverse=True)
    ub, ib = np.unique(basis.b, return_inverse=True)
    fy = sqrt_c * basis.y.val[:, ua]  # (H, |A|)
    fx = basis.x.val[:, ub]  # (W, |B|)
    if ua.size * ub.size * r > 4 * h * w * r:  # sparse mode set: the dense product is cheaper
        g_grid = ((sqrt_c * basis.y.val[:, basis.a])[:, None, :] * basis.x.val[:, basis.b][None, :, :]).reshape(
            h * w, r)
        factor = g_grid @ factor_w
    else:
        scattered = np.zeros((ua.size, ub.size, r))
        scattered[ia, ib] = factor_w  # rows of L_P^-T placed at their (row mode, column mode)
        q = fx @ scattered.transpose(1, 0, 2).reshape(ub.size, -1)  # (W, |A| r)
        q = q.reshape(w, ua.size, r).transpose(1, 0, 2).reshape(ua.size, -1)  # (|A|, W r)
        factor = (fy @ q).reshape(h * w, r)
    if r > h * w:
        factor = qr(factor.T, mode='r', check_finite=False)[0][:h * w].T  # (H*W, H*W), same F F^T
    return np.ascontiguousarray(factor)


def _exact_variance(chol_lower: np.ndarray, c: float, kx_star: np.ndarray, ky_star: np.ndarray,
                    max_block: int = 4_000_000) -> np.ndarray:
    """Eq. 2 on every cell (row-major): C - k*^T (K + N)^-1 k*, as ||L^-1 k*||^2 in chunks."""
    n = kx_star.shape[1]
    h, w = ky_star.shape[0], kx_star.shape[0]
    rows, cols = np.divmod(np.arange(h * w), w)
    chunk = max(1, max_block // max(n, 1))
    out = np.empty(h * w)
    for start in range(0, h * w, chunk):
        sl = slice(start, min(start + chunk, h * w))
        k_star = (c * ky_star[rows[sl]] * kx_star[cols[sl]]).T  # (n, chunk)
        v = solve_triangular(chol_lower, k_star, lower=True, check_finite=False)
        out[sl] = c - np.einsum('ij,ij->j', v, v)
    return out


# ----------------------------------------------------------------------------------------------
# gradient observations of an EDT signed distance

def gradient_observations(sdf_m: np.ndarray, noise_variance_m2: np.ndarray, train_mask: np.ndarray,
                          geometry: GridGeometry, base_variance: float = 0.01
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """SDF gradient observations for the GPIS (section III, derivative observations) and their noise.

    Each component is the central difference of the grid SDF (:func:`~gpis_grasp_ros.core.sdf.sdf_gradient`)
    at a training cell whose two neighbours along that axis are training cells too. Its noise
    variance (dimensionless) is the sum of three independent errors:

    * ``base_variance`` g0: the discretisation error of an EDT gradient component away from kinks.
      Measured on rasterised discs (M = 25, radii 1.5 - 4.5 cm) against the analytic gradient the
      RMS error is ~0.1 per component, so g0 = 0.01 by default.
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


# ----------------------------------------------------------------------------------------------
# hyperparameters

def negative_log_marginal_likelihood(log_theta: np.ndarray, kernel: _DenseKernel, resid: np.ndarray,
                                     noise: np.ndarray) -> tuple[float, np.ndarray]:
    """-log p(y | X, C, l) and its gradient in (log C, log l) (Rasmussen & Williams eqs. 5.8, 5.9).

    ``kernel`` is the joint value/gradient Gram matrix of the observations as a function of l,
    ``resid`` = y - m (values) or the gradient observation, ``noise`` per-observation variances
    (jitter included). Raises ``numpy.linalg.LinAlgError`` when K + N is not numerically
    positive definite (the caller records it; no silent substitute value).
    """
    c, ell = math.exp(log_theta[0]), math.exp(log_theta[1])
    k0, dk0 = kernel(ell, with_dlog=True)
    a = c * k0
    a[np.diag_indices_from(a)] += noise
    cf = cho_factor(a, lower=True, check_finite=False)  # raises LinAlgError if not positive definite
    alpha = cho_solve(cf, resid, check_finite=False)
    n = resid.size
    nll = 0.5 * float(resid @ alpha) + float(np.sum(np.log(np.diag(cf[0])))) + 0.5 * n * LOG_2PI
    # d nll / d theta = -1/2 tr((alpha alpha^T - A^-1) dA/dtheta); A^-1 is needed for the trace term
    # (R&W Algorithm 5.1) and is formed from the Cholesky factor (LAPACK potri); it never solves a system.
    inv, info = dpotri(cf[0], lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f'potri failed with info={info}')
    inv_lower = np.tril(inv)  # potri fills the lower triangle only; A^-1 and dA/dtheta are symmetric

    def trace_inv(b: np.ndarray) -> float:  # tr(A^-1 B) for symmetric B from the lower triangle
        return 2.0 * float(np.vdot(inv_lower, b)) - float(np.dot(np.diag(inv_lower), np.diag(b)))

    grad = 0.5 * np.array([
        c * (trace_inv(k0) - float(alpha @ (k0 @ alpha))),  # dA / dlog C = C k0
        c * (trace_inv(dk0) - float(alpha @ (dk0 @ alpha))),  # dA / dlog l = C dk0 / dlog l
    ])
    if not (math.isfinite(nll) and np.all(np.isfinite(grad))):
        raise np.linalg.LinAlgError('non-finite marginal likelihood')
    return nll, grad


def hyperparameter_bounds(geometry: GridGeometry, params: GpisParams,
                          inscribed_radius_m: float | None = None) -> tuple[tuple[float, float], tuple[float, float]]:
    """Bounds (m^2, m) for C and l (module docstring, Hyperparameters).

    l in [``length_scale_min_cells`` cells, min(``length_scale_max_extent`` x E,
    ``length_scale_max_thickness`` x ``inscribed_radius_m``)], sqrt(C) in ``signal_std_bounds`` x E,
    E the grid's metric extent (its longer side), ``inscribed_radius_m`` the object's largest
    inscribed radius (m; None or <= 0: no thickness bound).
    """
    extent = max(geometry.size_m)
    lo_l = params.length_scale_min_cells * geometry.resolution
    hi_l = params.length_scale_max_extent * extent
    if params.length_scale_max_thickness is not None and inscribed_radius_m is not None and inscribed_radius_m > 0:
        hi_l = min(hi_l, params.length_scale_max_thickness * inscribed_radius_m)
    hi_l = max(hi_l, 1.01 * lo_l)
    lo_s, hi_s = (params.signal_std_bounds[0] * extent, params.signal_std_bounds[1] * extent)
    return (lo_s ** 2, hi_s ** 2), (lo_l, hi_l)


def initial_hyperparameters(geometry: GridGeometry, train_y: np.ndarray, params: GpisParams,
                            inscribed_radius_m: float | None = None) -> tuple[float, float]:
    """Start / default (C, l): given values, else C = mean (y - m)^2 and l = extent / 12 (~2 cells at M = 25)."""
    (c_lo, c_hi), (l_lo, l_hi) = hyperparameter_bounds(geometry, params, inscribed_radius_m)
    c0 = params.signal_variance
    if c0 is None:
        c0 = float(np.clip(np.mean((train_y - params.prior_mean) ** 2), c_lo, c_hi))
    l0 = params.length_scale if params.length_scale is not None else float(
        np.clip(max(geometry.size_m) / 12.0, l_lo, l_hi))
    return float(c0), float(l0)


_WALL = 1e25  # objective value L-BFGS-B sees where K + N cannot be factorised (counted and logged)


def _search_subset(obs: _Observations, max_points: int, rng: np.random.Generator,
                   eligible: np.ndarray | None = None) -> _Observations:
    """At most ``max_points`` observations: a random subset of the (``eligible``) value cells with their gradients."""
    pool = np.arange(obs.n_values) if eligible is None else np.flatnonzero(eligible)
    if pool.size == 0:
        pool = np.arange(obs.n_values)
    if eligible is None and obs.size <= max_points:
        return obs
    n_cells = min(pool.size, max(1, int(max_points * obs.n_values / obs.size)))
    cells = rng.choice(pool, n_cells, replace=False)
    keys = {tuple(p) for p in np.round(obs.xy[cells] * 1e9).astype(np.int64).tolist()}
    grads = np.arange(obs.n_values, obs.size)
    grad_keys = np.round(obs.xy[grads] * 1e9).astype(np.int64).tolist()
    chosen = grads[np.array([tuple(p) in keys for p in grad_keys], dtype=bool)] if grads.size else grads
    return obs.subset(np.concatenate([cells, chosen]))


def fit_hyperparameters(geometry: GridGeometry, obs: _Observations, params: GpisParams,
                        eligible: np.ndarray | None = None,
                        inscribed_radius_m: float | None = None) -> HyperparameterFit:
    """Maximum-marginal-likelihood C (m^2) and l (m) from values and gradient observations.

    L-BFGS-B on (log C, log l) within :func:`hyperparameter_bounds`, on a seeded subset of at most
    ``max_opt_points`` observations. Binding bounds and Cholesky failures are logged and
    reported on the returned :class:`HyperparameterFit`.
    """
    with blas_threads(params.blas_threads):
        return _fit_hyperparameters(geometry, obs, params, eligible, inscribed_radius_m)


def _fit_hyperparameters(geometry: GridGeometry, obs: _Observations, params: GpisParams,
                         eligible: np.ndarray | None, inscribed_radius_m: float | None) -> HyperparameterFit:
    rng = np.random.default_rng(params.seed)
    sub = _search_subset(obs, params.max_opt_points, rng, eligible)
    kernel = _DenseKernel(sub)
    resid = sub.y - np.where(sub.kind == VALUE, params.prior_mean, 0.0)
    noise = sub.noise + params.jitter
    (c_lo, c_hi), (l_lo, l_hi) = bounds = hyperparameter_bounds(geometry, params, inscribed_radius_m)
    log_bounds = [(math.log(c_lo), math.log(c_hi)), (math.log(l_lo), math.log(l_hi))]
    c0, l0 = initial_hyperparameters(geometry, sub.y[:sub.n_values], params, inscribed_radius_m)
    starts = [np.log([np.clip(c0, c_lo, c_hi), np.clip(l0, l_lo, l_hi)])]
    for _ in range(params.n_restarts):
        starts.append(np.array([rng.uniform(*log_bounds[0]), rng.uniform(*log_bounds[1])]))
    failures = [0]

    def objective(x: np.ndarray) -> tuple[float, np.ndarray]:
        try:
            return negative_log_marginal_likelihood(x, kernel, resid, noise)
        except np.linalg.LinAlgError:
            failures[0] += 1
            return _WALL, np.zeros(2)

    best_x, best_f, failed_starts = starts[0], math.inf, 0
    for x0 in starts:
        before = failures[0]
        f0 = objective(x0)[0]
        if failures[0] > before:
            failed_starts += 1
            continue  # L-BFGS-B cannot move from a start without a likelihood
        res = minimize(objective, x0, jac=True, method='L-BFGS-B', bounds=log_bounds, options={'maxiter': 200})
        fun = float(res.fun) if res.fun < _WALL else f0
        x = res.x if res.fun < _WALL else x0
        if fun < best_f:
            best_x, best_f = x, fun
    ok = math.isfinite(best_f)
    if failures[0]:
        logger.warning('hyperparameter search: K + N was not positive definite at %d of the likelihood '
                       'evaluations (%d of %d starts unusable)', failures[0], failed_starts, len(starts))
    if not ok:
        logger.error('hyperparameter search failed at every start: keeping the start values C = %.3g m^2, '
                     'l = %.3g m', math.exp(starts[0][0]), math.exp(starts[0][1]))
    hits = []
    for i, name in enumerate(('signal_variance', 'length_scale')):
        lo, hi = log_bounds[i]
        if ok and best_x[i] <= lo + 1e-6:
            hits.append(f'{name}_lower')
        elif ok and best_x[i] >= hi - 1e-6:
            hits.append(f'{name}_upper')
    c, ell = math.exp(best_x[0]), math.exp(best_x[1])
    if hits:
        logger.warning('maximum-likelihood hyperparameters sit on the bound(s) %s: C = %.3g m^2 in [%.3g, %.3g], '
                       'l = %.3g m in [%.3g, %.3g]', ', '.join(hits), c, c_lo, c_hi, ell, l_lo, l_hi)
    return HyperparameterFit(signal_variance=c, length_scale=ell, log_likelihood=-best_f if ok else math.nan,
                             bounds=bounds, bound_hits=tuple(hits), cholesky_failures=failures[0],
                             failed_starts=failed_starts, n_starts=len(starts), n_observations=sub.size, ok=ok)


# ----------------------------------------------------------------------------------------------
# public entry points

def fit_gpis(sdf_m: np.ndarray, noise_variance_m2: np.ndarray, train_mask: np.ndarray, geometry: GridGeometry,
             params: GpisParams = GpisParams()) -> GpisPosterior:
    """GPIS posterior from a grid SDF and noise map (sections III-A, III-B, V-A).

    Args:
        sdf_m: ``(H, W)`` observed signed distances (m), e.g. :func:`~gpis_grasp_ros.core.sdf.signed_distance`.
        noise_variance_m2: ``(H, W)`` observation-noise variance of each SDF value (m^2).
        train_mask: ``(H, W)`` bool, cells used for training (missing measurements excluded).
        geometry: placement of the grid (cell centres are the training inputs, m).
        params: prior mean, gradient observations, hyperparameter search, numerical settings.

    Returns:
        :class:`GpisPosterior` with mean (eq. 1), variance (eq. 2), mean gradient, joint
        covariance factor and the training data that reproduce it (:func:`posterior_from_data`).
        With ``params.gradient_observations`` the GP is also trained on the SDF's central-difference
        gradient (:func:`gradient_observations`).
    """
    sdf = np.asarray(sdf_m, dtype=np.float64)
    noise = np.asarray(noise_variance_m2, dtype=np.float64)
    mask = np.asarray(train_mask, dtype=bool)
    if sdf.shape != geometry.shape or noise.shape != geometry.shape or mask.shape != geometry.shape:
        raise ValueError(f'sdf {sdf.shape}, noise {noise.shape} and train_mask {mask.shape} must all match the '
                         f'grid shape {geometry.shape}')
    if not mask.any():
        raise ValueError('train_mask selects no cell: nothing to fit the GPIS to')
    if not (np.all(np.isfinite(sdf[mask])) and np.all(np.isfinite(noise[mask]))):
        raise ValueError('training data contain non-finite values')
    centers = geometry.cell_centers()
    gradients = None
    if params.gradient_observations:
        gradients = gradient_observations(sdf, noise, mask, geometry, params.gradient_noise_variance)
    obs = _observations_from(centers[mask], sdf[mask], noise[mask], gradients)
    inscribed_radius = max(0.0, -float(sdf.min()))  # m, largest inscribed radius of the object (Thickness bound)
    with blas_threads(params.blas_threads):
        fit = None
        if params.optimize_hyperparameters:
            eligible = None
            if params.search_band_cells is not None:
                eligible = np.abs(sdf[mask]) <= params.search_band_cells * geometry.resolution
            fit = fit_hyperparameters(geometry, obs, params, eligible, inscribed_radius)
            c, ell = fit.signal_variance, fit.length_scale
        else:
            c, ell = initial_hyperparameters(geometry, obs.y[:obs.n_values], params, inscribed_radius)
        kp = KernelParams(signal_variance=c, length_scale=ell, prior_mean=params.prior_mean)
        return _condition(geometry, kp, obs, params.jitter, params.max_exact_points, params.rank_tolerance,
                          params.max_rank, params.optimize_hyperparameters, fit)


def posterior_from_data(geometry: GridGeometry, kernel_params: KernelParams, train_xy: np.ndarray,
                        train_y: np.ndarray, train_noise: np.ndarray, jitter: float = 0.0, *,
                        train_grad_xy: np.ndarray | None = None, train_grad_axis: np.ndarray | None = None,
                        train_grad: np.ndarray | None = None, train_grad_noise: np.ndarray | None = None,
                        hyperparameters_optimized: bool = False, max_exact_points: int = 2500,
                        rank_tolerance: float = 1e-10, max_rank: int = 2000,
                        blas_threads_limit: int | None = 1) -> GpisPosterior:
    """Rebuild the GPIS posterior from its training data (what a ``GpisModel`` message carries).

    Values ``train_*`` and, optionally, gradient observations ``train_grad_*`` (component
    ``train_grad_axis`` 0 = d/dx, 1 = d/dy at ``train_grad_xy``, dimensionless values and noise).
    With the same numerical settings as the :class:`GpisParams` used by :func:`fit_gpis` (the
    defaults match), the result equals ``fit_gpis``'s to rounding. Training inputs may lie
    off the cell centres: mean, variance and gradient stay exact (exact path), while the
    Kronecker basis behind ``cov_factor`` is extended by the Nystroem formula, which drops the
    part of the prior not determined by the grid values (~1e-4 C for l = 2 cells).
    """
    gradients = None
    if train_grad_xy is not None and np.asarray(train_grad_xy).size:
        gradients = (train_grad_xy, train_grad_axis, train_grad, train_grad_noise)
    obs = _observations_from(train_xy, np.asarray(train_y, dtype=np.float64).ravel(),
                             np.asarray(train_noise, dtype=np.float64).ravel(), gradients)
    with blas_threads(blas_threads_limit):
        return _condition(geometry, kernel_params, obs, float(jitter), max_exact_points, rank_tolerance, max_rank,
                          hyperparameters_optimized)


def build_gpis(sensing_result: SensingResult, params: GpisParams = GpisParams()) -> GpisPosterior:
    """Section III-B end to end: SDF of the occupancy with every unknown cell as object, GPR on the others.

    Unknown = outside ``train_mask`` (missing, or uncertain: the sensing module's Noise map), exactly as
    :func:`~gpis_grasp_ros.core.pipeline.publishable_grids` publishes them (-1) for gpis_node.
    """
    geometry = sensing_result.geometry
    train_mask = getattr(sensing_result, 'train_mask', None)
    if train_mask is None:
        train_mask = ~np.asarray(sensing_result.missing, dtype=bool)
    train_mask = np.asarray(train_mask, dtype=bool)
    sdf = signed_distance((np.asarray(sensing_result.occupancy) >= 0.5) | ~train_mask, geometry.resolution)
    return fit_gpis(sdf, sensing_result.noise_variance, train_mask, geometry, params)
