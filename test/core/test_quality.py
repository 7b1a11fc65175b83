"""Ferrari–Canny Q_F and Monte-Carlo P_F (paper V-C, V-D): analytic values and property tests."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from gpis_grasp_ros.core.contacts import find_contacts
from gpis_grasp_ros.core.gpis import center_of_mass
from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.core.quality import (
    contact_wrenches,
    draw_shape_samples,
    ferrari_canny_l1,
    force_closure,
    grasp_quality,
    hull_ball_radius,
    probability_force_closure,
    torque_scale,
)
from gpis_grasp_ros.core.sdf_bank import SdfBank
from gpis_grasp_ros.tools.bench_planners import pf_python_loop
from support.synthetic_shapes import certain_rectangle_posterior, disc_sdf, make_geometry, make_posterior, rectangle_sdf

GAMMA = 0.5
G = make_geometry()
CENTRE = np.array([0.0625, 0.0625])


def _rot(v: np.ndarray, ang: np.ndarray) -> np.ndarray:
    c, s = np.cos(ang), np.sin(ang)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def _q_axis(k: float, gamma: float = GAMMA) -> float:
    """Hand-derived Q_F of an ideal antipodal grasp through the COM, contacts at distance k·ρ.

    Wrenches (±1, ±γ, ∓γk) form a symmetric tetrahedron; the facet through (1, γ, −γk),
    (1, −γ, γk), (−1, γ, γk) has normal ∝ (γk, k, 1) and offset γk.
    """
    return gamma * k / math.sqrt(1 + k * k * (1 + gamma * gamma))


def test_disc_diametric_grasp_matches_hand_value() -> None:
    radius = 0.03
    c1, c2 = CENTRE - [radius, 0], CENTRE + [radius, 0]
    q = ferrari_canny_l1(c1, c2, np.array([-1.0, 0]), np.array([1.0, 0]), CENTRE, GAMMA, radius)
    assert q == pytest.approx(GAMMA / math.sqrt(2 + GAMMA ** 2))  # = 1/3 for γ = 0.5
    # the same through contact finding on a disc SDF (normals from the grid, sub-cell contacts)
    bank = SdfBank(disc_sdf(G, tuple(CENTRE), radius), G)
    con = find_contacts(bank, CENTRE - [0.045, 0], CENTRE + [0.045, 0], GripperParams(jaw_width=0.0))
    assert grasp_quality(con, CENTRE, GripperParams(), radius) == pytest.approx(1 / 3, abs=2e-3)


@pytest.mark.parametrize('half', [(0.0175, 0.0125), (0.0225, 0.0075)])  # edges between cell centres
def test_rectangle_grasps_match_hand_values(half: tuple[float, float]) -> None:
    """Grasps through the centre of a rectangle across either side: Q_F = γk/sqrt(1 + k²(1 + γ²))."""
    sdf = rectangle_sdf(G, tuple(CENTRE), half)
    rho = torque_scale(sdf, G)
    bank = SdfBank(sdf, G)
    gr = GripperParams()
    for axis, a in ((np.array([1.0, 0]), half[0]), (np.array([0, 1.0]), half[1])):
        con = find_contacts(bank, CENTRE - 0.044 * axis, CENTRE + 0.044 * axis, gr)
        q = grasp_quality(con, CENTRE, gr, rho)
        assert q == pytest.approx(_q_axis(a / rho), abs=2e-3)
    # radius of gyration of a rectangle: sqrt((a² + b²)/3), up to the grid discretisation
    assert rho == pytest.approx(math.sqrt((half[0] ** 2 + half[1] ** 2) / 3), rel=0.05)


def test_tetrahedron_radius_matches_convex_hull() -> None:
    """Closed-form ball radius equals scipy's hull for origin-inside sets; signs agree otherwise."""
    rng = np.random.default_rng(0)
    w = rng.normal(size=(400, 4, 3)) + rng.normal(scale=0.5, size=(400, 1, 3))
    q = hull_ball_radius(w)
    for i in range(w.shape[0]):
        eq = ConvexHull(w[i]).equations
        inside = np.all(eq[:, 3] < 0)
        assert (q[i] > 0) == inside
        if inside:
            assert q[i] == pytest.approx(np.min(-eq[:, 3]), rel=1e-9, abs=1e-12)
    flat = np.array([[1.0, 0, 0], [0, 1, 0], [-1, -1, 0], [0.5, 0.5, 0]])
    assert hull_ball_radius(flat) == 0.0


def _random_pairs(rng: np.random.Generator, n: int):
    c1 = rng.uniform(-0.05, 0.05, (n, 2))
    ang = rng.uniform(0, 2 * np.pi, n)
    axis = np.stack([np.cos(ang), np.sin(ang)], axis=1)  # from contact 1 to contact 2
    c2 = c1 + rng.uniform(0.01, 0.08, (n, 1)) * axis
    com = rng.uniform(-0.05, 0.05, (n, 2))
    return c1, c2, axis, com


def test_antipodal_pairs_inside_friction_cones_are_force_closure() -> None:
    rng = np.random.default_rng(1)
    n = 600
    c1, c2, axis, com = _random_pairs(rng, n)
    half_angle = math.atan(GAMMA)
    th1 = rng.uniform(-0.97, 0.97, n) * half_angle
    th2 = rng.uniform(-0.97, 0.97, n) * half_angle
    n1 = _rot(-axis, th1)  # outward normal at contact 1 faces away from contact 2
    n2 = _rot(axis, th2)
    rho = rng.uniform(0.01, 0.1, n)
    q = ferrari_canny_l1(c1, c2, n1, n2, com, GAMMA, rho[:, None, None])
    assert np.all(q > 0)
    assert np.all(force_closure(c1, c2, n1, n2, GAMMA))
    # sanity: the wrench set has 4 rows of 3 components
    assert contact_wrenches(c1, c2, n1, n2, com, GAMMA, 0.05).shape == (n, 4, 3)


def test_pairs_outside_a_friction_cone_are_not_force_closure() -> None:
    rng = np.random.default_rng(2)
    n = 600
    c1, c2, axis, com = _random_pairs(rng, n)
    half_angle = math.atan(GAMMA)
    sign = rng.choice([-1.0, 1.0], n)
    bad = sign * rng.uniform(1.03, 3.0, n) * half_angle  # outside the cone (up to ~3x its half angle)
    ok = rng.uniform(-1.0, 1.0, n) * half_angle
    first = rng.random(n) < 0.5
    n1 = _rot(-axis, np.where(first, bad, ok))
    n2 = _rot(axis, np.where(first, ok, bad))
    q = ferrari_canny_l1(c1, c2, n1, n2, com, GAMMA, 0.05)
    assert np.all(q <= 0)
    assert not np.any(force_closure(c1, c2, n1, n2, GAMMA))


def test_closed_form_force_closure_equals_sign_of_q() -> None:
    """Nguyen's two-contact test (used for P_F) agrees with Q_F > 0 on arbitrary contact pairs."""
    rng = np.random.default_rng(9)
    n = 5000
    c1 = rng.uniform(-0.05, 0.05, (n, 2))
    c2 = rng.uniform(-0.05, 0.05, (n, 2))
    a1, a2 = rng.uniform(0, 2 * np.pi, (2, n))
    n1 = np.stack([np.cos(a1), np.sin(a1)], axis=1)
    n2 = np.stack([np.cos(a2), np.sin(a2)], axis=1)
    for gamma in (0.2, 0.5, 1.0):
        q = ferrari_canny_l1(c1, c2, n1, n2, np.zeros(2), gamma, 0.05)
        clear = np.abs(q) > 1e-9
        assert np.array_equal(force_closure(c1, c2, n1, n2, gamma)[clear], (q > 0)[clear])
        assert np.count_nonzero(q > 0) >= 30  # both outcomes represented (0.7 % .. 12 % closures)
    assert not force_closure(c1[:1], c1[:1], n1[:1], -n1[:1], GAMMA)[0]  # coincident contacts


def test_quality_invariant_to_translation_and_symmetric_grasps_equal() -> None:
    rng = np.random.default_rng(3)
    c1, c2, axis, com = _random_pairs(rng, 200)
    n1 = _rot(-axis, rng.uniform(-0.3, 0.3, 200))
    n2 = _rot(axis, rng.uniform(-0.3, 0.3, 200))
    shift = np.array([1.7, -0.4])
    q = ferrari_canny_l1(c1, c2, n1, n2, com, GAMMA, 0.05)
    q_shift = ferrari_canny_l1(c1 + shift, c2 + shift, n1, n2, com + shift, GAMMA, 0.05)
    np.testing.assert_allclose(q, q_shift, atol=1e-12)
    # translating the object and the jaws through contact finding on two grids
    sdf = rectangle_sdf(G, tuple(CENTRE), (0.015, 0.01))
    j1, j2 = CENTRE + [-0.044, 0.003], CENTRE + [0.044, 0.003]
    gr = GripperParams()
    base = grasp_quality(find_contacts(SdfBank(sdf, G), j1, j2, gr), CENTRE, gr, 0.01)
    g2 = make_geometry(origin=(0.3, 0.2))
    moved = grasp_quality(find_contacts(SdfBank(rectangle_sdf(g2, tuple(CENTRE + [0.3, 0.2]), (0.015, 0.01)), g2),
                                        j1 + [0.3, 0.2], j2 + [0.3, 0.2], gr), CENTRE + [0.3, 0.2], gr, 0.01)
    assert moved == pytest.approx(base, abs=1e-9)
    # mirror-symmetric grasps on a rectangle (above / below the centre line) score equal
    below = grasp_quality(find_contacts(SdfBank(sdf, G), CENTRE + [-0.044, -0.003], CENTRE + [0.044, -0.003], gr),
                          CENTRE, gr, 0.01)
    assert below == pytest.approx(base, abs=1e-6)
    # rotated diametric grasps on a disc score equal
    disc = SdfBank(disc_sdf(G, tuple(CENTRE), 0.03), G)
    ang = np.linspace(0, np.pi, 7)
    u = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    qd = grasp_quality(find_contacts(disc, CENTRE - 0.044 * u, CENTRE + 0.044 * u, gr), CENTRE, gr, 0.03)
    assert np.ptp(qd) < 5e-3


def test_pf_certain_rectangle_centred_grasp_is_one() -> None:
    post = certain_rectangle_posterior(G)
    samples = draw_shape_samples(post, 1000, np.random.default_rng(0))
    gr = GripperParams()
    j1 = np.array([CENTRE - [0.045, 0], CENTRE - [0, 0.045]])
    j2 = np.array([CENTRE + [0.045, 0], CENTRE + [0, 0.045]])
    est = probability_force_closure(j1, j2, samples, gr, gr.sigma_g)
    assert np.all(est.p >= 0.98)
    # closing at 35° to the face normals (> arctan γ = 26.6°) is never force closure
    u = np.array([math.sin(math.radians(35)), math.cos(math.radians(35))])
    tilted = probability_force_closure((CENTRE - 0.045 * u)[None], (CENTRE + 0.045 * u)[None], samples, gr,
                                       gr.sigma_g)
    assert tilted.p[0] <= 0.05
    # a grasp wider than the gripper always fails
    wide = probability_force_closure(CENTRE[None] - [0.05, 0], CENTRE[None] + [0.05, 0], samples, gr, gr.sigma_g)
    assert wide.p[0] == 0.0 and wide.successes[0] == 0


def test_pf_falls_with_shape_uncertainty() -> None:
    """Same grasp, same rectangle, growing SDF std: P_F drops from ~1 to a low value."""
    mean = rectangle_sdf(G, tuple(CENTRE), (0.015, 0.01))
    gr = GripperParams()
    j1, j2 = (CENTRE - [0, 0.045])[None], (CENTRE + [0, 0.045])[None]
    p = []
    for std_cells in (0.1, 1.0, 2.0, 5.0):
        post = make_posterior(mean, G, std_cells * G.resolution)
        samples = draw_shape_samples(post, 800, np.random.default_rng(4))
        p.append(probability_force_closure(j1, j2, samples, gr, gr.sigma_g).p[0])
    assert p[0] >= 0.98
    assert all(a > b for a, b in zip(p, p[1:], strict=False))
    assert p[-1] <= 0.3


def test_pf_standard_error_shrinks_like_inverse_sqrt() -> None:
    mean = rectangle_sdf(G, tuple(CENTRE), (0.015, 0.01))
    post = make_posterior(mean, G, 1.5 * G.resolution)
    gr = GripperParams()
    j1, j2 = (CENTRE - [0, 0.045])[None], (CENTRE + [0, 0.045])[None]
    rng = np.random.default_rng(5)
    spread = {}
    for n in (50, 800):
        est = [probability_force_closure(j1, j2, draw_shape_samples(post, n, rng), gr, gr.sigma_g)
               for _ in range(24 if n == 50 else 6)]
        p = np.array([e.p[0] for e in est])
        se = np.array([e.std_error[0] for e in est])
        np.testing.assert_allclose(se, np.sqrt(p * (1 - p) / n))
        spread[n] = (p.std(ddof=1), se.mean())
    # reported standard error scales as 1/sqrt(S) (16x samples -> 4x smaller) ...
    assert spread[50][1] / spread[800][1] == pytest.approx(4.0, rel=0.15)
    # ... and matches the empirical spread of independent estimates
    assert spread[50][0] == pytest.approx(spread[50][1], rel=0.4)


def test_vectorised_pf_equals_per_sample_loop() -> None:
    """Same samples, same perturbations: the vectorised estimate equals the straightforward loop."""
    mean = rectangle_sdf(G, tuple(CENTRE), (0.015, 0.01))
    post = make_posterior(mean, G, 1.0 * G.resolution)
    samples = draw_shape_samples(post, 120, np.random.default_rng(6))
    gr = GripperParams()
    rng = np.random.default_rng(7)
    ang = rng.uniform(0, np.pi, 6)
    u = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    j1 = CENTRE - 0.045 * u + rng.normal(0, 0.003, (6, 2))
    j2 = j1 + 0.09 * u
    est = probability_force_closure(j1, j2, samples, gr, gr.sigma_g)
    loop = np.array([pf_python_loop(a, b, samples, gr, gr.sigma_g)[1] for a, b in zip(j1, j2, strict=True)])
    assert np.abs(est.successes - loop).max() <= 1
    assert est.successes.sum() > 0


def test_shape_samples_carry_their_own_centres_of_mass() -> None:
    post = certain_rectangle_posterior(G, std_cells=1.0)
    samples = draw_shape_samples(post, 50, np.random.default_rng(8))
    np.testing.assert_allclose(samples.com, center_of_mass(samples.bank.sdfs, G))
    assert samples.eps.shape == (50, 2, 2)


def test_compiled_grasp_quality_equals_the_numpy_closed_form() -> None:
    """grasp_quality (compiled) == ferrari_canny_l1 (numpy) on random, near-antipodal and degenerate contacts."""
    from gpis_grasp_ros.core.contacts import Contacts

    rng = np.random.default_rng(5)
    shape = (400, 9)
    c1 = rng.normal(0.06, 0.02, shape + (2,))
    c2 = rng.normal(0.06, 0.02, shape + (2,))
    line = (c2 - c1) / np.linalg.norm(c2 - c1, axis=-1, keepdims=True)
    n1 = _rot(-line, rng.normal(0, 0.5, shape))  # around antipodal: about half in force closure
    n2 = _rot(line, rng.normal(0, 0.5, shape))
    valid = rng.random(shape) < 0.9
    n1[0, 0] = np.nan  # non-finite and flat cases
    c2[1, 1] = c1[1, 1]
    con = Contacts(c1=c1, c2=c2, n1=n1, n2=n2, valid=valid, no_contact=~valid, start_inside=np.zeros(shape, bool),
                   opening_exceeded=np.zeros(shape, bool), width=np.zeros(shape), clearance1=np.zeros(shape),
                   clearance2=np.zeros(shape))
    com = rng.normal(0.06, 0.01, (shape[0], 1, 2))
    q = grasp_quality(con, com, GripperParams(friction_coef=GAMMA), 0.03)
    ref = ferrari_canny_l1(c1, c2, n1, n2, com, GAMMA, 0.03)
    ref = np.where(valid & np.isfinite(ref), ref, -np.inf)
    assert 0.2 < np.mean(q > 0) < 0.8
    np.testing.assert_array_equal(np.isneginf(q), np.isneginf(ref))
    fin = np.isfinite(ref)
    np.testing.assert_allclose(q[fin], ref[fin], rtol=0, atol=1e-13)
