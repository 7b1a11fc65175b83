"""Grasp quality: 2-D Ferrari–Canny L1 metric Q_F and probability of force closure P_F (paper V-C, V-D).

**Contact wrenches.** Each of the two hard finger contacts with Coulomb friction γ contributes the
two edges of its friction cone, ``f± = −n ± γ t`` with ``n`` the unit *outward* normal (the jaw
pushes along −n) and ``t = (−n_y, n_x)`` the unit tangent; every edge has unit normal component
(the L1 Ferrari–Canny convention: the sum of the normal forces is bounded by 1). The wrench of a
force about the centre of mass ``z`` is ``w = (f_x, f_y, τ/ρ)`` with ``τ = (c − z) × f``.

**Torque scale ρ.** Torques are divided by a characteristic object length so that all three
wrench components are dimensionless. We use the object's radius of gyration about its centre of
mass, ``ρ = sqrt(mean_{x ∈ object} ‖x − z‖²)`` over the interior cells of the *mean* shape
(:func:`torque_scale`); it is a property of the object, not of the grasp, so Q_F values of
different grasps on one object are comparable (a per-grasp scale such as max ‖c_i − z‖ would
rescale the torque axis differently for every grasp). The same ρ is used for every
Monte-Carlo sample: rescaling the torque axis is a positive linear map of wrench space, so the
sign of Q_F — hence force closure and P_F — does not depend on ρ (nor on z: moving the reference
point is a shear of wrench space); ρ and z only set the magnitude of Q_F.

**Q_F.** The largest origin-centred ball inside the convex hull of the 4 wrenches. In 3-D the
hull of 4 points is a tetrahedron; Q_F is the minimum over its 4 facets of the signed distance
from the origin to the facet plane (positive inside), so Q_F > 0 ⇔ the origin is strictly inside
⇔ force closure (Nguyen: the line between the contacts lies inside both friction cones), and
Q_F ≤ 0 otherwise (then it is minus the distance to the farthest separating facet plane — not the
exact distance to the hull, but its sign is exact). A flat tetrahedron (|6·volume| < 1e-12)
has an empty interior and gets Q_F = 0. Computed in closed form, vectorised over any batch.

**P_F (eq. 3).** Monte-Carlo estimate over S *joint* draws of (shape sample f_m, grasp
perturbation ĝ_m): the trial succeeds iff the contacts of ĝ_m on f_m exist, neither jaw starts
inside f_m, and Q_F(ĝ_m, f_m) > 0 with contacts, normals (finite differences of f_m) and centre of
mass z_m = COM{f_m < 0} all taken from f_m (:class:`ShapeSamples` carries z_m). Because the sign of
Q_F depends on neither z nor ρ, the count uses the equivalent closed-form two-contact test
:func:`force_closure` (Nguyen) instead of building the wrench hull. Grasps whose commanded
opening exceeds w_g fail every trial. P̂_F = successes / S with standard error
sqrt(P̂_F (1 − P̂_F) / S). The same S draws (and perturbation noise) are used for every grasp
evaluated with one :class:`ShapeSamples` — common random numbers, which makes comparisons
between grasps much less noisy. Trials are laid out sample-major so consecutive trials reuse
one sample's interpolation coefficients from cache.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numba import njit

from gpis_grasp_ros.core.contacts import Contacts, find_contacts, perturb_grasps
from gpis_grasp_ros.core.gpis import GpisPosterior, center_of_mass
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.core.sdf_bank import SdfBank

#: Number of trials (grasps × samples) evaluated at once by :func:`probability_force_closure`.
MAX_TRIALS_PER_CHUNK = 1 << 13

_OPPOSITE = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])


def contact_wrenches(c1: np.ndarray, c2: np.ndarray, n1: np.ndarray, n2: np.ndarray, com: np.ndarray,
                     friction_coef: float, torque_scale: float) -> np.ndarray:
    """Friction-cone edge wrenches ``(..., 4, 3)``: (f_x, f_y, τ/ρ) for edges −n_i ± γ t_i.

    Contacts ``c`` and centre of mass ``com`` in m, unit outward normals ``n``, ρ in m.
    """
    c = np.stack(np.broadcast_arrays(np.asarray(c1, float), np.asarray(c2, float)), axis=-2)  # (..., 2, 2)
    n = np.stack(np.broadcast_arrays(np.asarray(n1, float), np.asarray(n2, float)), axis=-2)
    r = c - np.asarray(com, dtype=np.float64)[..., None, :]
    tx, ty = -n[..., 1], n[..., 0]
    fx = np.stack([-n[..., 0] + friction_coef * tx, -n[..., 0] - friction_coef * tx], axis=-1)  # (..., 2, 2)
    fy = np.stack([-n[..., 1] + friction_coef * ty, -n[..., 1] - friction_coef * ty], axis=-1)
    tau = (r[..., 0, None] * fy - r[..., 1, None] * fx) / torque_scale
    w = np.stack([fx, fy, tau], axis=-1)  # (..., contact, edge, 3)
    return w.reshape(w.shape[:-3] + (4, 3))


def hull_ball_radius(w: np.ndarray) -> np.ndarray:
    """Signed radius of the largest origin-centred ball in the tetrahedron of 4 points ``(..., 4, 3)``."""
    w = np.asarray(w, dtype=np.float64)
    a = w[..., _OPPOSITE[:, 0], :]
    b = w[..., _OPPOSITE[:, 1], :] - a
    c = w[..., _OPPOSITE[:, 2], :] - a
    nx = b[..., 1] * c[..., 2] - b[..., 2] * c[..., 1]
    ny = b[..., 2] * c[..., 0] - b[..., 0] * c[..., 2]
    nz = b[..., 0] * c[..., 1] - b[..., 1] * c[..., 0]
    rel = w - a  # vertex j relative to a point of the opposite facet
    side = nx * rel[..., 0] + ny * rel[..., 1] + nz * rel[..., 2]  # = ±6 V for every facet
    sign = np.where(side > 0, -1.0, 1.0)  # orient normals away from the opposite vertex
    norm = np.sqrt(nx * nx + ny * ny + nz * nz)
    dist = sign * (nx * a[..., 0] + ny * a[..., 1] + nz * a[..., 2]) / np.where(norm > 0, norm, 1.0)
    q = dist.min(axis=-1)
    degenerate = np.abs(side).max(axis=-1) < 1e-12
    return np.where(degenerate, 0.0, q)


def ferrari_canny_l1(c1: np.ndarray, c2: np.ndarray, n1: np.ndarray, n2: np.ndarray, com: np.ndarray,
                     friction_coef: float, torque_scale: float) -> np.ndarray:
    """2-D L1 Ferrari–Canny quality Q_F(c, n, z) (paper V-C); > 0 ⇔ force closure. NaN in → NaN out."""
    return hull_ball_radius(contact_wrenches(c1, c2, n1, n2, com, friction_coef, torque_scale))


def force_closure(c1: np.ndarray, c2: np.ndarray, n1: np.ndarray, n2: np.ndarray, friction_coef: float) -> np.ndarray:
    """Exact sign test Q_F > 0 for two frictional point contacts in the plane (Nguyen 1988).

    Force closure ⇔ the line through c1 and c2 lies strictly inside both friction cones: either
    ``c2 − c1`` is within arctan γ of the inward normal −n1 and ``c1 − c2`` within arctan γ of
    −n2 (a squeezing grasp), or the same with both directions reversed (an expanding grasp,
    which a closing parallel jaw essentially never produces but which Q_F also counts).
    Equivalent to :func:`ferrari_canny_l1` > 0 (checked in the tests) at a fraction of the cost,
    so Monte-Carlo P_F uses it; NaN contacts and coincident contacts give False.
    """
    d = np.asarray(c2, dtype=np.float64) - np.asarray(c1, dtype=np.float64)
    dist = np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2)
    lim = dist / math.sqrt(1.0 + friction_coef * friction_coef)  # |d| cos(arctan γ)
    cos1 = -(n1[..., 0] * d[..., 0] + n1[..., 1] * d[..., 1])
    cos2 = n2[..., 0] * d[..., 0] + n2[..., 1] * d[..., 1]
    squeeze = (cos1 > lim) & (cos2 > lim)
    expand = (cos1 < -lim) & (cos2 < -lim)
    return (squeeze | expand) & (dist > 0)


def torque_scale(sdf: np.ndarray, geometry: GridGeometry, com: np.ndarray | None = None) -> float:
    """Radius of gyration ρ (m) of the shape {sdf < 0} about ``com`` (default: its centre of mass).

    Falls back to one grid cell for an empty or single-cell shape.
    """
    sdf = np.asarray(sdf, dtype=np.float64)
    inside = sdf < 0
    if com is None:
        com = center_of_mass(sdf[None], geometry)[0]
    if not inside.any():
        return geometry.resolution
    pts = geometry.cell_centers()[inside]
    rho = float(np.sqrt(np.mean(np.sum((pts - np.asarray(com)) ** 2, axis=1))))
    return max(rho, geometry.resolution)


@njit(cache=True, nogil=True)
def _quality_kernel(c, n, com, valid, gamma, rho, out):
    """Compiled :func:`ferrari_canny_l1` for T trials (c, n (T, 2, 2), com (T or 1, 2)); −inf where not
    ``valid`` or not finite (the closed form of :func:`hull_ball_radius`, facet by facet)."""
    w = np.empty((4, 3))
    for t in range(c.shape[0]):
        ci = 0 if com.shape[0] == 1 else t
        if not valid[t]:
            out[t] = -np.inf
            continue
        for k in range(2):
            nx = n[t, k, 0]
            ny = n[t, k, 1]
            rx = c[t, k, 0] - com[ci, 0]
            ry = c[t, k, 1] - com[ci, 1]
            for e in range(2):
                sg = 1.0 if e == 0 else -1.0
                fx = -nx + sg * gamma * (-ny)
                fy = -ny + sg * gamma * nx
                w[2 * k + e, 0] = fx
                w[2 * k + e, 1] = fy
                w[2 * k + e, 2] = (rx * fy - ry * fx) / rho
        q = np.inf
        side_max = 0.0
        finite = True
        for f in range(4):
            i0 = 1 if f == 0 else 0
            i1 = 2 if f <= 1 else 1
            i2 = 3 if f <= 2 else 2
            ax, ay, az = w[i0, 0], w[i0, 1], w[i0, 2]
            bx, by, bz = w[i1, 0] - ax, w[i1, 1] - ay, w[i1, 2] - az
            cx, cy, cz = w[i2, 0] - ax, w[i2, 1] - ay, w[i2, 2] - az
            nx = by * cz - bz * cy
            ny = bz * cx - bx * cz
            nz = bx * cy - by * cx
            side = nx * (w[f, 0] - ax) + ny * (w[f, 1] - ay) + nz * (w[f, 2] - az)
            sign = -1.0 if side > 0 else 1.0
            norm = math.sqrt(nx * nx + ny * ny + nz * nz)
            dist = sign * (nx * ax + ny * ay + nz * az) / (norm if norm > 0 else 1.0)
            if not (math.isfinite(dist) and math.isfinite(side)):
                finite = False
            q = min(q, dist)
            side_max = max(side_max, abs(side))
        if not finite:
            out[t] = -np.inf
        elif side_max < 1e-12:
            out[t] = 0.0
        else:
            out[t] = q


def grasp_quality(contacts: Contacts, com: np.ndarray, gripper: GripperParams, rho: float) -> np.ndarray:
    """Q_F of a batch of contacts (``com`` broadcastable to ``(..., 2)``); −inf for degenerate grasps.

    Compiled (:func:`_quality_kernel`); :func:`ferrari_canny_l1` is the vectorised numpy form of
    the same closed form (the tests check they agree).
    """
    lead = contacts.valid.shape
    flat = int(np.prod(lead, dtype=np.int64))
    shape2 = lead + (2,)
    def full(x: np.ndarray) -> np.ndarray:
        return x if x.shape == shape2 else np.broadcast_to(x, shape2)

    c = np.stack([full(contacts.c1), full(contacts.c2)], axis=-2)
    n = np.stack([full(contacts.n1), full(contacts.n2)], axis=-2)
    com = np.asarray(com, dtype=np.float64)
    com_flat = com.reshape(1, 2) if com.shape == (2,) else np.ascontiguousarray(
        np.broadcast_to(com, shape2).reshape(-1, 2))
    c = c.reshape(flat, 2, 2)
    n = n.reshape(flat, 2, 2)
    out = np.empty(flat)
    _quality_kernel(c, n, com_flat, np.ascontiguousarray(contacts.valid, dtype=np.bool_).reshape(-1),
                    float(gripper.friction_coef), float(rho), out)
    return out.reshape(lead)


class ShapeSamples:
    """S joint GPIS samples with everything P_F needs, plus S grasp-perturbation draws (CRN).

    ``bank`` the sampled SDFs (m) ready for contact finding, ``eps`` (S, 2, 2) standard-normal
    perturbation draws (trial m pairs sample m with eps m), ``rho`` the torque scale (m), ``com``
    (S, 2) the samples' centres of mass (m). P_F does not read the centres of mass (force closure
    depends on neither z nor ρ), so ``com=None`` computes them on first access only.
    """

    def __init__(self, bank: SdfBank, com: np.ndarray | None, eps: np.ndarray, rho: float) -> None:
        self.bank = bank
        self._com = None if com is None else np.asarray(com, dtype=np.float64)
        self.eps = eps
        self.rho = rho

    @property
    def com(self) -> np.ndarray:
        """(S, 2) centres of mass (m) of the samples {f_m < 0} (computed on first access when not given)."""
        if self._com is None:  # the target's cells: inside a sample and not inside an obstacle
            sdfs = self.bank.sdfs if self.bank.obstacles is None else np.where(
                self.bank.obstacles[None] < 0, np.inf, self.bank.sdfs)
            self._com = center_of_mass(sdfs, self.bank.geometry)
        return self._com

    @property
    def n(self) -> int:
        return self.bank.n


def draw_shape_samples(posterior: GpisPosterior, n: int, rng: np.random.Generator,
                       rho: float | None = None, precision: type = np.float32) -> ShapeSamples:
    """Draw ``n`` joint SDF samples and perturbation noise for Monte-Carlo P_F.

    The random stream is :meth:`GpisPosterior.sample`'s (then the perturbations); ``precision`` is that of
    the product L eps (:meth:`GpisPosterior.sample_deviations`; float32 by default: the samples differ from
    the float64 ones by ~1e-9 m and the force-closure counts by a trial in thousands, docs/speed.md), the
    mean is added in float64. ``np.float64`` gives exactly ``SdfBank(posterior.sample(n, rng))``.
    """
    bank = SdfBank.from_deviations(posterior.mean, posterior.sample_deviations(n, rng, precision), posterior.geometry,
                                   obstacles=posterior.obstacles)
    eps = rng.standard_normal((n, 2, 2))
    if rho is None:
        rho = torque_scale(posterior.mean, posterior.geometry)
    return ShapeSamples(bank, None, eps, rho)


@dataclass
class PfEstimate:
    """Monte-Carlo P_F for G grasps: ``p`` (G,), ``std_error`` (G,), ``successes`` (G,) of ``n`` trials."""

    p: np.ndarray
    std_error: np.ndarray
    successes: np.ndarray
    n: int


def force_closure_successes(jaw1: np.ndarray, jaw2: np.ndarray, samples: ShapeSamples, gripper: GripperParams,
                            sigma_g: float, start: int = 0, stop: int | None = None,
                            checkpoint: Callable[[], None] | None = None) -> np.ndarray:
    """Number of force-closure trials (G,) of grasps ``(G, 2)`` over samples ``start:stop``.

    ``checkpoint`` is called before every chunk of about ``MAX_TRIALS_PER_CHUNK`` trials; it may
    raise to abort (cooperative cancellation of a plan).
    """
    jaw1 = np.atleast_2d(np.asarray(jaw1, dtype=np.float64))
    jaw2 = np.atleast_2d(np.asarray(jaw2, dtype=np.float64))
    stop = samples.n if stop is None else min(stop, samples.n)
    n_s = max(stop - start, 0)
    n_g = jaw1.shape[0]
    out = np.zeros(n_g, dtype=np.int64)
    if n_s == 0 or n_g == 0:
        return out
    feasible = np.linalg.norm(jaw2 - jaw1, axis=1) <= gripper.max_opening * (1.0 + 1e-9) + 1e-12
    rows = np.flatnonzero(feasible)
    if rows.size == 0:
        return out
    # Trials are laid out sample-major, (samples, grasps): consecutive trials close on the same
    # sample grid, which keeps its interpolation coefficients in cache (about 4x faster gathers).
    g1n, g2n = jaw1[rows], jaw2[rows]
    chunk = max(1, MAX_TRIALS_PER_CHUNK // rows.size)
    counts = np.zeros(rows.size, dtype=np.int64)
    for s0 in range(start, stop, chunk):
        if checkpoint is not None:
            checkpoint()
        s1 = min(s0 + chunk, stop)
        eps = samples.eps[s0:s1, None]  # (s, 1, 2, 2)
        g1, g2 = perturb_grasps(g1n[None], g2n[None], eps, sigma_g)
        index = np.arange(s0, s1)[:, None]
        con = find_contacts(samples.bank, g1, g2, gripper, index=index, check_opening=False)
        # Q_F(ĝ, f_m) > 0 ⇔ force closure: use the exact two-contact sign test (no wrench hull).
        ok = con.valid & force_closure(con.c1, con.c2, con.n1, con.n2, gripper.friction_coef)
        counts += np.count_nonzero(ok, axis=0)
    out[rows] = counts
    return out


def probability_force_closure(jaw1: np.ndarray, jaw2: np.ndarray, samples: ShapeSamples, gripper: GripperParams,
                              sigma_g: float, start: int = 0, stop: int | None = None,
                              checkpoint: Callable[[], None] | None = None) -> PfEstimate:
    """Monte-Carlo P_F (eq. 3) and its standard error for grasps ``(G, 2)`` (m) over samples ``start:stop``.

    ``checkpoint``: see :func:`force_closure_successes`.
    """
    stop = samples.n if stop is None else min(stop, samples.n)
    n = max(stop - start, 0)
    succ = force_closure_successes(jaw1, jaw2, samples, gripper, sigma_g, start, stop, checkpoint)
    p = succ / max(n, 1)
    se = np.sqrt(p * (1.0 - p) / max(n, 1))
    return PfEstimate(p=p, std_error=se, successes=succ, n=n)
