"""Contact finding of parallel jaws closing on signed-distance grids (paper section V-B).

A grasp is a pair of jaw positions ``g = (g1, g2)`` (metres, grid/sensor frame); during execution the jaws land
at the perturbed grasp ``ĝ1 ~ N(g1, σ_g² I)``, ``ĝ2 | ĝ1 ~ N(ĝ1 + (g2 − g1), σ_g² I)`` (:func:`perturb_grasps`)
and close along the line between them; the contact of each jaw is the first zero crossing of the SDF it meets
(:func:`find_contacts`). The jaw face is a set of parallel face lines, the contact the centre of a continuous
contact patch, crossings exact on the bilinear SDF (compiled kernel of :mod:`contact_kernel`; the vectorised
numpy march here is the reference). The model choices are in ``docs/planning.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gpis_grasp_ros.core.contact_kernel import exact_contacts, unit_normals, unit_normals_from_values
from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.core.sdf_bank import MIN_GRADIENT_NORM, WORKSPACE, SdfBank, bilinear, gather_records

#: Interpolated points per chunk in :func:`find_contacts`: small enough for the temporaries to stay in
#: cache (about 2x faster than large chunks), large enough to amortise the Python overhead.
MAX_POINTS_PER_CHUNK = 1 << 16

#: Trials per call of the compiled kernel (:mod:`contact_kernel`), which needs no large temporaries.
KERNEL_TRIALS_PER_CHUNK = 1 << 14

#: March step (cells) of the numpy reference (``compiled=False``) for lines that leave the padded grid.
OFF_GRID_STEP_CELLS = 0.1


@dataclass
class Contacts:
    """Contacts of a batch of (possibly perturbed) grasps; all arrays share a leading shape ``(...)``.

    ``c1, c2`` contact points (m) and ``n1, n2`` unit outward normals, NaN where no contact;
    ``width`` jaw separation ‖ĝ2 − ĝ1‖ (m); ``clearance1, clearance2`` the smallest SDF value (m)
    over each jaw face before closing (negative: the jaw starts inside the object);
    ``no_normal`` a contact exists but the SDF gradient vanishes there (no defined normal, NaN n);
    ``on_obstacle`` a jaw meets another object (the bank's obstacles, within :data:`OBSTACLE_CONTACT_CELLS`)
    instead of the target: the grasp would push or hold the neighbour, so it is invalid.
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
    on_obstacle: np.ndarray | None = None


#: A contact within this many cells of an obstacle's surface is on the obstacle: the bilinear world grid
#: ``min(f, obstacles)`` blends the two within a cell, and a jaw this close to a neighbour touches it at the
#: grid's resolution.
OBSTACLE_CONTACT_CELLS = 0.5


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
    grid of the bank each trial closes on. The contact model is described in docs/planning.md.
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
                        clearance1=e1.reshape(lead), clearance2=e1.reshape(lead), no_normal=none.reshape(lead),
                        on_obstacle=none.reshape(lead))
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
        grid_index = np.zeros(t_total, dtype=np.intp) if idx is None else np.array(idx)
        if bank.gradients_given:
            unit_normals(bank.gradient_grids, grid_index, np.ascontiguousarray(c), MIN_GRADIENT_NORM, normals)
        else:  # finite differences of the grids, at the contacts only (the same values as the gradient grids)
            unit_normals_from_values(bank.padded, bank.pad, float(g.resolution), grid_index, np.ascontiguousarray(c),
                                     MIN_GRADIENT_NORM, normals)
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
    on_obstacle = np.zeros(t_total, dtype=bool)
    if bank.obstacles is not None:
        reach = OBSTACLE_CONTACT_CELLS * g.resolution
        near = [bilinear(bank.obstacles, g, np.nan_to_num(cm[k])) <= reach for k in range(2)]
        on_obstacle = (near[0] | near[1]) & ~no_contact
    valid = ~(no_contact | inside | opening | no_normal | on_obstacle)
    shape2 = lead + (2,)
    return Contacts(
        c1=cm[0].reshape(shape2), c2=cm[1].reshape(shape2), n1=normals[0].reshape(shape2),
        n2=normals[1].reshape(shape2), valid=valid.reshape(lead), no_contact=no_contact.reshape(lead),
        start_inside=inside.reshape(lead), opening_exceeded=opening.reshape(lead), width=width.reshape(lead),
        clearance1=clear[0].reshape(lead), clearance2=clear[1].reshape(lead), no_normal=no_normal.reshape(lead),
        on_obstacle=on_obstacle.reshape(lead),
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
    rec = gather_records(bank._coef_rec, flat, bank._coef_dtype, 'exact')
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
    px = np.multiply(tt, u32[:, 0, None, None], out=WORKSPACE.get('march_x', shape, np.float32))
    px += (ox + pad).astype(np.float32)[:, :, None]
    py = np.multiply(tt, u32[:, 1, None, None], out=WORKSPACE.get('march_y', shape, np.float32))
    py += (oy + pad).astype(np.float32)[:, :, None]
    if on_padded:
        f = bank._values_padded32(px, py, None if idx is None else (idx * bank._cells_padded)[:, None, None])
    else:
        f = bank.values_cells(px - pad, py - pad, None if idx is None else idx[:, None, None], on_padded_grid=False)
    neg = np.less_equal(f, 0.0, out=WORKSPACE.get('neg', shape, np.bool_))
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
