"""Compiled (numba) kernel of the exact contact search of :mod:`contacts` (paper section V-B).

The model is exactly the one :mod:`contacts` documents — face lines across each jaw, exact zero
crossings of the bilinear SDF, the contact patch — but each line is walked cell by cell from
each jaw and the walk **stops at the first crossing** instead of solving the quadratic on every
cell the line crosses (on a 25 x 25 grid a jaw usually meets the object a few cells from where
it starts, while the line is ~18 cells long). Everything is float64 and read from the padded
float64 grids of the bank (the vectorised reference in :mod:`contacts` works in float32, 1e-6 cell
round-off).

Per segment (the part of a line inside one grid cell, cells cut where the line crosses a grid
line) the bilinear interpolant restricted to the line is ``c0 + c1 τ + c2 τ²``. A segment *hits*
when it starts at f <= 0 (the crossing then lies in the previous segment, whose end is inside)
or dips below zero inside (c2 > 0, vertex inside the segment, negative discriminant test); the
crossing is the smallest root in the segment (numerically stable quadratic formula). The crossing
seen from jaw 2 is the first crossing of the same line walked backwards from its far end.

**Lines that leave the padded grid** (a small object: the 9 cm opening spans many of its cells).
Beyond the padded grid the SDF is the value at the nearest point of the padded grid plus the
distance (m), as :meth:`sdf_bank.SdfBank.values_cells` extrapolates it (:func:`_extended`). Along a
line that field is piecewise simple (:func:`off_grid_crossing`): beside an edge of the grid it is the
edge's value (linear between two nodes) plus the distance to the edge (linear), so linear between
the points where the line crosses a node's row or column; beside a corner it is the corner node's
value plus the distance to it, whose zero is a circle around the corner (a quadratic). The walk
takes the part of the line before the grid, the part over it (the cell walk above, after clipping
the line to the grid, :func:`_clip`, Liang-Barsky) and the part after it in order, with exact
crossings in all three. When every border node of a padded grid is positive
(:func:`border_positive`) the extrapolated field is positive everywhere off the grid - the border
is linear between its nodes and the distance only adds - and only the part over the grid is walked.
The jaw clearances and the start-inside test use the extended field at the line ends.

``cache=True``: the machine code is cached next to this file (``__pycache__``), so only the first
import on a machine pays the compile time (a few seconds). The walk (:func:`_line_crossing`,
:func:`first_crossing`, :func:`_walk`) is inlined into the per-trial loop (``inline='always'``): the same
arithmetic, about a quarter less time than calls.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Roots within this tolerance (cells, plus the same relative to the segment) of a segment still count.
ROOT_TOL = 1e-6

#: Bounded jumps (see :func:`first_crossing`) are taken while they exceed this many cells.
JUMP_MIN_CELLS = 1.0


@njit(cache=True, nogil=True, inline='always')
def _bilinear(grid, u, v):
    """Bilinear value of one padded grid at padded cell coordinates (u, v) (on the padded grid)."""
    hp, wp = grid.shape
    j = min(max(int(math.floor(u)), 0), wp - 2)
    i = min(max(int(math.floor(v)), 0), hp - 2)
    fx = u - j
    fy = v - i
    f00 = grid[i, j]
    f01 = grid[i, j + 1]
    f10 = grid[i + 1, j]
    f11 = grid[i + 1, j + 1]
    return f00 + (f01 - f00) * fx + fy * ((f10 - f00) + (f11 - f01 - f10 + f00) * fx)


@njit(cache=True, nogil=True, inline='always')
def _extended(grid, u, v, res):
    """SDF (m) at padded cell coordinates (u, v) anywhere: bilinear on the padded grid, beyond it the
    value at the nearest point of the padded grid plus the distance to it (``res`` m per cell)."""
    hp, wp = grid.shape
    uc = min(max(u, 0.0), wp - 1.0)
    vc = min(max(v, 0.0), hp - 1.0)
    f = _bilinear(grid, uc, vc)
    if uc != u or vc != v:
        f += math.hypot(u - uc, v - vc) * res
    return f


@njit(cache=True, nogil=True, inline='always')
def _clip(px, py, ux, uy, length, wp, hp):
    """(t_in, t_out): the part of the segment from (px, py) along (ux, uy) for ``length`` cells that
    lies in the padded grid [0, wp - 1] x [0, hp - 1] (Liang-Barsky); t_in > t_out when it misses
    the grid. A segment inside the grid gives exactly (0, length)."""
    t_in = 0.0
    t_out = length
    for axis in range(2):
        p = px if axis == 0 else py
        u = ux if axis == 0 else uy
        hi = (wp - 1.0) if axis == 0 else (hp - 1.0)
        if abs(u) < 1e-15:
            if p < 0.0 or p > hi:
                return 1.0, 0.0
            continue
        a = -p / u
        b = (hi - p) / u
        if a > b:
            a, b = b, a
        t_in = max(t_in, a)
        t_out = min(t_out, b)
    return t_in, t_out


@njit(cache=True, nogil=True)
def off_grid_crossing(grid, px, py, ux, uy, t0, t1, res):
    """First zero crossing (t, from (px, py) along the unit vector (ux, uy); padded cell coordinates) in
    [t0, t1] of the extrapolated SDF (:func:`_extended`, ``res`` m per cell) on a part of a line that runs
    off the padded grid (on its border at most). Returns ``(t, hit)``; a part that starts at f <= 0 hits
    at t0.

    The part is cut where the line crosses an integer row or column; in each piece the clamped point
    runs along one border edge between two nodes (f linear in t) or stays at one corner node k
    (f = f(k) + res |p - k|, zero on the circle |p - k| = -f(k) / res)."""
    hp, wp = grid.shape
    xmax = wp - 1.0
    ymax = hp - 1.0
    ta = t0
    ga = _extended(grid, px + ta * ux, py + ta * uy, res)
    if ga <= 0:
        return ta, True
    while ta < t1:
        tb = t1
        for axis in range(2):
            p = (px + ta * ux) if axis == 0 else (py + ta * uy)
            u = ux if axis == 0 else uy
            p0 = px if axis == 0 else py
            if abs(u) < 1e-15:
                continue
            k = math.floor(p + 1e-9) + 1.0 if u > 0 else math.ceil(p - 1e-9) - 1.0  # next row / column
            tk = (k - p0) / u
            if ta < tk < tb:
                tb = tk
        tm = 0.5 * (ta + tb)
        mx = px + tm * ux
        my = py + tm * uy
        gb = _extended(grid, px + tb * ux, py + tb * uy, res)
        if (0.0 <= mx <= xmax) or (0.0 <= my <= ymax):  # beside an edge (or over the grid): linear
            if gb <= 0:
                return ta + (tb - ta) * ga / (ga - gb), True
        else:  # beside a corner node k: f(k) + res |p - k| = 0 on a circle of radius r
            kx = 0.0 if mx < 0 else xmax
            ky = 0.0 if my < 0 else ymax
            fk = grid[int(ky), int(kx)]
            if fk < 0:
                r = -fk / res
                dx = px + ta * ux - kx
                dy = py + ta * uy - ky
                b = dx * ux + dy * uy
                c = dx * dx + dy * dy - r * r
                disc = b * b - c
                if disc >= 0:
                    sq = math.sqrt(disc)
                    for tau in (-b - sq, -b + sq):
                        if 0.0 <= tau <= tb - ta:
                            return ta + tau, True
        ta = tb
        ga = gb
    return 0.0, False


@njit(cache=True, nogil=True, inline='always')
def _line_crossing(grid, px, py, ux, uy, window, lip, f_start, res, positive, t_in, t_out):
    """First zero crossing within ``window`` cells of (px, py) along (ux, uy) of a line that runs over the
    padded grid on [t_in, t_out] (t_in > t_out: never): the part before the grid, the part over it
    (:func:`first_crossing`) and the part after it, in order; the parts off the grid only if the grid's
    border is not ``positive``. Returns ``(t, hit)``."""
    if t_in > t_out:
        if positive:
            return 0.0, False
        return off_grid_crossing(grid, px, py, ux, uy, 0.0, window, res)
    if t_in > 0 and not positive:
        t, hit = off_grid_crossing(grid, px, py, ux, uy, 0.0, min(t_in, window), res)
        if hit:
            return t, True
    if window > t_in:
        s, hit = first_crossing(grid, px + t_in * ux, py + t_in * uy, ux, uy, min(window, t_out) - t_in, lip,
                                f_start if t_in == 0.0 else math.nan)
        if hit:
            return t_in + s, True
    if window > t_out and not positive:
        return off_grid_crossing(grid, px, py, ux, uy, t_out, window, res)
    return 0.0, False


@njit(cache=True, nogil=True, inline='always')
def grid_border_positive(grid):
    """Every node on the border of one padded grid (Hp, Wp) is > 0 (:func:`border_positive`)."""
    hp, wp = grid.shape
    for i in range(hp):
        if grid[i, 0] <= 0 or grid[i, wp - 1] <= 0:
            return False
    for j in range(wp):
        if grid[0, j] <= 0 or grid[hp - 1, j] <= 0:
            return False
    return True


@njit(cache=True, nogil=True)
def border_positive(grids):
    """Per padded grid (B, Hp, Wp): every node on its border is > 0 (then the extrapolated SDF is
    positive everywhere off the grid: see the module docstring)."""
    out = np.ones(grids.shape[0], dtype=np.bool_)
    for k in range(grids.shape[0]):
        out[k] = grid_border_positive(grids[k])
    return out


@njit(cache=True, nogil=True, inline='always')
def _smallest_root(q0, q1, q2, dd):
    """Smallest root of q0 + q1 τ + q2 τ² in [0, dd] (tolerance :data:`ROOT_TOL`); fallback 0 if
    q0 <= 0 (the segment starts inside), else dd (its end is inside)."""
    sq = math.sqrt(max(q1 * q1 - 4.0 * q2 * q0, 0.0))
    qq = -0.5 * (q1 + (sq if q1 >= 0 else -sq))
    tol = ROOT_TOL + ROOT_TOL * dd
    best = math.inf
    if abs(q2) > 1e-15:
        r = qq / q2
        if -tol <= r <= dd + tol:
            best = r
    if qq != 0:
        r = q0 / qq
        if -tol <= r <= dd + tol and r < best:
            best = r
    if best == math.inf:
        return 0.0 if q0 <= 0 else dd
    return min(max(best, 0.0), dd)


@njit(cache=True, nogil=True, inline='always')
def first_crossing(grid, px, py, ux, uy, length, lipschitz=0.0, f_start=math.nan):
    """First zero crossing (cells from the start) of the bilinear SDF on the segment from (px, py)
    (padded cell coordinates) along the unit vector (ux, uy) for ``length`` cells.

    ``lipschitz`` (m per cell, 0: unused) bounds the gradient norm of the bilinear interpolant on
    the whole padded grid (:func:`lipschitz_bounds`). Where f > 0 there is then no zero within
    f / lipschitz cells, so the walk first jumps ahead in steps of that size (sphere tracing with
    a proven bound, not a heuristic) while they exceed :data:`JUMP_MIN_CELLS`; the crossing found
    is the same. ``f_start`` (optional) is f at the start if the caller has it. Returns
    ``(t, hit)``; ``hit`` is False when f > 0 along the whole segment.
    """
    t_skip = 0.0
    if lipschitz > 0:
        f = f_start if f_start == f_start else _bilinear(grid, px, py)
        while f > JUMP_MIN_CELLS * lipschitz:
            t_skip += f / lipschitz
            if t_skip >= length:
                return 0.0, False
            f = _bilinear(grid, px + t_skip * ux, py + t_skip * uy)
        if t_skip > 0:
            t, hit = _walk(grid, px + t_skip * ux, py + t_skip * uy, ux, uy, length - t_skip)
            return t_skip + t, hit
    return _walk(grid, px, py, ux, uy, length)


@njit(cache=True, nogil=True, inline='always')
def grid_lipschitz(grid):
    """The Lipschitz constant (m per cell) of one padded grid's (Hp, Wp) bilinear interpolant
    (:func:`lipschitz_bounds`)."""
    hp, wp = grid.shape
    best = 0.0
    for i in range(hp - 1):
        for j in range(wp - 1):
            top = grid[i, j + 1] - grid[i, j]
            bottom = grid[i + 1, j + 1] - grid[i + 1, j]
            left = grid[i + 1, j] - grid[i, j]
            right = grid[i + 1, j + 1] - grid[i, j + 1]
            # the largest of the 4 corners' squared norms: max(top², bottom²) + max(left², right²) (rounding is
            # monotonic, so this is the largest of the 4 rounded sums, bit for bit); branch-free, it vectorises
            t2, b2, l2, r2 = top * top, bottom * bottom, left * left, right * right
            corner = (t2 if t2 > b2 else b2) + (l2 if l2 > r2 else r2)
            best = corner if corner > best else best
    return math.sqrt(best) * (1.0 + 1e-9)


@njit(cache=True, nogil=True)
def lipschitz_bounds(grids):
    """Per grid (B, Hp, Wp): the Lipschitz constant (m per cell) of its bilinear interpolant.

    In a cell ∇f = (k1 + k3·fy, k2 + k3·fx) is affine in (fx, fy), so ‖∇f‖² is convex and its
    maximum over the cell is reached at a corner, where the gradient is the pair of differences
    along the two cell edges meeting there. The maximum over all cells and corners is the exact
    bound (f is continuous across cells), ~1 cell of SDF per cell for a true SDF.
    """
    out = np.zeros(grids.shape[0])
    for k in range(grids.shape[0]):
        out[k] = grid_lipschitz(grids[k])
    return out


@njit(cache=True, nogil=True, inline='always')
def _walk(grid, px, py, ux, uy, length):
    """The cell-by-cell walk of :func:`first_crossing` (no jumps)."""
    hp, wp = grid.shape
    ax = abs(ux)
    ay = abs(uy)
    # distance (cells) to the k-th grid line crossed along x and y: (first + k) / |u|
    if ax > 1e-12:
        first_x = (math.floor(px) + 1.0 - px) if ux >= 0 else (px - math.ceil(px) + 1.0)
        inv_x = 1.0 / ax
    else:
        first_x = 0.0
        inv_x = math.inf
    if ay > 1e-12:
        first_y = (math.floor(py) + 1.0 - py) if uy >= 0 else (py - math.ceil(py) + 1.0)
        inv_y = 1.0 / ay
    else:
        first_y = 0.0
        inv_y = math.inf
    kx = 0
    ky = 0
    tx = first_x * inv_x if inv_x != math.inf else math.inf
    ty = first_y * inv_y if inv_y != math.inf else math.inf
    t_a = 0.0
    have_prev = False
    p0 = p1 = p2 = pdd = pt = 0.0
    while True:
        t_b = min(tx, ty, length)
        if t_b > t_a:
            tm = 0.5 * (t_a + t_b)
            cu = min(max(int(math.floor(px + tm * ux)), 0), wp - 2)
            cv = min(max(int(math.floor(py + tm * uy)), 0), hp - 2)
            fa = px + t_a * ux - cu
            fb = py + t_a * uy - cv
            f00 = grid[cv, cu]
            k1 = grid[cv, cu + 1] - f00
            k2 = grid[cv + 1, cu] - f00
            k3 = grid[cv + 1, cu + 1] - grid[cv, cu + 1] - grid[cv + 1, cu] + f00
            c0 = f00 + k1 * fa + fb * (k2 + k3 * fa)
            c1 = k1 * ux + k2 * uy + k3 * (fa * uy + fb * ux)
            c2 = k3 * (ux * uy)
            dd = t_b - t_a
            if c0 <= 0:
                if not have_prev:  # the start is inside: as the reference, the smallest root of this segment
                    return _smallest_root(c0, c1, c2, dd), True
                return pt + _smallest_root(p0, p1, p2, pdd), True
            if c2 > 0 and c1 < 0 and -c1 < 2.0 * c2 * dd and 4.0 * c0 * c2 < c1 * c1:
                return t_a + _smallest_root(c0, c1, c2, dd), True
            have_prev = True
            p0, p1, p2, pdd, pt = c0, c1, c2, dd, t_a
        if t_b >= length:
            break
        if tx <= t_b:
            kx += 1
            tx = (first_x + kx) * inv_x
        if ty <= t_b:
            ky += 1
            ty = (first_y + ky) * inv_y
        t_a = t_b
    if have_prev and p0 + pdd * (p1 + p2 * pdd) <= 0:  # the end point is inside
        return pt + _smallest_root(p0, p1, p2, pdd), True
    return 0.0, False


@njit(cache=True, nogil=True)
def exact_contacts(grids, lipschitz, positive, index, ax, ay, ux, uy, length, offsets, pad, patch_tol, contacts,
                   no_contact, inside, clearance, res):
    """Contacts of T trials (jaw 1 at (ax, ay), unpadded cells, closing along (ux, uy) for ``length``
    cells) on face lines at ``offsets`` (cells) across the jaw. Lines may leave the padded grid: off it
    the SDF is :func:`_extended` (``res`` m per cell), walked only where the grid's border is not
    ``positive`` (B,) (:func:`border_positive`; see the module docstring).

    ``grids`` (B, Hp, Wp) padded SDFs (m), ``lipschitz`` (B,) their :func:`lipschitz_bounds` (zeros:
    walk every cell), ``index`` (T,) grid of each trial. Fills ``contacts``
    (2, T, 2) (unpadded cells, jaw 1 then jaw 2), ``no_contact`` (T,), ``inside`` (T,) (a face
    line starts or ends at f <= 0) and ``clearance`` (2, T) (min f (m) over each jaw face).
    The contact patch is that of :func:`contacts._march_chunk` (linear ramp over ``patch_tol``
    cells times the trapezoid weight of the line).
    """
    n_t = ax.shape[0]
    n_l = offsets.shape[0]
    t_hit = np.empty((2, n_l))
    has = np.empty((2, n_l), dtype=np.bool_)
    hp = grids.shape[1]
    wp = grids.shape[2]
    for t in range(n_t):
        grid = grids[index[t]]
        lip = lipschitz[index[t]]
        pos = positive[index[t]]
        vx = ux[t]
        vy = uy[t]
        ln = length[t]
        perp_x = -vy
        perp_y = vx
        clear0 = math.inf
        clear1 = math.inf
        into = False
        any_hit = False
        # Crossings farther than (first touch + patch_tol) from a jaw get zero patch weight, so each
        # walk stops there: the windows only shrink as lines are added, never below the final one.
        reach1 = ln
        reach2 = ln
        for k in range(n_l):
            ox = ax[t] + pad + offsets[k] * perp_x
            oy = ay[t] + pad + offsets[k] * perp_y
            ex = ox + ln * vx
            ey = oy + ln * vy
            f0 = _extended(grid, ox, oy, res)
            f1 = _extended(grid, ex, ey, res)
            clear0 = min(clear0, f0)
            clear1 = min(clear1, f1)
            if f0 <= 0 or f1 <= 0:
                into = True
            has[1, k] = False
            # the part of the line over the padded grid, as distances from jaw 1 [t_in, t_out] and from
            # jaw 2 [ln - t_out, ln - t_in]; the whole line (0, ln) when it stays on the grid
            t_in, t_out = _clip(ox, oy, vx, vy, ln, wp, hp)
            # where a zero can be: the whole line, or only over the grid when the border is positive
            last1 = t_out if pos else ln
            last2 = ln - t_in if pos else ln
            s1, h1 = _line_crossing(grid, ox, oy, vx, vy, reach1, lip, f0, res, pos, t_in, t_out)
            has[0, k] = h1
            if h1 or reach1 < last1:  # a crossing, or the walk stopped at the window: try from jaw 2
                s2, h2 = _line_crossing(grid, ex, ey, -vx, -vy, reach2, lip, f1, res, pos, ln - t_out, ln - t_in)
                has[1, k] = h2
                if h1:
                    t_hit[0, k] = s1
                    any_hit = True
                    reach1 = min(reach1, s1 + patch_tol)
                if h2:
                    t_hit[1, k] = ln - s2
                    any_hit = True
                    reach2 = min(reach2, s2 + patch_tol)
                elif h1 and reach2 >= last2:  # round-off: the whole line walked back without the touch seen
                    has[1, k] = True
                    t_hit[1, k] = s1
        inside[t] = into
        no_contact[t] = not any_hit
        clearance[0, t] = clear0
        clearance[1, t] = clear1
        for side in range(2):
            sign = 1.0 if side == 0 else -1.0
            tau_min = math.inf
            for k in range(n_l):
                if has[side, k]:
                    tau_min = min(tau_min, sign * t_hit[side, k])
            total = 0.0
            o_sum = 0.0
            t_sum = 0.0
            if any_hit:
                for k in range(n_l):
                    if not has[side, k]:
                        continue
                    w = 1.0 - (sign * t_hit[side, k] - tau_min) / patch_tol
                    w = min(max(w, 0.0), 1.0)
                    if n_l > 1 and (k == 0 or k == n_l - 1):
                        w *= 0.5
                    total += w
                    o_sum += w * offsets[k]
                    t_sum += w * t_hit[side, k]
            if total <= 0:
                total = 1.0
            o = o_sum / total
            tm = t_sum / total
            contacts[side, t, 0] = ax[t] + o * perp_x + tm * vx
            contacts[side, t, 1] = ay[t] + o * perp_y + tm * vy


@njit(cache=True, nogil=True, inline='always')
def _cell_of(contacts, side, t, h, w):
    """Cell (i, j) and offsets (fx, fy) of a contact (unpadded cells, clamped to the grid); i = -1 when NaN."""
    u = contacts[side, t, 0]
    v = contacts[side, t, 1]
    if not (math.isfinite(u) and math.isfinite(v)):
        return -1, 0, 0.0, 0.0
    u = min(max(u, 0.0), w - 1.0)
    v = min(max(v, 0.0), h - 1.0)
    j = min(int(u), w - 2)
    i = min(int(v), h - 2)
    return i, j, u - j, v - i


@njit(cache=True, nogil=True, inline='always')
def _interpolate(f00, f01, f10, f11, fx, fy):
    return f00 + (f01 - f00) * fx + fy * ((f10 - f00) + (f11 - f01 - f10 + f00) * fx)


@njit(cache=True, nogil=True, inline='always')
def _normalise(gx, gy, min_norm, out, side, t):
    norm = math.sqrt(gx * gx + gy * gy)
    if norm > min_norm:
        out[side, t, 0] = gx / norm
        out[side, t, 1] = gy / norm
    else:
        out[side, t, 0] = 0.0
        out[side, t, 1] = 0.0


@njit(cache=True, nogil=True)
def unit_normals(gradients, index, contacts, min_norm, out):
    """Unit outward normals ``out`` (2, T, 2) at ``contacts`` (2, T, 2) (unpadded cells, clamped to
    the grid): the bilinearly interpolated gradient of grid ``index[t]`` of ``gradients`` (B, H, W, 2),
    normalised; zero where its norm is <= ``min_norm`` (no normal) or the contact is NaN."""
    h = gradients.shape[1]
    w = gradients.shape[2]
    for side in range(2):
        for t in range(contacts.shape[1]):
            i, j, fx, fy = _cell_of(contacts, side, t, h, w)
            if i < 0:
                out[side, t, 0] = 0.0
                out[side, t, 1] = 0.0
                continue
            g = gradients[index[t]]
            gx = _interpolate(g[i, j, 0], g[i, j + 1, 0], g[i + 1, j, 0], g[i + 1, j + 1, 0], fx, fy)
            gy = _interpolate(g[i, j, 1], g[i, j + 1, 1], g[i + 1, j, 1], g[i + 1, j + 1, 1], fx, fy)
            _normalise(gx, gy, min_norm, out, side, t)


@njit(cache=True, nogil=True, inline='always')
def _difference_x(grid, pad, w, i, j, resolution):
    """∂f/∂x at node (i, j) of the unpadded grid inside padded ``grid``, by ``np.gradient``'s formulas."""
    r = pad + i
    if j == 0:
        return (grid[r, pad + 1] - grid[r, pad]) / resolution
    if j == w - 1:
        return (grid[r, pad + w - 1] - grid[r, pad + w - 2]) / resolution
    return (grid[r, pad + j + 1] - grid[r, pad + j - 1]) / (2.0 * resolution)


@njit(cache=True, nogil=True, inline='always')
def _difference_y(grid, pad, h, i, j, resolution):
    """∂f/∂y at node (i, j), as :func:`_difference_x`."""
    c = pad + j
    if i == 0:
        return (grid[pad + 1, c] - grid[pad, c]) / resolution
    if i == h - 1:
        return (grid[pad + h - 1, c] - grid[pad + h - 2, c]) / resolution
    return (grid[pad + i + 1, c] - grid[pad + i - 1, c]) / (2.0 * resolution)


@njit(cache=True, nogil=True)
def unit_normals_from_values(grids, pad, resolution, index, contacts, min_norm, out):
    """:func:`unit_normals` with the gradient grids of the finite differences of the SDFs themselves, computed
    only at the 4 nodes around each contact from the padded grids ``grids`` (B, Hp, Wp) (their interior is the
    SDF: the same values and formulas as the bank's gradient grids, so the same normals)."""
    h = grids.shape[1] - 2 * pad
    w = grids.shape[2] - 2 * pad
    for side in range(2):
        for t in range(contacts.shape[1]):
            i, j, fx, fy = _cell_of(contacts, side, t, h, w)
            if i < 0:
                out[side, t, 0] = 0.0
                out[side, t, 1] = 0.0
                continue
            g = grids[index[t]]
            res = resolution
            gx = _interpolate(_difference_x(g, pad, w, i, j, res), _difference_x(g, pad, w, i, j + 1, res),
                              _difference_x(g, pad, w, i + 1, j, res), _difference_x(g, pad, w, i + 1, j + 1, res),
                              fx, fy)
            gy = _interpolate(_difference_y(g, pad, h, i, j, res), _difference_y(g, pad, h, i, j + 1, res),
                              _difference_y(g, pad, h, i + 1, j, res), _difference_y(g, pad, h, i + 1, j + 1, res),
                              fx, fy)
            _normalise(gx, gy, min_norm, out, side, t)
