"""Stacks of SDF grids prepared for batched bilinear lookups (the shape model the jaws close on).

Each grid is padded with extrapolated nodes (``f(nearest node) + distance``: the border is free space and a
distance grows at most by the distance travelled) so jaws may start off the grid. The 4 bilinear coefficients of
a cell are stored as one record so a lookup is a single gather; a per-thread workspace reuses large temporaries.
The compiled contact search reads only the float64 padded grids and gradients, built with their Lipschitz
bounds and border tests in one compiled pass; the numpy path's coefficient records are built on its first
lookup (a Monte-Carlo bank never needs them).
"""

from __future__ import annotations

import threading

import numpy as np
from numba import njit

from gpis_grasp_ros.core.contact_kernel import grid_border_positive, grid_lipschitz
from gpis_grasp_ros.core.grid import GridGeometry

#: An SDF gradient norm (dimensionless; 1 for an exact SDF) at or below this defines no normal:
#: the contact is flagged ``no_normal`` (invalid) instead of being given an arbitrary direction.
MIN_GRADIENT_NORM = 1e-6


def _coefficient_records(grids: np.ndarray, dtype: type = np.float32) -> np.ndarray:
    """Per-cell bilinear coefficients of grids ``(B, H, W)`` as records ``(B*H*W, 4)`` of ``dtype``.

    Inside cell (i, j) — corners (i, j)..(i+1, j+1) — ``f = a + b·fx + c·fy + d·fx·fy`` with
    ``fx, fy ∈ [0, 1]`` the fractional column and row offsets. The last row and column of cells
    are degenerate (they only interpolate along the grid's border), so a point exactly on the
    far border needs no index clamping; the row stride is W.
    """
    f = np.asarray(grids)
    out = np.zeros(f.shape + (4,), dtype=dtype)
    out[..., 0] = f
    out[:, :, :-1, 1] = f[:, :, 1:] - f[:, :, :-1]
    out[:, :-1, :, 2] = f[:, 1:, :] - f[:, :-1, :]
    out[:, :-1, :-1, 3] = f[:, 1:, 1:] - f[:, 1:, :-1] - f[:, :-1, 1:] + f[:, :-1, :-1]
    return out.reshape(-1, 4)


def pad_extrapolated(grids: np.ndarray, pad: int, resolution: float) -> np.ndarray:
    """Grids ``(B, H, W)`` padded by ``pad`` nodes per side with ``f(nearest node) + distance`` (the numpy
    reference of the compiled set-up, :func:`_pad_and_gradient`)."""
    ic, jc, dist = _pad_distances(grids.shape[1], grids.shape[2], pad, resolution)
    return grids[:, ic[:, None], jc[None, :]] + dist[None]


def _pad_distances(h: int, w: int, pad: int, resolution: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row and column of the nearest node of each padded node and its distance (m) to it: (Hp,), (Wp,), (Hp, Wp)."""
    ii = np.arange(-pad, h + pad)
    jj = np.arange(-pad, w + pad)
    ic = np.clip(ii, 0, h - 1)
    jc = np.clip(jj, 0, w - 1)
    return ic, jc, np.hypot((ii - ic)[:, None], (jj - jc)[None, :]) * resolution


@njit(cache=True, nogil=True, inline='always')
def _pad_grid(sdf, ic, jc, dist, padded):
    """``padded`` (Hp, Wp) = the value of ``sdf`` (H, W) at the nearest node (``ic``, ``jc``) + ``dist``
    (:func:`pad_extrapolated`, its numpy reference)."""
    hp, wp = dist.shape
    for i in range(hp):
        for j in range(wp):
            padded[i, j] = sdf[ic[i], jc[j]] + dist[i, j]


@njit(cache=True, nogil=True)
def _finite_differences(sdfs, resolution, gradients):
    """``gradients`` (B, H, W, 2) = ∂f/∂x, ∂f/∂y of grids ``sdfs`` (B, H, W) by the formulas of ``np.gradient``
    (central differences inside, one-sided on the border; the same floating-point operations, so the same
    bits; :func:`contact_kernel.unit_normals_from_values` evaluates the same formulas at single nodes)."""
    b, h, w = sdfs.shape
    two = 2.0 * resolution
    for k in range(b):
        sdf = sdfs[k]
        out = gradients[k]
        for i in range(h):  # the border cases outside the inner loops, so that these vectorise
            out[i, 0, 0] = (sdf[i, 1] - sdf[i, 0]) / resolution
            for j in range(1, w - 1):
                out[i, j, 0] = (sdf[i, j + 1] - sdf[i, j - 1]) / two
            out[i, w - 1, 0] = (sdf[i, w - 1] - sdf[i, w - 2]) / resolution
            if i == 0 or i == h - 1:
                lo, hi, step = (0, 1, resolution) if i == 0 else (h - 2, h - 1, resolution)
            else:
                lo, hi, step = i - 1, i + 1, two
            for j in range(w):
                out[i, j, 1] = (sdf[hi, j] - sdf[lo, j]) / step


@njit(cache=True, nogil=True)
def _prepare(sdfs, ic, jc, dist, padded, lipschitz, positive):
    """Per grid of ``sdfs`` (B, H, W): its padded grid (:func:`_pad_grid`) and, while that is in cache, its
    Lipschitz bound and border test (:func:`contact_kernel.lipschitz_bounds`,
    :func:`contact_kernel.border_positive`: the same operations)."""
    for k in range(sdfs.shape[0]):
        _pad_grid(sdfs[k], ic, jc, dist, padded[k])
        lipschitz[k] = grid_lipschitz(padded[k])
        positive[k] = grid_border_positive(padded[k])


@njit(cache=True, nogil=True)
def _prepare_deviations(mean, deviations, obstacles, ic, jc, dist, padded, lipschitz, positive):
    """:func:`_prepare` of the grids ``min(mean + deviations[k], obstacles)`` (float64 sums, one grid at a time in
    a scratch grid: the bank keeps them only as the padded grids' interior; ``obstacles`` +inf where there are
    none, which leaves the sums' bits unchanged)."""
    h, w = mean.shape
    sdf = np.empty((h, w))
    for k in range(deviations.shape[0]):
        for i in range(h):
            for j in range(w):
                sdf[i, j] = min(mean[i, j] + np.float64(deviations[k, i * w + j]), obstacles[i, j])
        _pad_grid(sdf, ic, jc, dist, padded[k])
        lipschitz[k] = grid_lipschitz(padded[k])
        positive[k] = grid_border_positive(padded[k])


def _bilinear_combine(rec: np.ndarray, fx: np.ndarray, fy: np.ndarray, out: np.ndarray) -> np.ndarray:
    """k0 + k1 fx + (k2 + k3 fx) fy from gathered coefficients ``rec[..., 0:4]``, in place (fx is overwritten)."""
    np.multiply(rec[..., 3], fx, out=out)
    out += rec[..., 2]
    out *= fy
    np.multiply(rec[..., 1], fx, out=fx)
    out += fx
    out += rec[..., 0]
    return out


class _Workspace(threading.local):
    """Per-thread scratch arrays reused between chunks (avoids re-faulting fresh large temporaries)."""

    max_arrays = 96

    def __init__(self) -> None:
        self.arrays: dict[tuple, np.ndarray] = {}

    def get(self, name: str, shape: tuple[int, ...], dtype: type = np.float64) -> np.ndarray:
        key = (name, shape, np.dtype(dtype).char)
        arr = self.arrays.get(key)
        if arr is None:
            if len(self.arrays) >= self.max_arrays:
                self.arrays.clear()
            arr = self.arrays[key] = np.empty(shape, dtype=dtype)
        return arr


WORKSPACE = _Workspace()

#: One record of 4 coefficients as a single numpy element: float32 x 4 = complex128, float64 x 4 = 2 x complex128.
_RECORD = {'f': np.dtype(np.complex128), 'd': np.dtype((np.void, 32))}


def gather_records(rec: np.ndarray, flat: np.ndarray, dtype: np.dtype, name: str) -> np.ndarray:
    """Gather coefficient records at ``flat`` → (..., 4) view of ``dtype`` (per-thread scratch)."""
    out = WORKSPACE.get(name, flat.shape, rec.dtype)
    np.take(rec, flat, out=out)
    return out.view(dtype).reshape(flat.shape + (4,))


class SdfBank:
    """A stack of ``B`` SDF grids (m) on one geometry, prepared for batched bilinear lookups.

    ``obstacles`` (H, W), the signed distance (m) to the other objects in the grid (deterministic), makes every
    grid the world the jaws move in, ``min(f, obstacles)``: a jaw must start outside both and stops at whichever
    it meets first; :func:`~gpis_grasp_ros.core.contacts.find_contacts` flags a contact on an obstacle.

    ``gradients`` (B, H, W, 2) holds ∂f/∂x, ∂f/∂y (dimensionless); by default central finite
    differences of each grid (the right normals for Monte-Carlo samples). Pass the GPIS
    posterior's analytic gradient for the mean shape.

    Values are interpolated from grids padded by ``pad_cells`` extrapolated nodes per side
    (``f(nearest node) + distance``), so jaws a few cells off the grid need no clamping; farther
    points are clamped to the padded grid and the remaining distance is added. Coefficients are
    stored in ``dtype`` (float32 by default: a 1000-sample bank of a 25 x 25 grid takes ~42 MB
    with the gradient coefficients; SDF round-off ~1e-8 m) for the vectorised numpy path, built on its
    first lookup. The compiled kernel reads ``padded`` (float64, 11 MB for that bank, built with the
    Lipschitz bounds and border tests in one compiled pass) and, for given gradients, ``gradient_grids``;
    finite-difference gradients it evaluates at the contacts from the values, so their grids (another
    10 MB) are built only when asked for. ``sdfs`` keeps the float64 grids. Read-only after construction
    (safe to share between threads; what is built on first use is built once).
    """

    def __init__(self, sdfs: np.ndarray, geometry: GridGeometry, gradients: np.ndarray | None = None,
                 pad_cells: int = 6, dtype: type = np.float32, *, obstacles: np.ndarray | None = None,
                 _n_deviations: int | None = None) -> None:
        if geometry.height < 2 or geometry.width < 2:
            raise ValueError('contact finding needs a grid of at least 2 x 2 cells')
        if obstacles is not None:
            obstacles = np.ascontiguousarray(obstacles, dtype=np.float64)
            if obstacles.shape != geometry.shape or not np.all(np.isfinite(obstacles)):
                raise ValueError(f'the obstacle distance must be a finite grid of shape {geometry.shape}, got '
                                 f'{obstacles.shape}')
        #: (H, W) signed distance (m) to the other objects, min-ed into every grid (None: no obstacle)
        self.obstacles = obstacles
        if _n_deviations is None:
            sdfs = np.ascontiguousarray(sdfs, dtype=np.float64)
            if sdfs.ndim == 2:
                sdfs = sdfs[None]
            if sdfs.ndim != 3 or sdfs.shape[1:] != geometry.shape:
                raise ValueError(f'SDF grids must have shape (B, {geometry.height}, {geometry.width}), '
                                 f'got {sdfs.shape}')
            if obstacles is not None:
                world = np.minimum(sdfs, obstacles[None])
                if gradients is not None:  # where an obstacle is nearer, the world's gradient is the obstacle's
                    gradients = np.asarray(gradients, dtype=np.float64)
                    gradients = np.where((obstacles[None] < sdfs)[..., None],
                                         obstacle_gradient(obstacles, geometry.resolution),
                                         gradients if gradients.ndim == 4 else gradients[None])
                sdfs = world
        self.geometry = geometry
        n = sdfs.shape[0] if _n_deviations is None else _n_deviations
        self.n = n
        res = geometry.resolution
        self.pad = int(pad_cells)
        self._pw = geometry.width + 2 * self.pad
        self._ph = geometry.height + 2 * self.pad
        ic, jc, dist = _pad_distances(geometry.height, geometry.width, self.pad, res)
        #: float64 padded grids (B, Hp, Wp) read by the compiled kernel (:mod:`contact_kernel`)
        self.padded = np.empty((n, self._ph, self._pw))
        #: (B,) bounds (m per cell) on the gradient norm of each padded grid's bilinear interpolant
        #: (:func:`contact_kernel.lipschitz_bounds`)
        self.lipschitz = np.empty(n)
        #: (B,) bool: every border node of the padded grid is > 0, so the extrapolated SDF has no zero
        #: off the padded grid and the compiled kernel walks lines that leave it only over the grid
        #: (:func:`contact_kernel.border_positive`)
        self.border_positive = np.empty(n, dtype=np.bool_)
        #: True when ``gradients`` were given; else the gradients are the grids' finite differences, which the
        #: compiled normals evaluate at the contacts (:func:`contact_kernel.unit_normals_from_values`) and
        #: :attr:`gradient_grids` builds on first use
        self.gradients_given = gradients is not None
        self._gradient_grids: np.ndarray | None = None
        if gradients is not None:
            gradients = np.asarray(gradients, dtype=np.float64)
            if gradients.ndim == 3:
                gradients = gradients[None]
            if gradients.shape != (n,) + geometry.shape + (2,):
                raise ValueError(f'gradients must have shape {(n,) + geometry.shape + (2,)}, got {gradients.shape}')
            self._gradient_grids = np.array(gradients, dtype=np.float64)
        if _n_deviations is None:
            _prepare(sdfs, ic, jc, dist, self.padded, self.lipschitz, self.border_positive)
        else:  # filled by from_deviations; the grids are the padded grids' interior (f + 0.0: -0.0 reads +0.0)
            sdfs = self.padded[:, self.pad:self.pad + geometry.height, self.pad:self.pad + geometry.width]
        #: float64 grids (B, H, W), m
        self.sdfs = sdfs
        # Array-of-structures: the 4 coefficients of a cell are adjacent and gathered as one record
        # (a 16-byte element for float32), ~1.5x faster than 4 gathers when lookups miss the cache.
        self._coef_dtype = np.dtype(dtype)
        self._records: tuple[np.ndarray, tuple[np.ndarray, np.ndarray]] | None = None
        self._cells_padded = self._ph * self._pw
        self._float_index_exact = self.n * self._cells_padded < 2 ** 24
        self._cells_per_grid = geometry.height * geometry.width

    @classmethod
    def from_deviations(cls, mean: np.ndarray, deviations: np.ndarray, geometry: GridGeometry,
                        pad_cells: int = 6, obstacles: np.ndarray | None = None) -> SdfBank:
        """The bank of the grids ``mean + deviations[k]``: ``mean`` (H, W) m, ``deviations`` (B, H*W) row-major
        (float32 or float64, e.g. :meth:`GpisPosterior.sample_deviations`), each grid summed in float64 within the
        compiled set-up pass. With float64 deviations the bank equals ``SdfBank(mean + deviations)`` bit for bit
        (its ``sdfs`` are a view of the padded grids' interior, where an exact -0.0 reads +0.0); ``obstacles`` as
        in the constructor."""
        mean = np.ascontiguousarray(mean, dtype=np.float64)
        deviations = np.ascontiguousarray(deviations)
        if mean.shape != geometry.shape or deviations.ndim != 2 or deviations.shape[1] != mean.size:
            raise ValueError(f'mean {mean.shape} and deviations {deviations.shape} do not match the grid '
                             f'{geometry.shape}')
        bank = cls(mean, geometry, pad_cells=pad_cells, obstacles=obstacles, _n_deviations=deviations.shape[0])
        ic, jc, dist = _pad_distances(geometry.height, geometry.width, bank.pad, geometry.resolution)
        world = np.full(geometry.shape, np.inf) if obstacles is None else bank.obstacles
        _prepare_deviations(mean, deviations, world, ic, jc, dist, bank.padded, bank.lipschitz, bank.border_positive)
        return bank

    @property
    def gradient_grids(self) -> np.ndarray:
        """float64 gradient grids (B, H, W, 2): the given gradients, else the finite differences of ``sdfs``
        (``np.gradient``'s values, built on first use: the compiled contact search does not need them)."""
        if self._gradient_grids is None:
            grads = np.empty((self.n,) + self.geometry.shape + (2,))
            _finite_differences(self.sdfs, float(self.geometry.resolution), grads)
            self._gradient_grids = grads
        return self._gradient_grids

    @gradient_grids.setter
    def gradient_grids(self, value: np.ndarray) -> None:  # given gradients after construction (e.g. a reference)
        self._gradient_grids = np.asarray(value, dtype=np.float64)
        self.gradients_given = True

    def _build_records(self) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        if self._records is None:
            record = _RECORD[self._coef_dtype.char]
            coef = _coefficient_records(self.padded, self._coef_dtype).view(record).reshape(-1)
            grad = tuple(_coefficient_records(self.gradient_grids[..., k], self._coef_dtype).view(record).reshape(-1)
                         for k in range(2))
            self._records = (coef, grad)
        return self._records

    @property
    def _coef_rec(self) -> np.ndarray:
        """Bilinear coefficient records of the padded grids (numpy path; built on first use)."""
        return self._build_records()[0]

    @property
    def _grad_rec(self) -> tuple[np.ndarray, np.ndarray]:
        """Bilinear coefficient records of ∂f/∂x and ∂f/∂y (numpy path; built on first use)."""
        return self._build_records()[1]

    def _locate(self, u: np.ndarray, v: np.ndarray, index: np.ndarray | None):
        """Flat cell index and fractional offsets of unpadded cell coordinates (clamped to the grid)."""
        g = self.geometry
        uc = np.clip(u, 0.0, g.width - 1.0)
        vc = np.clip(v, 0.0, g.height - 1.0)
        j0 = uc.astype(np.intp)
        i0 = vc.astype(np.intp)
        fx = uc - j0
        fy = vc - i0
        flat = i0 * g.width
        flat += j0
        if index is not None:
            flat += np.asarray(index, dtype=np.intp) * self._cells_per_grid
        return flat, fx, fy

    def values_cells(self, u: np.ndarray, v: np.ndarray, index: np.ndarray | None = None,
                     on_padded_grid: bool | None = None, scratch: bool = False) -> np.ndarray:
        """SDF (m) at fractional cell coordinates ``u`` (col), ``v`` (row), extrapolated off-grid.

        ``index`` (broadcastable to ``u``) selects the grid of the bank; ``None`` means grid 0.
        ``on_padded_grid`` may assert that every point lies on the padded grid (skips the check);
        ``scratch=True`` returns a per-thread scratch array overwritten by the next such call.
        """
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        p = self.pad
        wp1, hp1 = self._pw - 1.0, self._ph - 1.0
        shape = np.broadcast_shapes(u.shape, v.shape)
        ws = WORKSPACE
        up = np.add(u, p, out=ws.get('up', shape))
        vp = np.add(v, p, out=ws.get('vp', shape))
        if on_padded_grid is None:
            on_padded_grid = up.size == 0 or bool(up.min() >= 0.0 and vp.min() >= 0.0
                                                  and up.max() <= wp1 and vp.max() <= hp1)
        extra = None
        if not on_padded_grid:
            uc = np.clip(up, 0.0, wp1)
            vc = np.clip(vp, 0.0, hp1)
            extra = np.hypot(up - uc, vp - vc) * self.geometry.resolution
            up, vp = uc, vc
        j0 = ws.get('j0', shape, np.intp)
        np.copyto(j0, up, casting='unsafe')  # truncation = floor for non-negative coordinates
        i0 = ws.get('i0', shape, np.intp)
        np.copyto(i0, vp, casting='unsafe')
        fx = np.subtract(up, j0, out=ws.get('fx', shape))
        fy = np.subtract(vp, i0, out=ws.get('fy', shape))
        i0 *= self._pw
        i0 += j0
        if index is not None:
            i0 += np.asarray(index, dtype=np.intp) * self._cells_padded
        rec = gather_records(self._coef_rec, i0, self._coef_dtype, 'rec')
        out = _bilinear_combine(rec, fx, fy, ws.get('val', shape) if scratch else np.empty(shape))
        if extra is not None:
            out += extra
        return out

    def _values_padded32(self, up: np.ndarray, vp: np.ndarray, offset: np.ndarray | None,
                         tag: str = '') -> np.ndarray:
        """Hot path of the march: float32 *padded* cell coordinates, all on the padded grid (>= 0).

        ``offset`` is the grid index times the cells per padded grid (broadcastable). Returns a
        per-thread float32 scratch array (named by ``tag``).
        """
        shape = up.shape
        ws = WORKSPACE
        fu = np.floor(up, out=ws.get('fu' + tag, shape, np.float32))
        fv = np.floor(vp, out=ws.get('fv' + tag, shape, np.float32))
        fx = np.subtract(up, fu, out=ws.get('fx32' + tag, shape, np.float32))
        fy = np.subtract(vp, fv, out=ws.get('fy32' + tag, shape, np.float32))
        fv *= self._pw
        fv += fu
        flat = ws.get('flat' + tag, shape, np.intp)
        if offset is not None and self._float_index_exact:
            fv += np.asarray(offset, dtype=np.float32)  # cell index < 2**24: exact in float32
            np.copyto(flat, fv, casting='unsafe')
        else:
            np.copyto(flat, fv, casting='unsafe')
            if offset is not None:
                flat += offset
        rec = gather_records(self._coef_rec, flat, self._coef_dtype, 'rec32' + tag)
        return _bilinear_combine(rec, fx, fy, ws.get('val32' + tag, shape, self._coef_dtype))

    def values(self, xy: np.ndarray, index: np.ndarray | None = None) -> np.ndarray:
        """SDF (m) at metric points ``(..., 2)``."""
        uv = self.geometry.to_cell(xy)
        return self.values_cells(uv[..., 0], uv[..., 1], index)

    def gradients_at(self, xy: np.ndarray, index: np.ndarray | None = None) -> np.ndarray:
        """Bilinearly interpolated SDF gradient ``(..., 2)`` at metric points (clamped to the grid)."""
        uv = self.geometry.to_cell(xy)
        flat, fx, fy = self._locate(uv[..., 0], uv[..., 1], index)
        out = np.empty(flat.shape + (2,))
        for k in range(2):
            rec = gather_records(self._grad_rec[k], flat, self._coef_dtype, 'grad')
            out[..., k] = rec[..., 0] + fx * rec[..., 1] + fy * (rec[..., 2] + fx * rec[..., 3])
        return out

    def normals_at(self, xy: np.ndarray, index: np.ndarray | None = None) -> np.ndarray:
        """Unit outward normals ``(..., 2)`` (normalised gradient); zero where the gradient vanishes
        (‖∇f‖ <= :data:`MIN_GRADIENT_NORM`)."""
        grad = self.gradients_at(xy, index)
        norm = np.sqrt(grad[..., 0] ** 2 + grad[..., 1] ** 2)[..., None]
        ok = norm > MIN_GRADIENT_NORM
        grad /= np.where(ok, norm, 1.0)
        grad *= ok
        return grad


def obstacle_gradient(obstacles: np.ndarray, resolution: float) -> np.ndarray:
    """(H, W, 2) ∂/∂x, ∂/∂y of an obstacle distance grid (central differences, ``np.gradient``'s)."""
    gy, gx = np.gradient(np.asarray(obstacles, dtype=np.float64), resolution)
    return np.stack([gx, gy], axis=-1)


def bilinear(grid: np.ndarray, geometry: GridGeometry, xy: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of one ``(H, W)`` grid at metric points ``(..., 2)`` (clamped to the grid)."""
    grid = np.asarray(grid, dtype=np.float64)
    uv = geometry.to_cell(xy)
    h, w = geometry.shape
    u = np.clip(uv[..., 0], 0.0, w - 1.0)
    v = np.clip(uv[..., 1], 0.0, h - 1.0)
    j0 = np.minimum(u.astype(np.intp), max(w - 2, 0))
    i0 = np.minimum(v.astype(np.intp), max(h - 2, 0))
    j1 = np.minimum(j0 + 1, w - 1)
    i1 = np.minimum(i0 + 1, h - 1)
    fx = u - j0
    fy = v - i0
    top = grid[i0, j0] * (1 - fx) + grid[i0, j1] * fx
    bottom = grid[i1, j0] * (1 - fx) + grid[i1, j1] * fx
    return top * (1 - fy) + bottom * fy

