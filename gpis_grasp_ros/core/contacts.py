"""Parallel-jaw grasp model and contact finding on signed-distance grids (paper section V-B).

A grasp is a pair of jaw positions ``g = (g1, g2)`` (metres, grid/sensor frame). During execution
the jaws land at the *perturbed grasp* ``ĝ``::

    ĝ1 ~ N(g1, σ_g² I),        ĝ2 | ĝ1 ~ N(ĝ1 + (g2 − g1), σ_g² I)

and close along the line between them. The contact ``c_i`` of jaw ``i`` is the first zero
crossing of the SDF ``f`` met by the jaw while it travels toward the other jaw.

Choices where the paper is silent (documented here, relied on by :mod:`quality` and :mod:`planners`):

* **Jaw width.** The jaw face (width ``w_j``, perpendicular to the closing direction) is
  represented by parallel face lines spread evenly across the face, at most
  ``face_line_spacing_cells`` (0.25) grid cell apart (:meth:`GripperParams.face_offsets`).
  Both jaws travel on the same lines (ĝ2 lies on the line through ĝ1 along the closing
  direction), so each line is searched once from both ends. The first contact anywhere across the
  face wins. 0.25 cell is where P_F stops depending on the spacing: on the shipped bags halving it
  moves P_F of the planned grasps by at most 0.004 (< 1 standard error at S = 1000), while 1-cell
  lines had moved it by up to 0.09 (``test/core/test_contact_refinement.py``).
* **Contact patch.** A rigid flat jaw meeting a flat face touches along a segment, not at the
  corner line that happens to cross first. Lines whose crossing lies within
  ``contact_patch_cells`` (0.5 cell; or ``contact_patch`` in m, which :meth:`GripperParams.resolved`
  fixes from the planning grid so executions on a finer true grid model the same jaw) of the
  first touch form the patch, weighted by a linear
  ramp (1 at the first touch, 0 at the tolerance) times the trapezoid weight of the line (½ for
  the two edge lines, which stand for half a spacing); the contact is the patch centre. A spike
  hit by one edge line is still the contact (nothing else is within the tolerance), a flat face
  gives the centre of the jaw, and the contact moves continuously with the jaws (needed for
  finite differences).
* **Exact crossings** (``exact_crossings``, default). Each face line is cut where it crosses a
  grid line; inside a cell the bilinear SDF restricted to the line is a quadratic, so the first
  zero crossing seen from each jaw is found in closed form — sub-cell exact, with no sampling step
  that a sliver of the object (common in GP shape samples) could slip through. The march step
  ``march_step_cells`` no longer matters for lines on the (padded) grid. Outside the grid the SDF
  is extrapolated as ``f(nearest node) + distance`` (the grid border is free space and a distance
  grows at most by the distance travelled), so jaws may start off the grid; lines that leave the
  padded grid, and ``exact_crossings=False``, use the sampled march: ``n = ceil(L /
  march_step_cells)`` equal steps, the bracket around the first sign change halved once and the
  crossing placed by linear interpolation. The old default (1-cell step and 1-cell face lines)
  biased P_F upward by up to several standard errors (issue 11, item 6).
* **Normals.** Outward normals are the normalised SDF gradient, bilinearly interpolated at the
  contact. For the GPIS mean the gradient is the posterior's analytic ``gradient`` (paper V-A:
  ``n = ∇μ/‖∇μ‖``); for a Monte-Carlo *sample* f the normal must come from f itself (the surface
  being grasped is f's zero set, whose orientation differs from the mean's), so
  :class:`SdfBank` defaults to central finite differences of each stored grid.
* **Degenerate grasps** are flagged, never silently "repaired": ``no_contact`` (no zero crossing
  on any line), ``start_inside`` (a sample of a jaw face already has ``f <= 0``: the jaw would
  land on the object), ``no_normal`` (the SDF gradient vanishes at a contact, so there is no
  normal; its normal is NaN) and ``opening_exceeded`` (commanded opening ``‖g2 − g1‖ > w_g``).
  ``valid`` is the conjunction of their negations. The opening check applies to the *commanded*
  jaws passed in; Monte-Carlo code checks the nominal grasp once and calls with
  ``check_opening=False`` for the perturbed jaws, because positioning noise is an execution
  error, not a command the gripper could refuse.

**Performance.** Contacts (exact crossings, patch) and normals of trials on the padded grid are
found by compiled numba kernels (:mod:`contact_kernel`, float64): each face line is walked cell
by cell from each jaw, first jumping ahead by f / L where the grid's Lipschitz constant L proves
there is no zero, and the walk stops at the first crossing — or as soon as it is farther than
the contact-patch tolerance beyond the nearest touch found on the other lines (such a crossing
has zero patch weight) — instead of solving the quadratic on every cell of every line: about
7x less CPU per call on the planners benchmark than the vectorised implementation, which is
kept as the reference (``compiled=False``). Lines that leave the padded grid (small objects: the
9 cm opening spans far more cells than the grid) are walked by the kernel too, with exact crossings
of the extrapolated SDF off the grid (piecewise linear beside an edge, a circle around a corner
node; skipped where the grid's padded border is positive, :attr:`SdfBank.border_positive`, since
the field cannot vanish there); the reference marches them every ``OFF_GRID_STEP_CELLS`` (on a 25 x 25
grid of 1.2-1.6 mm cells GP-GPIS-OPT took 7-12 s with every such line marched, 0.2 s with the kernel:
``python -m gpis_grasp_ros.bench planners --small``). In the numpy path everything is vectorised
over a flat batch of
"trials" (a perturbed grasp paired with one SDF of a bank, e.g. G grasps × S shape samples),
processed in chunks of about 65k interpolated points so temporaries stay in cache and are reused
between chunks (a per-thread workspace avoids re-faulting fresh large arrays). The bank stores,
per cell of a padded grid, the 4 bilinear coefficients as one float32 record, so each lookup is a
single gather; sample positions are float32 (1e-6 cell round-off).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, replace

import numpy as np

from gpis_grasp_ros.core.contact_kernel import border_positive, exact_contacts, lipschitz_bounds, unit_normals
from gpis_grasp_ros.core.grid import GridGeometry

#: Interpolated points per chunk in :func:`find_contacts`: small enough for the temporaries to stay in
#: cache (about 2x faster than large chunks), large enough to amortise the Python overhead.
MAX_POINTS_PER_CHUNK = 1 << 16

#: Trials per call of the compiled kernel (:mod:`contact_kernel`), which needs no large temporaries.
KERNEL_TRIALS_PER_CHUNK = 1 << 14

#: March step (cells) of the numpy reference (``compiled=False``) for lines that leave the padded grid.
OFF_GRID_STEP_CELLS = 0.1

#: An SDF gradient norm (dimensionless; 1 for an exact SDF) at or below this defines no normal:
#: the contact is flagged ``no_normal`` (invalid) instead of being given an arbitrary direction.
MIN_GRADIENT_NORM = 1e-6


@dataclass(frozen=True)
class GripperParams:
    """Parallel-jaw gripper (paper V-B). Lengths in metres.

    ``friction_coef`` γ = 0.5 is a typical rubber-pad-on-plastic/cardboard value (the paper
    assumes a known constant γ without giving it); β = cos(arctan γ) of eq. 5 follows from it.
    ``position_noise`` σ_g (m) defaults to ``None``: then ``position_noise_cells`` × the grid
    resolution is used, i.e. the paper's σ_g² = 0.25 cells² (σ_g = 0.5 cell), which can only be
    resolved once the planning grid is known (see :meth:`sigma_g` and :meth:`resolved`).
    """

    jaw_width: float = 0.01  # w_j, m
    max_opening: float = 0.09  # w_g, m (about a PR2 gripper)
    friction_coef: float = 0.5  # γ, dimensionless
    position_noise: float | None = None  # σ_g, m; None -> position_noise_cells * resolution
    position_noise_cells: float = 0.5  # σ_g in cells of the planning grid (paper: σ_g² = 0.25)
    march_step_cells: float = 1.0  # sampling step of the sampled march (off-grid lines / exact_crossings=False)
    face_line_spacing_cells: float = 0.25  # max spacing of the face lines across a jaw face, cells
    contact_patch_cells: float = 0.5  # lines touching within this distance of the first touch form the patch
    contact_patch: float | None = None  # the same tolerance in m; None -> contact_patch_cells * resolution
    exact_crossings: bool = True  # exact zero crossings of the bilinear SDF (False: sampled march, step above)

    def __post_init__(self) -> None:
        if not self.jaw_width >= 0:
            raise ValueError(f'jaw width must be >= 0 m, got {self.jaw_width}')
        if not self.max_opening > 0:
            raise ValueError(f'max opening must be > 0 m, got {self.max_opening}')
        if not self.friction_coef > 0:
            raise ValueError(f'friction coefficient must be > 0, got {self.friction_coef}')
        if self.position_noise is not None and not self.position_noise >= 0:
            raise ValueError(f'position noise must be >= 0 m, got {self.position_noise}')
        if self.contact_patch is not None and not self.contact_patch > 0:
            raise ValueError(f'contact patch tolerance must be > 0 m, got {self.contact_patch}')
        if not (self.march_step_cells > 0 and self.face_line_spacing_cells > 0):
            raise ValueError('march step and face line spacing must be positive')

    @property
    def beta(self) -> float:
        """β = cos(arctan γ) of the antipodal constraints (eq. 5)."""
        return float(math.cos(math.atan(self.friction_coef)))

    @staticmethod
    def position_noise_from_cells(sigma_cells: float, geometry: GridGeometry) -> float:
        """σ_g in metres from σ_g in cells of ``geometry`` (paper: σ_g² = 0.25 cells² → 0.5)."""
        return float(sigma_cells) * geometry.resolution

    def sigma_g(self, geometry: GridGeometry) -> float:
        """Jaw positioning noise σ_g (m) for planning on ``geometry``."""
        if self.position_noise is not None:
            return float(self.position_noise)
        return self.position_noise_from_cells(self.position_noise_cells, geometry)

    def patch_cells(self, geometry: GridGeometry) -> float:
        """Contact-patch tolerance in cells of ``geometry`` (the grid the jaws close on)."""
        if self.contact_patch is not None:
            return float(self.contact_patch) / geometry.resolution
        return float(self.contact_patch_cells)

    def resolved(self, geometry: GridGeometry) -> GripperParams:
        """Copy with ``position_noise`` and ``contact_patch`` fixed in metres on the planning grid
        ``geometry`` (use before executing on another grid, e.g. the 1 mm ground truth)."""
        return replace(self, position_noise=self.sigma_g(geometry),
                       contact_patch=self.patch_cells(geometry) * geometry.resolution)

    def face_offsets(self, geometry: GridGeometry) -> np.ndarray:
        """Lateral offsets (m) of the march lines across a jaw face, centred on the jaw."""
        spacing = self.face_line_spacing_cells * geometry.resolution
        n = 1 if self.jaw_width <= 0 else int(math.ceil(self.jaw_width / spacing - 1e-9)) + 1
        if n == 1:
            return np.zeros(1)
        return np.linspace(-0.5 * self.jaw_width, 0.5 * self.jaw_width, n)


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


def _pad_extrapolated(grids: np.ndarray, pad: int, resolution: float) -> np.ndarray:
    """Grids ``(B, H, W)`` padded by ``pad`` nodes per side with ``f(nearest node) + distance``."""
    _, h, w = grids.shape
    ii = np.arange(-pad, h + pad)
    jj = np.arange(-pad, w + pad)
    ic = np.clip(ii, 0, h - 1)
    jc = np.clip(jj, 0, w - 1)
    dist = np.hypot((ii - ic)[:, None], (jj - jc)[None, :]) * resolution
    return grids[:, ic[:, None], jc[None, :]] + dist[None]


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


_WS = _Workspace()

#: One record of 4 coefficients as a single numpy element: float32 x 4 = complex128, float64 x 4 = 2 x complex128.
_RECORD = {'f': np.dtype(np.complex128), 'd': np.dtype((np.void, 32))}


def _gather4(rec: np.ndarray, flat: np.ndarray, dtype: np.dtype, name: str) -> np.ndarray:
    """Gather coefficient records at ``flat`` → (..., 4) view of ``dtype`` (per-thread scratch)."""
    out = _WS.get(name, flat.shape, rec.dtype)
    np.take(rec, flat, out=out)
    return out.view(dtype).reshape(flat.shape + (4,))


class SdfBank:
    """A stack of ``B`` SDF grids (m) on one geometry, prepared for batched bilinear lookups.

    ``gradients`` (B, H, W, 2) holds ∂f/∂x, ∂f/∂y (dimensionless); by default central finite
    differences of each grid (the right normals for Monte-Carlo samples). Pass the GPIS
    posterior's analytic gradient for the mean shape.

    Values are interpolated from grids padded by ``pad_cells`` extrapolated nodes per side
    (``f(nearest node) + distance``), so jaws a few cells off the grid need no clamping; farther
    points are clamped to the padded grid and the remaining distance is added. Coefficients are
    stored in ``dtype`` (float32 by default: a 1000-sample bank of a 25 x 25 grid takes ~42 MB
    with the gradient coefficients; SDF round-off ~1e-8 m) for the vectorised numpy path;
    ``padded`` and ``gradient_grids`` keep float64 copies for the compiled kernel (another ~21 MB
    for that bank). ``sdfs`` keeps the float64 grids. Read-only after construction (safe to share
    between threads; the Lipschitz bounds are computed once on first use).
    """

    def __init__(self, sdfs: np.ndarray, geometry: GridGeometry, gradients: np.ndarray | None = None,
                 pad_cells: int = 6, dtype: type = np.float32) -> None:
        sdfs = np.asarray(sdfs, dtype=np.float64)
        if sdfs.ndim == 2:
            sdfs = sdfs[None]
        if sdfs.ndim != 3 or sdfs.shape[1:] != geometry.shape:
            raise ValueError(f'SDF grids must have shape (B, {geometry.height}, {geometry.width}), got {sdfs.shape}')
        if geometry.height < 2 or geometry.width < 2:
            raise ValueError('contact finding needs a grid of at least 2 x 2 cells')
        self.geometry = geometry
        self.sdfs = sdfs
        self.n = sdfs.shape[0]
        res = geometry.resolution
        if gradients is None:
            gy, gx = np.gradient(sdfs, res, axis=(1, 2))
        else:
            gradients = np.asarray(gradients, dtype=np.float64)
            if gradients.ndim == 3:
                gradients = gradients[None]
            if gradients.shape != sdfs.shape + (2,):
                raise ValueError(f'gradients must have shape {sdfs.shape + (2,)}, got {gradients.shape}')
            gx, gy = gradients[..., 0], gradients[..., 1]
        self.pad = int(pad_cells)
        self._pw = geometry.width + 2 * self.pad
        self._ph = geometry.height + 2 * self.pad
        # Array-of-structures: the 4 coefficients of a cell are adjacent and gathered as one record
        # (a 16-byte element for float32), ~1.5x faster than 4 gathers when lookups miss the cache.
        self._coef_dtype = np.dtype(dtype)
        record = _RECORD[self._coef_dtype.char]
        #: float64 padded grids (B, Hp, Wp) read by the compiled kernel (:mod:`contact_kernel`)
        self.padded = np.ascontiguousarray(_pad_extrapolated(sdfs, self.pad, res))
        self._lipschitz: np.ndarray | None = None
        self._border_positive: np.ndarray | None = None
        self._coef_rec = _coefficient_records(self.padded, dtype).view(record).reshape(-1)
        self._cells_padded = self._ph * self._pw
        self._float_index_exact = self.n * self._cells_padded < 2 ** 24
        self._grad_rec = tuple(_coefficient_records(gc, dtype).view(record).reshape(-1) for gc in (gx, gy))
        #: float64 gradient grids (B, H, W, 2) read by the compiled normals (:func:`contact_kernel.unit_normals`)
        self.gradient_grids = np.ascontiguousarray(np.stack([gx, gy], axis=-1), dtype=np.float64)
        self._cells_per_grid = geometry.height * geometry.width

    @property
    def border_positive(self) -> np.ndarray:
        """(B,) bool: every border node of the padded grid is > 0, so the extrapolated SDF has no zero
        off the padded grid and the compiled kernel walks lines that leave it only over the grid
        (:func:`contact_kernel.border_positive`; computed on first use)."""
        if self._border_positive is None:
            self._border_positive = border_positive(self.padded)
        return self._border_positive

    @property
    def lipschitz(self) -> np.ndarray:
        """(B,) bounds (m per cell) on the gradient norm of each padded grid's bilinear interpolant
        (computed on first use; :func:`contact_kernel.lipschitz_bounds`)."""
        if self._lipschitz is None:
            self._lipschitz = lipschitz_bounds(self.padded)
        return self._lipschitz

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
        ws = _WS
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
        rec = _gather4(self._coef_rec, i0, self._coef_dtype, 'rec')
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
        ws = _WS
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
        rec = _gather4(self._coef_rec, flat, self._coef_dtype, 'rec32' + tag)
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
            rec = _gather4(self._grad_rec[k], flat, self._coef_dtype, 'grad')
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


@dataclass
class Contacts:
    """Contacts of a batch of (possibly perturbed) grasps; all arrays share a leading shape ``(...)``.

    ``c1, c2`` contact points (m) and ``n1, n2`` unit outward normals, NaN where no contact;
    ``width`` jaw separation ‖ĝ2 − ĝ1‖ (m); ``clearance1, clearance2`` the smallest SDF value (m)
    over each jaw face before closing (negative: the jaw starts inside the object);
    ``no_normal`` a contact exists but the SDF gradient vanishes there (no defined normal, NaN n).
    """

    c1: np.ndarray
    c2: np.ndarray
    n1: np.ndarray
    n2: np.ndarray
    valid: np.ndarray
    no_contact: np.ndarray
    start_inside: np.ndarray
    opening_exceeded: np.ndarray
    width: np.ndarray
    clearance1: np.ndarray
    clearance2: np.ndarray
    no_normal: np.ndarray | None = None


def perturb_grasps(jaw1: np.ndarray, jaw2: np.ndarray, eps: np.ndarray,
                   sigma_g: float) -> tuple[np.ndarray, np.ndarray]:
    """Perturbed jaws (paper V-B) from standard-normal draws ``eps (..., 2, 2)``.

    ``ĝ1 = g1 + σ_g ε1``, ``ĝ2 = ĝ1 + (g2 − g1) + σ_g ε2``; ``jaw1, jaw2`` broadcast against
    ``eps[..., 0, :]``. Fixed ``eps`` give common random numbers across grasps.
    """
    jaw1 = np.asarray(jaw1, dtype=np.float64)
    jaw2 = np.asarray(jaw2, dtype=np.float64)
    g1 = jaw1 + sigma_g * eps[..., 0, :]
    g2 = g1 + (jaw2 - jaw1) + sigma_g * eps[..., 1, :]
    return g1, g2


def find_contacts(bank: SdfBank, jaw1: np.ndarray, jaw2: np.ndarray, gripper: GripperParams,
                  index: np.ndarray | None = None, check_opening: bool = True, compiled: bool = True) -> Contacts:
    """Contacts of jaws closing from ``jaw1`` and ``jaw2`` (m, shape ``(..., 2)``) on SDFs of ``bank``.

    ``index`` (int array broadcastable to the leading shape, or None for grid 0) selects which
    grid of the bank each trial closes on. See the module docstring for the algorithm.
    ``compiled=False`` finds the exact crossings with the vectorised numpy implementation (float32,
    every cell of every line) instead of the compiled kernel: the independent reference the tests
    compare the kernel against; both implement the same model.
    """
    jaw1 = np.asarray(jaw1, dtype=np.float64)
    jaw2 = np.asarray(jaw2, dtype=np.float64)
    lead = np.broadcast_shapes(jaw1.shape[:-1], jaw2.shape[:-1], () if index is None else np.shape(index))
    j1 = np.broadcast_to(jaw1, lead + (2,)).reshape(-1, 2)
    j2 = np.broadcast_to(jaw2, lead + (2,)).reshape(-1, 2)
    idx = None if index is None else np.broadcast_to(np.asarray(index, dtype=np.intp), lead).reshape(-1)
    t_total = j1.shape[0]
    g = bank.geometry
    offsets = gripper.face_offsets(g) / g.resolution  # cells
    n_lines = offsets.size

    # Jaws in cell coordinates; direction and length of the closing line.
    a = g.to_cell(j1)
    d = g.to_cell(j2) - a
    length = np.hypot(d[:, 0], d[:, 1])
    degenerate = length <= 1e-12
    unit = d / np.where(degenerate, 1.0, length)[:, None]
    unit[degenerate] = (1.0, 0.0)
    # Each line is cut into n_i = ceil(L_i / step) equal steps, so a trial's samples do not depend
    # on the other trials of the batch; shorter lines repeat their end point up to the longest.
    n_seg = np.maximum(np.ceil(length / gripper.march_step_cells - 1e-9), 1.0)
    n_steps = int(n_seg.max(initial=1.0)) + 1
    # exact crossings: one segment per grid line crossed (at most (|u_x| + |u_y|) L + 3 per line)
    n_work = int(math.ceil(math.sqrt(2.0) * float(length.max(initial=0.0)))) + 3 if gripper.exact_crossings \
        else n_steps
    chunk = max(1, MAX_POINTS_PER_CHUNK // (n_lines * n_work))
    use_kernel = compiled and gripper.exact_crossings
    if use_kernel:  # the kernel needs no temporaries: large chunks
        chunk = max(chunk, KERNEL_TRIALS_PER_CHUNK)

    if t_total == 0:
        e2, e1 = np.zeros((0, 2)), np.zeros(0)
        none = np.zeros(0, dtype=bool)
        return Contacts(c1=e2.reshape(lead + (2,)), c2=e2.reshape(lead + (2,)), n1=e2.reshape(lead + (2,)),
                        n2=e2.reshape(lead + (2,)), valid=none.reshape(lead), no_contact=none.reshape(lead),
                        start_inside=none.reshape(lead), opening_exceeded=none.reshape(lead), width=e1.reshape(lead),
                        clearance1=e1.reshape(lead), clearance2=e1.reshape(lead), no_normal=none.reshape(lead))
    parts = [_march_chunk(bank, a[s:s + chunk], unit[s:s + chunk], length[s:s + chunk], n_seg[s:s + chunk],
                          offsets, n_steps, None if idx is None else idx[s:s + chunk], gripper.patch_cells(g),
                          gripper.exact_crossings, use_kernel)
             for s in range(0, t_total, chunk)]
    if len(parts) == 1:
        c, no_contact, inside, clear = parts[0]
    else:
        c = np.concatenate([p[0] for p in parts], axis=1)
        no_contact = np.concatenate([p[1] for p in parts])
        inside = np.concatenate([p[2] for p in parts])
        clear = np.concatenate([p[3] for p in parts], axis=1)

    # Outward normals of the SDF each trial closed on, at both contacts at once.
    cm = g.to_metric(c)  # (2, T, 2)
    if use_kernel:
        normals = np.empty((2, t_total, 2))
        unit_normals(bank.gradient_grids, np.zeros(t_total, dtype=np.intp) if idx is None else np.array(idx),
                     np.ascontiguousarray(c), MIN_GRADIENT_NORM, normals)
    else:
        normals = bank.normals_at(cm, None if idx is None else idx[None, :])
    # A vanishing gradient (flat SDF) defines no normal: the contact is invalid (never a made-up
    # direction, which would look perfectly antipodal).
    flat = ~np.any(normals != 0, axis=2)
    no_normal = flat.any(axis=0) & ~no_contact
    normals[flat] = np.nan
    cm[:, no_contact] = np.nan
    normals[:, no_contact] = np.nan

    width = length * g.resolution
    if check_opening:
        opening = width > gripper.max_opening * (1.0 + 1e-9) + 1e-12
    else:
        opening = np.zeros(t_total, dtype=bool)
    valid = ~(no_contact | inside | opening | no_normal)
    shape2 = lead + (2,)
    return Contacts(
        c1=cm[0].reshape(shape2), c2=cm[1].reshape(shape2), n1=normals[0].reshape(shape2),
        n2=normals[1].reshape(shape2), valid=valid.reshape(lead), no_contact=no_contact.reshape(lead),
        start_inside=inside.reshape(lead), opening_exceeded=opening.reshape(lead), width=width.reshape(lead),
        clearance1=clear[0].reshape(lead), clearance2=clear[1].reshape(lead), no_normal=no_normal.reshape(lead),
    )


_SIDE_SIGN = np.array([1.0, -1.0])[:, None, None]


def _over_lines(op: np.ufunc, x: np.ndarray) -> np.ndarray:
    """Reduce the (short) last axis of ``x`` with the binary ufunc ``op`` by element-wise steps.

    numpy's axis reductions pay a large per-row overhead on a 2-5 long axis; chaining the
    element-wise op over the few columns is several times faster here.
    """
    out = x[..., 0].copy()
    for k in range(1, x.shape[-1]):
        op(out, x[..., k], out=out)
    return out


def _exact_crossings(bank: SdfBank, ox: np.ndarray, oy: np.ndarray, unit: np.ndarray, length: np.ndarray,
                     idx: np.ndarray | None):
    """Exact first and last zero crossings of the bilinear SDF along T x L lines (cell units).

    Lines start at (ox, oy) (T, L) (unpadded cell coordinates, all on the padded grid), run along
    ``unit`` (T, 2) for ``length`` (T, L) cells. Each line is cut where it crosses a grid line;
    inside a cell the bilinear interpolant restricted to the line is a quadratic
    ``c0 + c1 τ + c2 τ²``, whose smallest (largest) root in the first (last) segment that reaches
    f <= 0 is the crossing seen from jaw 1 (jaw 2). No sampling step: a sliver of the object
    thinner than any step is still found. Returns ``t_first, t_last, has, f_start, f_end`` (T, L):
    crossing positions along the line (cells), whether the line meets f <= 0, and f (m) at both ends.
    """
    n_t, n_l = ox.shape
    pad = bank.pad
    ux64, uy64 = unit[:, 0, None, None], unit[:, 1, None, None]
    px0 = (ox + pad)[..., None]
    py0 = (oy + pad)[..., None]
    len3 = np.broadcast_to(length, (n_t, n_l))[..., None]
    # Breakpoints: both ends and every grid line crossed (a superset is harmless).
    breaks = [np.zeros((n_t, n_l, 1)), len3]
    for p0, u in ((px0, ux64), (py0, uy64)):
        k = int(math.ceil(float((len3 * np.abs(u)).max(initial=0.0)))) + 1
        au = np.abs(u)
        first = np.where(u >= 0, np.floor(p0) + 1.0 - p0, p0 - np.ceil(p0) + 1.0)
        with np.errstate(divide='ignore', invalid='ignore'):
            tk = (first + np.arange(k)) / np.where(au > 1e-12, au, np.nan)
        breaks.append(np.fmin(tk, len3))  # NaN (line parallel to the axis) -> the end point
    t = np.sort(np.concatenate(breaks, axis=2), axis=2).astype(np.float32)  # (T, L, S + 1)
    t0 = t[..., :-1]
    dseg = t[..., 1:] - t0
    ux = unit[:, 0].astype(np.float32)[:, None, None]
    uy = unit[:, 1].astype(np.float32)[:, None, None]
    px = px0.astype(np.float32)
    py = py0.astype(np.float32)
    # cell of each segment (its midpoint), clamped to the padded grid's cells
    tm = t0 + 0.5 * dseg
    cu = np.floor(px + tm * ux)
    cv = np.floor(py + tm * uy)
    np.clip(cu, 0, bank._pw - 1, out=cu)
    np.clip(cv, 0, bank._ph - 1, out=cv)
    flat = (cv * bank._pw + cu).astype(np.intp)
    if idx is not None:
        flat += (np.asarray(idx, dtype=np.intp) * bank._cells_padded)[:, None, None]
    rec = _gather4(bank._coef_rec, flat, bank._coef_dtype, 'exact')
    k0, k1, k2, k3 = rec[..., 0], rec[..., 1], rec[..., 2], rec[..., 3]
    fa = px + t0 * ux - cu  # fractional position in the cell at the segment start
    fb = py + t0 * uy - cv
    # f(τ) = c0 + c1 τ + c2 τ² on the segment, τ ∈ [0, dseg]
    c0 = k0 + k1 * fa + fb * (k2 + k3 * fa)
    c1 = k1 * ux + k2 * uy + k3 * (fa * uy + fb * ux)
    c2 = k3 * (ux * uy)
    # a segment reaches f <= 0 at its start, or dips below 0 at an interior vertex (the end is the
    # next segment's start: continuity of the bilinear interpolant)
    hit = c0 <= 0
    hit |= (c2 > 0) & (c1 < 0) & (-c1 < 2.0 * c2 * dseg) & (4.0 * c0 * c2 < c1 * c1)
    n_s = hit.shape[2]
    last_seg = n_s - 1
    f_stop = (c0[..., last_seg] + dseg[..., last_seg] * (c1[..., last_seg] + c2[..., last_seg] * dseg[..., last_seg])
              ).astype(np.float64)
    hit[..., last_seg] |= f_stop <= 0
    has = hit.any(axis=2)
    base = (np.arange(n_t * n_l) * n_s).reshape(n_t, n_l)
    j_first = base + np.argmax(hit, axis=2)  # flat indices into the (T, L, S) arrays
    # entered f <= 0 at the start of segment j: the crossing lies in segment j - 1 (whose end is inside)
    j_first -= (c0.reshape(-1).take(j_first) <= 0) & (j_first > base)
    j_last = base + (last_seg - np.argmax(hit[..., ::-1], axis=2))
    flat_arrays = [np.ascontiguousarray(arr).reshape(-1) for arr in (c0, c1, c2, dseg, t0)]

    def root(j: np.ndarray, largest: bool) -> np.ndarray:
        q0, q1, q2, dd, ts = (arr.take(j).astype(np.float64) for arr in flat_arrays)
        sq = np.sqrt(np.maximum(q1 * q1 - 4.0 * q2 * q0, 0.0))
        qq = -0.5 * (q1 + np.where(q1 >= 0, sq, -sq))
        with np.errstate(divide='ignore', invalid='ignore'):
            r1 = np.where(np.abs(q2) > 1e-15, qq / q2, np.nan)
            r2 = np.where(qq != 0, q0 / qq, np.nan)
        tol = 1e-6 + 1e-6 * dd
        cands = np.stack([r1, r2])
        ok = np.isfinite(cands) & (cands >= -tol) & (cands <= dd + tol)
        if largest:
            r = np.where(ok, cands, -np.inf).max(axis=0)
            fallback = np.where(q0 + q1 * dd + q2 * dd * dd <= 0, dd, 0.0)  # end inside / no clean root
        else:
            r = np.where(ok, cands, np.inf).min(axis=0)
            fallback = np.where(q0 <= 0, 0.0, dd)
        r = np.where(np.isfinite(r), np.clip(r, 0.0, dd), fallback)
        return ts + r

    return root(j_first, largest=False), root(j_last, largest=True), has, c0[..., 0].astype(np.float64), f_stop


def _sampled_crossings(bank: SdfBank, ox: np.ndarray, oy: np.ndarray, unit: np.ndarray, length: np.ndarray,
                       n_seg: np.ndarray, n_steps: int, idx: np.ndarray | None, on_padded: bool):
    """Crossings by marching N samples per line (step ``length / n_seg``), one bisection and a secant.

    Used for lines that leave the padded grid (where the extrapolated SDF is not bilinear) and
    when ``GripperParams.exact_crossings`` is off. Returns ``t`` (2, T, L), ``has`` (T, L), the
    no-contact and start-inside flags (T,) and the clearances (2, T).
    """
    n_t, n_lines = ox.shape
    pad = bank.pad
    dt = (length / n_seg)[:, None]
    # Sample positions in float32 padded cell coordinates (1e-6 cell round-off; halves memory traffic).
    shape = (n_t, n_lines, n_steps)
    tt = (np.minimum(np.arange(n_steps, dtype=np.float64), n_seg[:, None]) * dt).astype(np.float32)[:, None, :]
    u32 = unit.astype(np.float32)
    px = np.multiply(tt, u32[:, 0, None, None], out=_WS.get('march_x', shape, np.float32))
    px += (ox + pad).astype(np.float32)[:, :, None]
    py = np.multiply(tt, u32[:, 1, None, None], out=_WS.get('march_y', shape, np.float32))
    py += (oy + pad).astype(np.float32)[:, :, None]
    if on_padded:
        f = bank._values_padded32(px, py, None if idx is None else (idx * bank._cells_padded)[:, None, None])
    else:
        f = bank.values_cells(px - pad, py - pad, None if idx is None else idx[:, None, None], on_padded_grid=False)
    neg = np.less_equal(f, 0.0, out=_WS.get('neg', shape, np.bool_))
    # Bracket of the first sign change seen from each jaw: (side, T, L) sample indices.
    first = np.argmax(neg, axis=2)
    last = (n_steps - 1) - np.argmax(neg[:, :, ::-1], axis=2)
    base = (np.arange(n_t * n_lines) * n_steps).reshape(n_t, n_lines)
    nflat = neg.reshape(-1)
    has = nflat.take(base + first)  # (T, L): the line meets the object (argmax found a True)
    no_contact = ~_over_lines(np.logical_or, has)
    inside = _over_lines(np.logical_or, nflat.take(base)) | _over_lines(np.logical_or, nflat.take(base + n_steps - 1))
    fflat = f.reshape(-1)
    clear = np.stack([_over_lines(np.minimum, fflat.take(base)),
                      _over_lines(np.minimum, fflat.take(base + n_steps - 1))])

    # (an inside sample is never a repeated end point unless the jaw starts inside: then flagged)
    j_in = np.stack([np.maximum(first, 1), np.minimum(last, n_seg[:, None].astype(np.intp) - 1)])
    j_out = j_in + np.array([-1, 1])[:, None, None]
    f_in = fflat.take(base + j_in).astype(np.float64)
    f_out = fflat.take(base + j_out).astype(np.float64)
    t_in = j_in * dt
    t_out = j_out * dt
    # Halve the bracket once, then place the crossing by linear interpolation.
    t_mid = 0.5 * (t_in + t_out)
    mx = ox + t_mid * unit[:, 0, None]
    my = oy + t_mid * unit[:, 1, None]
    if on_padded:
        f_mid = bank._values_padded32((mx + pad).astype(np.float32), (my + pad).astype(np.float32),
                                      None if idx is None else (idx * bank._cells_padded)[:, None], tag='mid')
        f_mid = f_mid.astype(np.float64)
    else:
        f_mid = bank.values_cells(mx, my, None if idx is None else idx[:, None])
    mid_in = f_mid <= 0.0
    ta = np.where(mid_in, t_out, t_mid)
    fa = np.where(mid_in, f_out, f_mid)
    tb = np.where(mid_in, t_mid, t_in)
    fb = np.where(mid_in, f_mid, f_in)
    denom = fa - fb
    w = np.where(denom > 0, fa / np.where(denom > 0, denom, 1.0), 0.5)
    t = ta + np.clip(w, 0.0, 1.0) * (tb - ta)  # (side, T, L)

    return t, has, no_contact, inside, clear


def _exact_on_padded(bank: SdfBank, ox: np.ndarray, oy: np.ndarray, unit: np.ndarray, length: np.ndarray,
                     idx: np.ndarray | None):
    """:func:`_exact_crossings` packaged like :func:`_sampled_crossings`' result."""
    t_first, t_last, has, f_start, f_stop = _exact_crossings(bank, ox, oy, unit, length[:, None], idx)
    no_contact = ~_over_lines(np.logical_or, has)
    inside = _over_lines(np.logical_or, f_start <= 0) | _over_lines(np.logical_or, f_stop <= 0)
    clear = np.stack([_over_lines(np.minimum, f_start), _over_lines(np.minimum, f_stop)])
    return np.stack([t_first, t_last]), has, no_contact, inside, clear


def _kernel_contacts(bank: SdfBank, a: np.ndarray, unit: np.ndarray, length: np.ndarray, offsets: np.ndarray,
                      idx: np.ndarray | None, patch_tol: float):
    """Contacts (2, T, 2) (cells), no-contact and start-inside flags (T,), clearances (2, T) (m) of
    trials by the compiled kernel (lines on or off the padded grid)."""
    n_t = a.shape[0]
    # a fresh writeable array: a read-only view would compile a second specialisation of the kernel
    index = np.zeros(n_t, dtype=np.intp) if idx is None else np.array(idx, dtype=np.intp)
    c = np.empty((2, n_t, 2))
    no_contact = np.empty(n_t, dtype=bool)
    inside = np.empty(n_t, dtype=bool)
    clear = np.empty((2, n_t))
    exact_contacts(bank.padded, bank.lipschitz, bank.border_positive, index, np.ascontiguousarray(a[:, 0]),
                   np.ascontiguousarray(a[:, 1]),
                   np.ascontiguousarray(unit[:, 0]), np.ascontiguousarray(unit[:, 1]),
                   np.ascontiguousarray(length, dtype=np.float64), np.ascontiguousarray(offsets, dtype=np.float64),
                   float(bank.pad), float(patch_tol), c, no_contact, inside, clear, float(bank.geometry.resolution))
    return c, no_contact, inside, clear


def on_padded_grid(bank: SdfBank, a: np.ndarray, unit: np.ndarray, length: np.ndarray,
                   offsets: np.ndarray) -> np.ndarray:
    """(T,) bool: every face line of each trial (jaw 1 at ``a``, closing along ``unit`` for ``length``
    cells, lines at ``offsets`` cells across the jaw) lies on the padded grid - a conservative test on the
    box spanned by both jaw faces."""
    reach = float(np.abs(offsets).max())
    b = a + length[:, None] * unit
    lo = np.minimum(a, b) - reach
    hi = np.maximum(a, b) + reach
    pad = bank.pad
    return ((lo >= -pad).all(axis=1) & (hi[:, 0] <= bank.geometry.width - 1 + pad)
            & (hi[:, 1] <= bank.geometry.height - 1 + pad))


def _march_chunk(bank: SdfBank, a: np.ndarray, unit: np.ndarray, length: np.ndarray, n_seg: np.ndarray,
                 offsets: np.ndarray, n_steps: int, idx: np.ndarray | None, patch_tol: float, exact: bool = True,
                 compiled: bool = False):
    """March one chunk of T trials along L face lines with N samples each (all in cell units).

    Returns contact points (2, T, 2) in cells for jaw 1 and jaw 2, the no-contact and
    start-inside flags (T,) and the clearances (2, T) (m) of both jaw faces. With ``compiled``
    (exact crossings only) every trial goes through the compiled kernel; otherwise lines on the padded
    grid get the vectorised exact crossings and lines leaving it this function's sampled march.
    """
    if exact and compiled:
        return _kernel_contacts(bank, a, unit, length, offsets, idx, patch_tol)
    n_lines = offsets.size
    on_t = on_padded_grid(bank, a, unit, length, offsets)
    on_padded = bool(on_t.all())
    perp = np.stack([-unit[:, 1], unit[:, 0]], axis=1)
    # Line origins (T, L) and samples (T, L, N) in cells.
    ox = a[:, 0, None] + offsets * perp[:, 0, None]
    oy = a[:, 1, None] + offsets * perp[:, 1, None]
    if not exact:
        return_vals = _sampled_crossings(bank, ox, oy, unit, length, n_seg, n_steps, idx, on_padded)
    elif on_padded:
        return_vals = _exact_on_padded(bank, ox, oy, unit, length, idx)
    else:
        # Per trial, never per batch (a trial's contacts must not depend on the rest of the batch):
        # exact crossings on the padded grid; lines leaving it are marched every OFF_GRID_STEP_CELLS.
        n_t, n_l = ox.shape
        t = np.zeros((2, n_t, n_l))
        has = np.zeros((n_t, n_l), dtype=bool)
        no_contact = np.zeros(n_t, dtype=bool)
        inside = np.zeros(n_t, dtype=bool)
        clear = np.zeros((2, n_t))
        for rows, use_exact in ((np.flatnonzero(on_t), True), (np.flatnonzero(~on_t), False)):
            if rows.size == 0:
                continue
            sub_idx = None if idx is None else idx[rows]
            if use_exact:
                out = _exact_on_padded(bank, ox[rows], oy[rows], unit[rows], length[rows], sub_idx)
            else:
                seg = np.maximum(np.ceil(length[rows] / OFF_GRID_STEP_CELLS - 1e-9), 1.0)
                out = _sampled_crossings(bank, ox[rows], oy[rows], unit[rows], length[rows], seg,
                                         int(seg.max()) + 1, sub_idx, False)
            t[:, rows], has[rows], no_contact[rows], inside[rows], clear[:, rows] = out
        return_vals = (t, has, no_contact, inside, clear)
    t, has, no_contact, inside, clear = return_vals

    # Contact patch: lines touching within `patch_tol` of the first touch, weighted by a linear
    # ramp (1 at the first touch, 0 `patch_tol` later) so its centre moves continuously with the jaws.
    tau = np.where(has, _SIDE_SIGN * t, np.inf)  # distance travelled toward the other jaw (+const)
    tau_min = _over_lines(np.minimum, tau)[..., None]
    tau_min = np.where(np.isfinite(tau_min), tau_min, 0.0)
    weight = np.clip(1.0 - (tau - tau_min) / patch_tol, 0.0, 1.0)
    if n_lines > 1:  # trapezoid rule across the face: the edge lines stand for half a spacing
        weight[..., 0] *= 0.5
        weight[..., -1] *= 0.5
    total = _over_lines(np.add, weight)
    total = np.where(total > 0, total, 1.0)
    o = _over_lines(np.add, weight * offsets) / total  # (side, T)
    tm = _over_lines(np.add, weight * np.where(has, t, 0.0)) / total
    c = a + o[..., None] * perp + tm[..., None] * unit
    return c, no_contact, inside, clear
