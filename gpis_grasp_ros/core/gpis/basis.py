"""Kronecker (Karhunen-Loeve) eigenbasis of the GPIS prior on the grid, and the products it makes cheap.

The SE kernel is separable, so on the cell centres the prior is C (K_y (x) K_x): the eigenpairs of
two 1-D matrices (joint value/derivative matrices with gradient observations) give every product
mode. The weight-space conditioning (:mod:`~gpis_grasp_ros.core.gpis.regression`) uses them for
P = I + G_X^T N^-1 G_X and for the covariance factor G L_P^-T.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import eigh, qr
from scipy.linalg.lapack import dtrtri

from gpis_grasp_ros.core.gpis.kernel import _se_1d
from gpis_grasp_ros.core.gpis.observations import GRAD_X, GRAD_Y
from gpis_grasp_ros.core.grid import GridGeometry


def _grid_axes(geometry: GridGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Metric x of the columns (W,) and y of the rows (H,) of the grid's cell centres."""
    res = geometry.resolution
    xs = geometry.origin_x + (np.arange(geometry.width) + 0.5) * res
    ys = geometry.origin_y + (np.arange(geometry.height) + 0.5) * res
    return xs, ys


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
    capped: bool = False  # modes above the tolerance were dropped to keep at most max_rank

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
    keep = keep[flat[keep] > 0]
    capped = max_rank is not None and keep.size > max_rank
    keep = keep[np.argsort(-flat[keep], kind='stable')][:max_rank]
    a, b = np.divmod(keep, mx.lam.size)
    total = flat.sum()
    truncation = float(max(total - flat[keep].sum(), 0.0) / total)
    return _Basis(my, mx, a, b, truncation, capped)


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
