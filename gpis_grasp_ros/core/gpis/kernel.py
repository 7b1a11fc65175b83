"""Squared-exponential kernel of the GPIS and its derivatives (paper section III-A, derivative observations).

k(xi, xj) = C exp(-|xi - xj|^2 / (2 l^2)); the covariances of gradient observations are its
derivatives (docs/gpis-model.md, Model). Kept apart from the regression so that the likelihood,
the grid basis and the posterior evaluate the same kernel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpis_grasp_ros.core.gpis.observations import _Observations


@dataclass(frozen=True)
class KernelParams:
    """Squared-exponential kernel k = C exp(-|xi - xj|^2 / (2 l^2)) and constant prior mean."""

    signal_variance: float  # C, m^2
    length_scale: float  # l, m
    prior_mean: float  # m (negative: unobserved space leans to "object")


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
    row and column observation), precomputed once. The conditioning's off-grid path uses it; the
    likelihood's compiled pass (likelihood._gram_lower) evaluates the same formula and is tested against it.
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
