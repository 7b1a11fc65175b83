"""Log marginal likelihood of the GPIS observations, its gradient and Fisher information in (log C, log l).

The model-selection objective of :mod:`.hyperparameters` (Rasmussen & Williams eqs. 5.8, 5.9). One
evaluation is one compiled pass that writes K + N and d K / d log l (lower triangles, Fortran order,
into buffers reused across evaluations), the in-place LAPACK Cholesky and inverse, and one compiled
pass for the trace terms (docs/gpis-model.md, Speed).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from scipy.linalg.lapack import dpotrf, dpotri, dpotrs

from gpis_grasp_ros.core.gpis.observations import _Observations

LOG_2PI = math.log(2.0 * math.pi)


@njit(cache=True, nogil=True, fastmath=True)
def _gram_lower(x, y, px, py, c, ell, noise, a, d):  # pragma: no cover - compiled
    """a = C k0 + N and d = d k0 / d log l on the lower triangle (j <= i) of Fortran-ordered buffers.

    Per axis the derivative-observation factor is w00 + (s d + w11) / l^2 - w11 d^2 / l^4 (kernel.py,
    _DenseKernel), written branch-free in the derivative orders p (row) and q (column) so that the
    inner loop vectorises.
    """
    n = x.size
    il2 = 1.0 / (ell * ell)
    il4 = il2 * il2
    for j in range(n):
        xj, yj, qx, qy = x[j], y[j], px[j], py[j]
        for i in range(j, n):
            dx = x[i] - xj
            dy = y[i] - yj
            r2 = dx * dx + dy * dy
            s = math.exp(-0.5 * il2 * r2)
            ppx, ppy = px[i], py[i]
            w11x, w11y = ppx * qx, ppy * qy
            ax = (qx - ppx) * dx + w11x
            ay = (qy - ppy) * dy + w11y
            bx = w11x * dx * dx
            by = w11y * dy * dy
            fx = (1.0 - ppx) * (1.0 - qx) + ax * il2 - bx * il4
            fy = (1.0 - ppy) * (1.0 - qy) + ay * il2 - by * il4
            dfx = -2.0 * il2 * ax + 4.0 * il4 * bx
            dfy = -2.0 * il2 * ay + 4.0 * il4 * by
            k0 = s * fx * fy
            a[i, j] = c * k0
            d[i, j] = k0 * (r2 * il2) + s * (dfx * fy + fx * dfy)
        a[j, j] += noise[j]


@njit(cache=True, nogil=True, fastmath=True)
def _trace_terms(inv, d, alpha, noise):  # pragma: no cover - compiled
    """(tr(A^-1 N), alpha^T N alpha, tr(A^-1 D) - alpha^T D alpha) from the lower triangles of inv and d."""
    n = alpha.size
    tr_n = 0.0
    an = 0.0
    tl = 0.0
    for j in range(n):
        aj = alpha[j]
        tr_n += noise[j] * inv[j, j]
        an += noise[j] * aj * aj
        tl += (inv[j, j] - aj * aj) * d[j, j]
        off = 0.0
        for i in range(j + 1, n):
            off += (inv[i, j] - alpha[i] * aj) * d[i, j]
        tl += 2.0 * off
    return tr_n, an, tl


class _LikelihoodWorkspace:
    """Observation geometry of one search subset and the n x n buffers its likelihood evaluations reuse.

    After an evaluation ``inv`` holds (K + N)^-1 and ``d`` holds d k0 / d log l (lower triangles) at
    that evaluation's hyperparameters; :func:`fisher_information` reads them.
    """

    def __init__(self, obs: _Observations) -> None:
        self.x = np.ascontiguousarray(obs.xy[:, 0], dtype=np.float64)
        self.y = np.ascontiguousarray(obs.xy[:, 1], dtype=np.float64)
        self.px = obs.px.astype(np.float64)
        self.py = obs.py.astype(np.float64)
        n = obs.size
        self.a = np.empty((n, n), order='F')
        self.d = np.empty((n, n), order='F')
        self.inv: np.ndarray | None = None  # (K + N)^-1 (lower triangle, in a's memory; whole after fisher_information)
        self.log_theta: np.ndarray | None = None  # where inv and d were last evaluated
        self.signal_step = 0.0  # log C* - log C of the last evaluation (profile_signal_variance)

    @property
    def size(self) -> int:
        return self.x.size


def negative_log_marginal_likelihood(log_theta: np.ndarray, workspace: _LikelihoodWorkspace, resid: np.ndarray,
                                     noise: np.ndarray) -> tuple[float, np.ndarray]:
    """-log p(y | X, C, l) and its gradient in (log C, log l) (Rasmussen & Williams eqs. 5.8, 5.9).

    ``workspace`` holds the observations (values and gradient components), ``resid`` = y - m
    (values) or the gradient observation, ``noise`` per-observation variances (jitter included).
    With A = C k0 + N: d A / d log C = C k0 = A - N, so that component needs only diag(A^-1);
    d A / d log l = C d k0 / d log l. Raises ``numpy.linalg.LinAlgError`` when A is not numerically
    positive definite (the caller records it; no silent substitute value).
    """
    c, ell = math.exp(log_theta[0]), math.exp(log_theta[1])
    ws = workspace
    ws.log_theta = None
    _gram_lower(ws.x, ws.y, ws.px, ws.py, c, ell, noise, ws.a, ws.d)
    chol, info = dpotrf(ws.a, lower=1, clean=0, overwrite_a=1)
    if info != 0:
        raise np.linalg.LinAlgError(f'K + N is not positive definite (potrf info={info})')
    alpha, info = dpotrs(chol, resid, lower=1)
    if info != 0:  # pragma: no cover - potrs fails only on invalid arguments
        raise np.linalg.LinAlgError(f'potrs failed with info={info}')
    n = resid.size
    r_alpha = float(resid @ alpha)
    nll = 0.5 * r_alpha + float(np.sum(np.log(np.diagonal(chol)))) + 0.5 * n * LOG_2PI
    inv, info = dpotri(chol, lower=1, overwrite_c=1)  # A^-1 in the lower triangle (R&W Algorithm 5.1)
    if info != 0:
        raise np.linalg.LinAlgError(f'potri failed with info={info}')
    tr_n, an, tl = _trace_terms(inv, ws.d, alpha, noise)
    ws.inv = inv
    quad, trace = r_alpha - an, n - tr_n  # alpha^T C k0 alpha and tr(A^-1 C k0): equal at the optimum in C
    ws.signal_step = math.log(quad / trace) if quad > 0 and trace > 0 else 0.0
    # d nll / d theta = 1/2 tr((A^-1 - alpha alpha^T) dA/dtheta)
    grad = 0.5 * np.array([(n - tr_n) - (r_alpha - an), c * tl])
    if not (math.isfinite(nll) and np.all(np.isfinite(grad))):
        raise np.linalg.LinAlgError('non-finite marginal likelihood')
    ws.log_theta = np.array(log_theta, dtype=np.float64)
    return nll, grad


def profile_signal_variance(workspace: _LikelihoodWorkspace) -> float:
    """log C* - log C at the last evaluation: the optimum of C given l if the noise were proportional to C.

    The likelihood is stationary in C where alpha^T C k0 alpha = tr(A^-1 C k0). Without noise
    (or with N proportional to C) the quadratic form scales as 1/C and the trace is constant, so
    C* = C alpha^T C k0 alpha / tr(A^-1 C k0) in closed form; with the sensing noise N, far below
    C k0 here, it is the fixed-point step towards the optimum (docs/gpis-model.md, Speed).
    """
    return workspace.signal_step


@njit(cache=True, nogil=True)
def _symmetrise_lower(m):  # pragma: no cover - compiled
    """Copy the lower triangle of the square matrix ``m`` onto its upper triangle, in place."""
    n = m.shape[0]
    for j in range(n):
        for i in range(j + 1, n):
            m[j, i] = m[i, j]


@njit(cache=True, nogil=True)
def _fisher_terms(inv, p, noise):  # pragma: no cover - compiled
    """(sum_ij N_i inv_ij^2 N_j, tr(inv N), tr(P), sum_ij inv_ij N_j P_ji, sum_ij P_ij P_ji) of symmetric ``inv``."""
    n = noise.size
    quad = 0.0
    tr_n = 0.0
    tr_p = 0.0
    inp = 0.0
    pp = 0.0
    for j in range(n):
        nj = noise[j]
        tr_n += nj * inv[j, j]
        tr_p += p[j, j]
        for i in range(n):
            v = inv[i, j]
            quad += noise[i] * v * v * nj
            inp += v * nj * p[j, i]
            pp += p[i, j] * p[j, i]
    return quad, tr_n, tr_p, inp, pp


def fisher_information(workspace: _LikelihoodWorkspace, noise: np.ndarray) -> np.ndarray:
    """Fisher information of (log C, log l), 1/2 tr(A^-1 dA_i A^-1 dA_j), at the last evaluation's hyperparameters.

    The covariance of the likelihood's gradient when the data are a draw of the GP (the score
    test of the warm start, :mod:`.hyperparameters`). With M_C = A^-1 (A - N) = I - A^-1 N only
    M_l = A^-1 dA / dlog l needs a matrix product (one GEMM); the traces are one compiled pass.
    The workspace's two triangles are made symmetric in place (the next evaluation rewrites them).
    """
    ws = workspace
    if ws.log_theta is None:
        raise ValueError('no successful likelihood evaluation in this workspace')
    c = math.exp(ws.log_theta[0])
    _symmetrise_lower(ws.inv)
    _symmetrise_lower(ws.d)
    p = ws.inv @ ws.d  # A^-1 d k0 / d log l
    quad, tr_n, tr_p, inp, pp = _fisher_terms(ws.inv, p, np.ascontiguousarray(noise, dtype=np.float64))
    n = noise.size
    cc = n - 2.0 * tr_n + quad
    # tr(M_C M_l) = C (tr(P) - tr(A^-1 N P)),  tr(A^-1 N P) = sum_ij inv_ij N_j P_ji
    cl = c * (tr_p - inp)
    ll = c * c * pp
    return 0.5 * np.array([[cc, cl], [cl, ll]])
