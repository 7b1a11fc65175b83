"""Gaussian process implicit surfaces (paper sections III-A and V-A).

CONTRACT (other modules rely on it; extend, do not rename):

``GpisPosterior`` holds a GPIS posterior on the cells of a :class:`~gpis_grasp_ros.core.grid.GridGeometry`:

* ``mean``       (H, W) float64, posterior mean signed distance mu (m), eq. 1
* ``variance``   (H, W) float64, posterior marginal variance sigma^2 (m^2), eq. 2
* ``gradient``   (H, W, 2) float64, d mu / dx and d mu / dy (dimensionless), kernel derivative
* ``cov_factor`` (H*W, r) float64, L with joint posterior covariance Sigma ~= L L^T over the
  row-major flattened grid; used by :meth:`GpisPosterior.sample`
* ``params``     :class:`KernelParams` (C in m^2, l in m, constant prior mean in m)
* training data: ``train_xy`` (n, 2) m, ``train_y`` (n,) m, ``train_noise`` (n,) m^2

Model (section III-A): f ~ GP(m, k), k(xi, xj) = C exp(-|xi - xj|^2 / (2 l^2)), observations
y_i = f(x_i) + e_i with e_i ~ N(0, s_i^2), s_i^2 = ``train_noise[i]`` (the sensing noise map) plus
``jitter``. The prior mean m is a constant, *negative* so that space without data leans to
"object" (section III-B). Default m = -0.01 m: the interior depth of a tabletop object about
2 cm wide; it is in metres and does not depend on the grid size M. C and l are set by maximum
marginal likelihood (type-II ML, Rasmussen & Williams eq. 5.8/5.9) unless fixed.

Computation. On the grid the prior covariance of all H x W cells is the Kronecker product
C (K_y (x) K_x) of two 1-D SE matrices (the SE kernel is separable), so its eigenpairs are
products of 1-D eigenpairs: the prior is f = m + G w, w ~ N(0, I), with the Karhunen-Loeve
basis G = sqrt(C) (U_y L_y^1/2 (x) U_x L_x^1/2) restricted to the r product modes whose
eigenvalue is at least ``tol`` x the largest. Conditioning on the n observations is done in
this weight space (Woodbury / Bayesian linear regression):

    P = I + G_X^T N^-1 G_X  (r x r, P >= I),   w_mean = P^-1 G_X^T N^-1 (y - m),
    alpha = (K + N)^-1 (y - m) = N^-1 (y - m - G_X w_mean),
    mu(x*) = m + k(X, x*)^T alpha  (eq. 1),   grad mu(x*) = sum_i alpha_i d k(x*, x_i)/d x*
    Sigma = G P^-1 G^T = F F^T,  F = G L_P^-T  (``cov_factor``),   sigma^2 = diag(F F^T)  (eq. 2)

with d k / d x* = -k (x* - x) / l^2 (section V-A) and mu, grad mu evaluated as separable
products (H x n)(n x W). P is assembled from the Kronecker structure in O(H W |B|^2 + H |A|^2
|B|^2) (A, B: row / column modes in use) instead of O(n r^2), and F by two GEMMs.

* **exact** (n <= ``max_exact_points``, default 2500): every mode above 1e-15 of the largest is
  kept - the dropped ones are below the rounding error of the 1-D eigendecompositions - so
  this is exact GP regression to rounding (checked against textbook dense GPR and
  scikit-learn to ~1e-10 m). Because the SE spectrum decays like exp(-w^2 l^2 / 2), r is set
  by the grid's extent in length scales rather than by n, so even the exact path costs
  O(r^3) with r <= H W instead of O(n^3). Training inputs off the cell centres (possible in
  :func:`posterior_from_data`) use a function-space Cholesky of K + N for mean and variance.
* **reduced_rank** (n > ``max_exact_points``): the same algorithm with the looser
  ``rank_tolerance`` (1e-10) and at most ``max_rank`` modes - a reduced-rank (truncated
  Karhunen-Loeve) GP; ``truncation`` reports the dropped share of the prior variance. Its
  error against the exact posterior is measured in ``bench_gpis`` (M = 25, 50 and 100 against
  scikit-learn) and bounded in ``test_gpis``. r ~ 700 for object SDFs at any M, so M = 100
  (10^4 cells) fits in well under a second and 1000 joint samples never form the 10^4 x 10^4
  covariance (800 MB).

The joint covariance factor has r columns; P >= I needs no jitter (``jitter`` is still added to
every noise variance, as the GpisModel message documents).

Hyperparameters: the negative log marginal likelihood and its analytic gradient in
(log C, log l) are minimised with L-BFGS-B within bounds proportional to the grid extent E
(sqrt(C) in [E/1000, 2E], l in [E/25, E/12]), from a data-driven start (C = mean (y - m)^2,
l = E/12) plus ``n_restarts`` seeded log-uniform starts, on a seeded random subset of at most
``max_opt_points`` training points (subset-of-data for model selection; the posterior then uses
all points). ``optimize_hyperparameters=False`` uses the given values or that same data-driven start.

Upper bound on l (a documented choice): the SE posterior mean is a low-pass filter of the SDF
at scale l, and an SDF has kinks along the medial axis; maximum likelihood on object SDFs
prefers l ~ 3-6 cells at M = 25, which erased thin parts of the shipped recordings (the nail,
2 cells wide, vanished from the mean shape - IoU with the true shape 0.0 instead of 0.5 - and
the toy plane's IoU fell from ~0.8 to ~0.55). l <= E/12 (about 2 cells at M = 25, the paper's
grid) keeps such parts, and makes the posterior more uncertain inside missing regions, as the
paper intends. Being relative to E, the bound (and the Kronecker rank r) does not change with M.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.linalg import cho_factor, cho_solve, eigh, solve_triangular
from scipy.linalg.lapack import dpotri, dtrtri
from scipy.optimize import minimize

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.sdf import signed_distance

if TYPE_CHECKING:  # pragma: no cover
    from gpis_grasp_ros.core.sensing import SensingResult

LOG_2PI = math.log(2.0 * math.pi)
_BLAS_CONTROLLER: list = []  # lazily created threadpoolctl.ThreadpoolController (or None if unavailable)


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
    """Settings of :func:`fit_gpis` (lengths in metres, variances in m^2)."""

    prior_mean: float = -0.01  # constant prior mean m (m), negative = "object" (section III-B)
    optimize_hyperparameters: bool = True  # maximise the log marginal likelihood over C and l
    signal_variance: float | None = None  # C (m^2): fixed value, or start of the search; None = data-driven
    length_scale: float | None = None  # l (m): fixed value, or start of the search; None = extent / 12
    n_restarts: int = 2  # extra random starts of L-BFGS-B
    seed: int = 0  # seeds restarts and the model-selection subset
    jitter: float = 1e-10  # m^2 added to every noise variance (diagonal of K + N)
    max_exact_points: int = 2500  # above this many training cells use the reduced-rank path
    max_opt_points: int = 600  # training points used for the hyperparameter search (random subset)
    rank_tolerance: float = 1e-10  # relative eigenvalue cut-off of the Kronecker basis
    max_rank: int = 2000  # cap on the basis size r (memory H*W*r*8 bytes)
    blas_threads: int | None = 1  # BLAS threads during the fit (None = library default), see blas_threads()
    length_scale_bounds: tuple[float, float] = (1.0 / 25.0, 1.0 / 12.0)  # x grid extent (see docstring)
    signal_std_bounds: tuple[float, float] = (1e-3, 2.0)  # sqrt(C) x grid extent

    def __post_init__(self) -> None:
        if self.jitter < 0 or not math.isfinite(self.jitter):
            raise ValueError(f'jitter must be a non-negative number of m^2, got {self.jitter}')
        for name in ('signal_variance', 'length_scale'):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f'{name} must be positive, got {value}')
        if self.max_rank < 1 or not (0 <= self.rank_tolerance < 1):
            raise ValueError('max_rank must be >= 1 and rank_tolerance in [0, 1)')


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
    alpha: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (K + N)^-1 (y - m), 1/m
    approximation: str = 'exact'  # 'exact' or 'reduced_rank' (see module docstring)
    rank: int = 0  # columns of cov_factor (size of the Kronecker basis)
    truncation: float = 0.0  # dropped share of the prior variance by the basis truncation
    log_marginal_likelihood: float = float('nan')  # log p(y | X, C, l, m) of the training data

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

    def predict_mean(self, xy: np.ndarray) -> np.ndarray:
        """Posterior mean mu (m) at arbitrary metric points ``(..., 2)`` (eq. 1), off the grid too."""
        xy = np.asarray(xy, dtype=np.float64)
        pts = xy.reshape(-1, 2)
        out = np.empty(pts.shape[0])
        for sl in self._point_chunks(pts.shape[0]):
            out[sl] = self.params.prior_mean + _cross_kernel(pts[sl], self.train_xy, self.params) @ self.alpha
        return out.reshape(xy.shape[:-1])

    def predict_gradient(self, xy: np.ndarray) -> np.ndarray:
        """Gradient of the posterior mean (dimensionless) at metric points ``(..., 2)`` → ``(..., 2)``.

        d mu / d x* = sum_i alpha_i d k(x*, x_i) / d x*, with d k / d x* = -k (x* - x_i) / l^2.
        """
        xy = np.asarray(xy, dtype=np.float64)
        pts = xy.reshape(-1, 2)
        out = np.empty_like(pts)
        ell2 = self.params.length_scale ** 2
        for sl in self._point_chunks(pts.shape[0]):
            ka = _cross_kernel(pts[sl], self.train_xy, self.params) * self.alpha[None, :]  # (p, n)
            # sum_i ka_i (x* - x_i) = x* sum_i ka_i - sum_i ka_i x_i
            out[sl] = -(pts[sl] * ka.sum(axis=1)[:, None] - ka @ self.train_xy) / ell2
        return out.reshape(xy.shape)

    def _point_chunks(self, p: int) -> list[slice]:
        n = self.train_xy.shape[0]
        if n == 0 or self.alpha.shape != (n,):
            raise ValueError('this posterior carries no training data / representer weights: build it with '
                             'fit_gpis or posterior_from_data to evaluate it off the grid')
        step = max(1, 2_000_000 // n)
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
# kernel helpers

def _se_1d(a: np.ndarray, b: np.ndarray, ell: float) -> np.ndarray:
    """Unit-amplitude 1-D SE factor exp(-(a_i - b_j)^2 / (2 l^2)), shape (len(a), len(b))."""
    d = a[:, None] - b[None, :]
    return np.exp(-0.5 * (d / ell) ** 2)


def _se_1d_grad(a: np.ndarray, b: np.ndarray, ell: float) -> np.ndarray:
    """d/da of :func:`_se_1d`: -(a - b) / l^2 exp(-(a - b)^2 / (2 l^2))."""
    d = a[:, None] - b[None, :]
    return -(d / ell ** 2) * np.exp(-0.5 * (d / ell) ** 2)


def _cross_kernel(a: np.ndarray, b: np.ndarray, kp: KernelParams) -> np.ndarray:
    """k(a_i, b_j) for metric points (p, 2) x (n, 2)."""
    d2 = np.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=-1)
    return kp.signal_variance * np.exp(-0.5 * d2 / kp.length_scale ** 2)


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
class _Basis:
    """Selected product modes (a_k, b_k) of the 1-D eigenpairs of K_y and K_x (unit amplitude)."""

    uy: np.ndarray  # (H, H) eigenvectors of K_y, descending eigenvalues
    lam_y: np.ndarray  # (H,)
    ux: np.ndarray  # (W, W)
    lam_x: np.ndarray  # (W,)
    a: np.ndarray  # (r,) row-mode index of each selected product mode
    b: np.ndarray  # (r,) column-mode index
    truncation: float  # dropped share of the prior variance

    @property
    def rank(self) -> int:
        return self.a.size

    @property
    def fy(self) -> np.ndarray:  # (H, r) sqrt(lambda_y) u_y of each selected mode
        return self.uy[:, self.a] * np.sqrt(self.lam_y[self.a])

    @property
    def fx(self) -> np.ndarray:  # (W, r)
        return self.ux[:, self.b] * np.sqrt(self.lam_x[self.b])


def _eig_desc(k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    lam, u = eigh(k)
    return np.clip(lam[::-1], 0.0, None), u[:, ::-1]


def _kronecker_basis(geometry: GridGeometry, ell: float, tol: float, max_rank: int) -> _Basis:
    """Product eigenpairs of K_y (x) K_x above ``tol`` x the largest, at most ``max_rank``."""
    xs, ys = _grid_axes(geometry)
    lam_x, ux = _eig_desc(_se_1d(xs, xs, ell))
    lam_y, uy = _eig_desc(_se_1d(ys, ys, ell))
    flat = np.outer(lam_y, lam_x).ravel()
    keep = np.flatnonzero(flat >= tol * flat.max())
    keep = keep[np.argsort(-flat[keep], kind='stable')][:max_rank]
    keep = keep[flat[keep] > 0]
    a, b = np.divmod(keep, geometry.width)
    total = flat.sum()
    truncation = float(max(total - flat[keep].sum(), 0.0) / total)
    return _Basis(uy=uy, lam_y=lam_y, ux=ux, lam_x=lam_x, a=a, b=b, truncation=truncation)


def _basis_1d_at(coords: np.ndarray, idx: np.ndarray, on_grid: np.ndarray, axis: np.ndarray, u: np.ndarray,
                 lam: np.ndarray, modes: np.ndarray, ell: float) -> np.ndarray:
    """1-D basis functions sqrt(lambda) u(x) of ``modes`` at ``coords``: exact on cell centres, Nystroem elsewhere."""
    f = u[:, modes] * np.sqrt(lam[modes])
    if np.all(on_grid):
        return f[idx]
    out = np.empty((coords.size, modes.size))
    out[on_grid] = f[idx[on_grid]]
    off = ~on_grid
    # u(x) = k(x, axis) u / lambda  =>  sqrt(lambda) u(x) = k(x, axis) u / sqrt(lambda)
    out[off] = (_se_1d(coords[off], axis, ell) @ u[:, modes]) / np.sqrt(lam[modes])[None, :]
    return out


def _axis_index(coords: np.ndarray, axis: np.ndarray, res: float) -> tuple[np.ndarray, np.ndarray]:
    """Cell index of 1-D metric coordinates and whether each lies on a cell centre (to 1e-6 cell)."""
    idx_f = (coords - axis[0]) / res
    idx = np.rint(idx_f).astype(np.int64)
    on_grid = (np.abs(idx_f - idx) < 1e-6) & (idx >= 0) & (idx < axis.size)
    return np.where(on_grid, idx, 0), on_grid


def _precision_on_grid(basis: _Basis, sqrt_c: float, weights: np.ndarray, max_entries: int = 20_000_000) -> np.ndarray:
    """G_X^T N^-1 G_X (r x r) for training inputs on cell centres, from the Kronecker structure.

    ``weights`` (H, W) holds sum 1/noise of the training points in each cell (0 elsewhere).
    With the row / column modes A, B in use, entry ((a, b), (a', b')) is
    sum_i Fy[i, a] Fy[i, a'] sum_j w_ij Fx[j, b] Fx[j, b']: O(H W |B|^2 + H |A|^2 |B|^2) instead of O(n r^2).
    Returns None when the |A|^2 |B|^2 intermediate would exceed ``max_entries``.
    """
    ua, ia = np.unique(basis.a, return_inverse=True)
    ub, ib = np.unique(basis.b, return_inverse=True)
    if ua.size ** 2 * ub.size ** 2 > max_entries:
        return None
    fy = sqrt_c * basis.uy[:, ua] * np.sqrt(basis.lam_y[ua])  # (H, |A|)
    fx = basis.ux[:, ub] * np.sqrt(basis.lam_x[ub])  # (W, |B|)
    t = np.matmul(np.swapaxes(weights[:, :, None] * fx[None, :, :], 1, 2), fx)  # (H, |B|, |B|)
    u = (fy[:, :, None] * fy[:, None, :]).reshape(fy.shape[0], -1)  # (H, |A|^2)
    p4 = (u.T @ t.reshape(t.shape[0], -1)).reshape(ua.size, ua.size, ub.size, ub.size)
    full = p4.transpose(0, 2, 1, 3).reshape(ua.size * ub.size, ua.size * ub.size)  # ((a, b), (a', b'))
    idx = ia * ub.size + ib
    return full.take(idx, axis=0).take(idx, axis=1)


# ----------------------------------------------------------------------------------------------
# conditioning (shared by fit_gpis and posterior_from_data so both give identical posteriors)

def _validate_training(train_xy: np.ndarray, train_y: np.ndarray, train_noise: np.ndarray) -> None:
    if train_xy.ndim != 2 or train_xy.shape[1] != 2:
        raise ValueError(f'train_xy must have shape (n, 2), got {train_xy.shape}')
    n = train_xy.shape[0]
    if n == 0:
        raise ValueError('no training data: every cell is missing, the GPIS would be the prior only')
    if train_y.shape != (n,) or train_noise.shape != (n,):
        raise ValueError(f'train_y and train_noise must have shape ({n},), got {train_y.shape} and '
                         f'{train_noise.shape}')
    if not (np.all(np.isfinite(train_xy)) and np.all(np.isfinite(train_y)) and np.all(np.isfinite(train_noise))):
        raise ValueError('training data contain non-finite values')
    if np.any(train_noise < 0):
        raise ValueError('training noise variances must be >= 0 m^2')


EXACT_RANK_TOLERANCE = 1e-15  # product eigenvalues below this x the largest are at the rounding level


def _condition(geometry: GridGeometry, kp: KernelParams, train_xy: np.ndarray, train_y: np.ndarray,
               train_noise: np.ndarray, jitter: float, max_exact_points: int, rank_tolerance: float,
               max_rank: int, hyperparameters_optimized: bool) -> GpisPosterior:
    """GPIS posterior on ``geometry`` from training data (eqs. 1, 2 and the kernel derivative)."""
    train_xy = np.ascontiguousarray(train_xy, dtype=np.float64)
    train_y = np.ascontiguousarray(train_y, dtype=np.float64)
    train_noise = np.ascontiguousarray(train_noise, dtype=np.float64)
    _validate_training(train_xy, train_y, train_noise)
    c, ell, m = float(kp.signal_variance), float(kp.length_scale), float(kp.prior_mean)
    if not (c > 0 and ell > 0 and math.isfinite(c) and math.isfinite(ell) and math.isfinite(m)):
        raise ValueError(f'invalid kernel parameters {kp}')
    noise = train_noise + jitter
    if np.any(noise <= 0):
        raise ValueError('noise variance + jitter must be > 0 m^2 for every training point')
    n = train_xy.shape[0]
    h, w = geometry.shape
    resid = train_y - m
    xs, ys = _grid_axes(geometry)
    cols, col_on = _axis_index(train_xy[:, 0], xs, geometry.resolution)
    rows, row_on = _axis_index(train_xy[:, 1], ys, geometry.resolution)
    on_grid = bool(np.all(col_on) and np.all(row_on))
    exact = n <= max_exact_points
    approximation = 'exact' if exact else 'reduced_rank'
    basis = _kronecker_basis(geometry, ell, EXACT_RANK_TOLERANCE if exact else rank_tolerance,
                             h * w if exact else max_rank)
    sqrt_c = math.sqrt(c)
    fy_sel = sqrt_c * basis.fy  # (H, r): f = m + sum_k w_k fy[:, k] fx[:, k]^T on the grid
    fx_sel = basis.fx  # (W, r)

    # weight-space precision P = I + G_X^T N^-1 G_X and G_X^T N^-1 (y - m)
    precision = None
    if on_grid:
        weights = np.zeros((h, w))
        np.add.at(weights, (rows, cols), 1.0 / noise)
        precision = _precision_on_grid(basis, sqrt_c, weights)
        rhs_grid = np.zeros((h, w))
        np.add.at(rhs_grid, (rows, cols), resid / noise)
        g_rhs = np.einsum('ik,ij,jk->k', fy_sel, rhs_grid, fx_sel)
    if precision is None:
        fx_tr = _basis_1d_at(train_xy[:, 0], cols, col_on, xs, basis.ux, basis.lam_x, basis.b, ell)
        fy_tr = _basis_1d_at(train_xy[:, 1], rows, row_on, ys, basis.uy, basis.lam_y, basis.a, ell)
        g_train = sqrt_c * fy_tr * fx_tr  # (n, r) basis functions at the training inputs
        g_scaled = g_train / noise[:, None]
        precision = g_train.T @ g_scaled
        g_rhs = g_scaled.T @ resid
    precision[np.diag_indices_from(precision)] += 1.0
    chol_p = np.linalg.cholesky(precision)  # P >= I: always positive definite, no jitter needed

    variance = None
    if on_grid or not exact:
        # representer weights from the weight-space posterior mean (Woodbury):
        # alpha = (K + N)^-1 (y - m) = N^-1 (y - m - G_X w),  w = P^-1 G_X^T N^-1 (y - m)
        w_mean = cho_solve((chol_p, True), g_rhs, check_finite=False)
        f_train = ((fy_sel * w_mean[None, :]) @ fx_sel.T)[rows, cols] if on_grid else g_train @ w_mean
        alpha = (resid - f_train) / noise
        logdet = 2.0 * float(np.sum(np.log(np.diag(chol_p)))) + float(np.sum(np.log(noise)))
        lml = -0.5 * float(resid @ alpha) - 0.5 * logdet - 0.5 * n * LOG_2PI
    else:  # exact with inputs off the grid: function-space Cholesky (the basis only serves sampling)
        k_xx = c * np.exp(-0.5 * _sq_dists(train_xy) / ell ** 2)
        k_xx[np.diag_indices_from(k_xx)] += noise
        cf = cho_factor(k_xx, lower=True, check_finite=False)
        alpha = cho_solve(cf, resid, check_finite=False)
        lml = -0.5 * float(resid @ alpha) - float(np.sum(np.log(np.diag(cf[0])))) - 0.5 * n * LOG_2PI
        variance = _exact_variance(cf[0], c, _se_1d(xs, train_xy[:, 0], ell), _se_1d(ys, train_xy[:, 1], ell))

    # Sigma = G P^-1 G^T = (G L_P^-T)(G L_P^-T)^T; its diagonal is eq. 2
    cov_factor = _covariance_factor(basis, sqrt_c, chol_p, h, w)
    if variance is None:
        variance = np.einsum('ij,ij->i', cov_factor, cov_factor)

    # eq. 1 and its gradient with the SE kernel: separable products (H x n)(n x W)
    kx_star = _se_1d(xs, train_xy[:, 0], ell)  # (W, n)
    weighted = _se_1d(ys, train_xy[:, 1], ell) * (c * alpha)[None, :]  # (H, n)
    mean = m + weighted @ kx_star.T
    grad_x = weighted @ _se_1d_grad(xs, train_xy[:, 0], ell).T
    grad_y = (_se_1d_grad(ys, train_xy[:, 1], ell) * (c * alpha)[None, :]) @ kx_star.T
    return GpisPosterior(
        geometry=geometry, mean=mean, variance=np.clip(variance.reshape(h, w), 0.0, None),
        gradient=np.stack([grad_x, grad_y], axis=-1), cov_factor=cov_factor, params=kp,
        train_xy=train_xy, train_y=train_y, train_noise=train_noise, jitter=float(jitter),
        hyperparameters_optimized=hyperparameters_optimized, alpha=alpha, approximation=approximation,
        rank=basis.rank, truncation=basis.truncation, log_marginal_likelihood=lml)


def _covariance_factor(basis: _Basis, sqrt_c: float, chol_p: np.ndarray, h: int, w: int) -> np.ndarray:
    """F = G L_P^-T, (H*W, r), so that Sigma = F F^T, using the Kronecker structure of G.

    L_P^-T is the factor of the weight-space posterior covariance P^-1 (w = w_mean + L_P^-T xi),
    so it is formed once (LAPACK trtri, r^3 / 3). G L_P^-T is then two GEMMs through the
    row / column modes, O(r |A| W (|B| + H)) instead of O(H W r^2).
    """
    r = basis.rank
    inv_l, info = dtrtri(chol_p, lower=1)
    if info != 0:  # pragma: no cover - P >= I is never singular
        raise np.linalg.LinAlgError(f'trtri failed with info={info}')
    factor_w = np.triu(inv_l.T)  # (r, r) = L_P^-T
    ua, ia = np.unique(basis.a, return_inverse=True)
    ub, ib = np.unique(basis.b, return_inverse=True)
    fy = sqrt_c * basis.uy[:, ua] * np.sqrt(basis.lam_y[ua])  # (H, |A|)
    fx = basis.ux[:, ub] * np.sqrt(basis.lam_x[ub])  # (W, |B|)
    if ua.size * ub.size * r > 4 * h * w * r:  # sparse mode set: the dense product is cheaper
        g_grid = ((sqrt_c * basis.fy)[:, None, :] * basis.fx[None, :, :]).reshape(h * w, r)
        return g_grid @ factor_w
    scattered = np.zeros((ua.size, ub.size, r))
    scattered[ia, ib] = factor_w  # rows of L_P^-T placed at their (row mode, column mode)
    q = fx @ scattered.transpose(1, 0, 2).reshape(ub.size, -1)  # (W, |A| r)
    q = q.reshape(w, ua.size, r).transpose(1, 0, 2).reshape(ua.size, -1)  # (|A|, W r)
    return (fy @ q).reshape(h * w, r)


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
# hyperparameters

def negative_log_marginal_likelihood(log_theta: np.ndarray, sq_dists: np.ndarray, resid: np.ndarray,
                                     noise: np.ndarray) -> tuple[float, np.ndarray]:
    """-log p(y | X, C, l) and its gradient in (log C, log l) (Rasmussen & Williams eqs. 5.8, 5.9).

    ``resid`` = y - m (m), ``noise`` per-point variances (m^2, jitter included),
    ``sq_dists`` pairwise squared distances (m^2).
    """
    c, ell = math.exp(log_theta[0]), math.exp(log_theta[1])
    k0 = np.exp(-0.5 * sq_dists / ell ** 2)
    a = c * k0
    a[np.diag_indices_from(a)] += noise
    try:
        cf = cho_factor(a, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return 1e25, np.zeros(2)
    alpha = cho_solve(cf, resid, check_finite=False)
    n = resid.size
    nll = 0.5 * float(resid @ alpha) + float(np.sum(np.log(np.diag(cf[0])))) + 0.5 * n * LOG_2PI
    # d nll / d theta = -1/2 tr((alpha alpha^T - A^-1) dA/dtheta); A^-1 is needed for the trace term
    # (R&W Algorithm 5.1) and is formed from the Cholesky factor (LAPACK potri); it never solves a system.
    inv, info = dpotri(cf[0], lower=1)
    if info != 0:
        return 1e25, np.zeros(2)
    inv_lower = np.tril(inv)  # potri fills the lower triangle only; A^-1 and dA/dtheta are symmetric

    def trace_inv(b: np.ndarray) -> float:  # tr(A^-1 B) for symmetric B from the lower triangle
        return 2.0 * float(np.vdot(inv_lower, b)) - float(np.dot(np.diag(inv_lower), np.diag(b)))

    k0_sq = k0 * sq_dists  # dA/dlog l = C k0 |xi - xj|^2 / l^2
    grad = 0.5 * np.array([
        c * (trace_inv(k0) - float(alpha @ (k0 @ alpha))),
        c / ell ** 2 * (trace_inv(k0_sq) - float(alpha @ (k0_sq @ alpha))),
    ])
    return nll, grad


def hyperparameter_bounds(geometry: GridGeometry,
                          params: GpisParams) -> tuple[tuple[float, float], tuple[float, float]]:
    """Bounds (m^2, m) for C and l, proportional to the grid's metric extent."""
    extent = max(geometry.size_m)
    lo_l, hi_l = (params.length_scale_bounds[0] * extent, params.length_scale_bounds[1] * extent)
    lo_s, hi_s = (params.signal_std_bounds[0] * extent, params.signal_std_bounds[1] * extent)
    return (lo_s ** 2, hi_s ** 2), (lo_l, hi_l)


def initial_hyperparameters(geometry: GridGeometry, train_y: np.ndarray, params: GpisParams) -> tuple[float, float]:
    """Start / default (C, l): given values, else C = mean (y - m)^2 and l = extent / 12."""
    (c_lo, c_hi), (l_lo, l_hi) = hyperparameter_bounds(geometry, params)
    c0 = params.signal_variance
    if c0 is None:
        c0 = float(np.clip(np.mean((train_y - params.prior_mean) ** 2), c_lo, c_hi))
    l0 = params.length_scale if params.length_scale is not None else float(
        np.clip(max(geometry.size_m) / 12.0, l_lo, l_hi))
    return float(c0), float(l0)


def fit_hyperparameters(geometry: GridGeometry, train_xy: np.ndarray, train_y: np.ndarray,
                        train_noise: np.ndarray, params: GpisParams) -> tuple[float, float, float]:
    """Maximum-marginal-likelihood C (m^2) and l (m) → ``(C, l, log-likelihood on the subset)``."""
    rng = np.random.default_rng(params.seed)
    n = train_xy.shape[0]
    if n > params.max_opt_points:
        sub = np.sort(rng.choice(n, params.max_opt_points, replace=False))
        train_xy, train_y, train_noise = train_xy[sub], train_y[sub], train_noise[sub]
    sq = _sq_dists(train_xy)
    resid = train_y - params.prior_mean
    noise = train_noise + params.jitter
    (c_lo, c_hi), (l_lo, l_hi) = hyperparameter_bounds(geometry, params)
    bounds = [(math.log(c_lo), math.log(c_hi)), (math.log(l_lo), math.log(l_hi))]
    c0, l0 = initial_hyperparameters(geometry, train_y, params)
    starts = [np.log([np.clip(c0, c_lo, c_hi), np.clip(l0, l_lo, l_hi)])]
    for _ in range(params.n_restarts):
        starts.append(np.array([rng.uniform(*bounds[0]), rng.uniform(*bounds[1])]))
    best_x, best_f = starts[0], math.inf
    for x0 in starts:
        res = minimize(negative_log_marginal_likelihood, x0, args=(sq, resid, noise), jac=True,
                       method='L-BFGS-B', bounds=bounds, options={'maxiter': 200})
        if res.fun < best_f:
            best_x, best_f = res.x, float(res.fun)
    return math.exp(best_x[0]), math.exp(best_x[1]), -best_f


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
        params: prior mean, hyperparameter search, numerical settings.

    Returns:
        :class:`GpisPosterior` with mean (eq. 1), variance (eq. 2), mean gradient, joint
        covariance factor and the training data that reproduce it (:func:`posterior_from_data`).
    """
    sdf = np.asarray(sdf_m, dtype=np.float64)
    noise = np.asarray(noise_variance_m2, dtype=np.float64)
    mask = np.asarray(train_mask, dtype=bool)
    if sdf.shape != geometry.shape or noise.shape != geometry.shape or mask.shape != geometry.shape:
        raise ValueError(f'sdf {sdf.shape}, noise {noise.shape} and train_mask {mask.shape} must all match the '
                         f'grid shape {geometry.shape}')
    if not mask.any():
        raise ValueError('train_mask selects no cell: nothing to fit the GPIS to')
    centers = geometry.cell_centers()
    train_xy = centers[mask]
    train_y = sdf[mask]
    train_noise = noise[mask]
    _validate_training(train_xy, train_y, train_noise)
    with blas_threads(params.blas_threads):
        if params.optimize_hyperparameters:
            c, ell, _ = fit_hyperparameters(geometry, train_xy, train_y, train_noise, params)
        else:
            c, ell = initial_hyperparameters(geometry, train_y, params)
        kp = KernelParams(signal_variance=c, length_scale=ell, prior_mean=params.prior_mean)
        return _condition(geometry, kp, train_xy, train_y, train_noise, params.jitter, params.max_exact_points,
                          params.rank_tolerance, params.max_rank, params.optimize_hyperparameters)


def posterior_from_data(geometry: GridGeometry, kernel_params: KernelParams, train_xy: np.ndarray,
                        train_y: np.ndarray, train_noise: np.ndarray, jitter: float = 0.0, *,
                        hyperparameters_optimized: bool = False, max_exact_points: int = 2500,
                        rank_tolerance: float = 1e-10, max_rank: int = 2000,
                        blas_threads_limit: int | None = 1) -> GpisPosterior:
    """Rebuild the GPIS posterior from its training data (what a ``GpisModel`` message carries).

    With the same numerical settings as the :class:`GpisParams` used by :func:`fit_gpis` (the
    defaults match), the result equals ``fit_gpis``'s to rounding. Training inputs may lie
    off the cell centres: mean, variance and gradient stay exact (exact path), while the
    Kronecker basis behind ``cov_factor`` is extended by the Nystroem formula, which drops the
    part of the prior not determined by the grid values (~1e-4 C for l = 2 cells).
    """
    with blas_threads(blas_threads_limit):
        return _condition(geometry, kernel_params, np.asarray(train_xy, dtype=np.float64).reshape(-1, 2),
                          np.asarray(train_y, dtype=np.float64).ravel(),
                          np.asarray(train_noise, dtype=np.float64).ravel(), float(jitter), max_exact_points,
                          rank_tolerance, max_rank, hyperparameters_optimized)


def build_gpis(sensing_result: SensingResult, params: GpisParams = GpisParams()) -> GpisPosterior:
    """Section III-B end to end: SDF of the occupancy (missing = object), GPR on non-missing cells."""
    geometry = sensing_result.geometry
    sdf = signed_distance(sensing_result.occupancy, geometry.resolution)
    train_mask = getattr(sensing_result, 'train_mask', None)
    if train_mask is None:
        train_mask = ~np.asarray(sensing_result.missing, dtype=bool)
    return fit_gpis(sdf, sensing_result.noise_variance, train_mask, geometry, params)
