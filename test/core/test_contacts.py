"""Contact finding (paper V-B): analytic shapes, jaw width, degenerate cases, batching."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpis_grasp_ros.core.contacts import find_contacts, perturb_grasps
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.core.sdf_bank import SdfBank, bilinear
from support.synthetic_shapes import disc_sdf, make_geometry, rectangle_sdf, union

G = make_geometry()  # 25 x 25, 5 mm cells, corner at the origin
CENTRE = np.array([0.0625, 0.0625])
RES = G.resolution


def _directions(n: int, rng: np.random.Generator) -> np.ndarray:
    th = rng.uniform(0, 2 * np.pi, n)
    return np.stack([np.cos(th), np.sin(th)], axis=1)


def test_gripper_params_units() -> None:
    gr = GripperParams()
    assert gr.sigma_g == pytest.approx(0.003)  # metres, whatever the grid
    assert GripperParams(position_noise=0.001).sigma_g == 0.001
    assert gr.patch_cells(G) == pytest.approx(0.002 / RES)  # the metric patch tolerance in cells of the grid closed on
    for bad in (dict(position_noise=-0.001), dict(position_noise=math.nan), dict(contact_patch=0.0)):
        with pytest.raises(ValueError):
            GripperParams(**bad)
    assert gr.beta == pytest.approx(1 / math.sqrt(1 + 0.25))
    off = gr.face_offsets(G)
    assert off[0] == pytest.approx(-0.005) and off[-1] == pytest.approx(0.005)
    assert np.max(np.diff(off)) <= 0.25 * RES + 1e-12  # lines at most a quarter cell apart
    with pytest.raises(ValueError):
        GripperParams(max_opening=0.0)


def test_disc_contacts_on_boundary_subcell() -> None:
    """A single-line jaw lands on an exact disc SDF within a few hundredths of a cell."""
    radius = 0.03
    bank = SdfBank(disc_sdf(G, tuple(CENTRE), radius), G)
    rng = np.random.default_rng(0)
    u = _directions(500, rng)
    perp = np.stack([-u[:, 1], u[:, 0]], axis=1)
    off = rng.uniform(-0.02, 0.02, (500, 1)) * perp
    thin = GripperParams(jaw_width=0.0)
    con = find_contacts(bank, CENTRE - 0.045 * u + off, CENTRE + 0.045 * u + off, thin)
    assert con.valid.all()
    for c in (con.c1, con.c2):
        r = np.linalg.norm(c - CENTRE, axis=1)
        assert np.max(np.abs(r - radius)) < 0.03 * RES
    # normals point outward, along the radius
    radial = (con.c1 - CENTRE) / np.linalg.norm(con.c1 - CENTRE, axis=1, keepdims=True)
    assert np.min(np.sum(con.n1 * radial, axis=1)) > 0.999
    # jaw 1 touches the side facing it
    assert np.all(np.sum((con.c1 - CENTRE) * u, axis=1) < 0)
    # a wide jaw still lands on the surface to sub-cell accuracy (contact-patch centre)
    wide = find_contacts(bank, CENTRE - 0.045 * u, CENTRE + 0.045 * u, GripperParams())
    assert np.max(np.abs(np.linalg.norm(wide.c1 - CENTRE, axis=1) - radius)) < 0.1 * RES


def test_rectangle_faces_and_normals() -> None:
    half = (0.015, 0.01)
    bank = SdfBank(rectangle_sdf(G, tuple(CENTRE), half), G)
    ys = np.linspace(-0.004, 0.004, 7)  # the whole 1 cm jaw face stays on the 2 cm face
    j1 = np.stack([np.full(7, CENTRE[0] - 0.04), CENTRE[1] + ys], axis=1)
    j2 = j1 + [0.08, 0.0]
    con = find_contacts(bank, j1, j2, GripperParams())
    assert con.valid.all()
    np.testing.assert_allclose(con.c1[:, 0], CENTRE[0] - half[0], atol=0.02 * RES)
    np.testing.assert_allclose(con.c2[:, 0], CENTRE[0] + half[0], atol=0.02 * RES)
    np.testing.assert_allclose(con.c1[:, 1], j1[:, 1], atol=1e-9)  # flat face: patch centre on the axis
    np.testing.assert_allclose(con.n1, np.tile([-1.0, 0.0], (7, 1)), atol=1e-6)
    np.testing.assert_allclose(con.n2, np.tile([1.0, 0.0], (7, 1)), atol=1e-6)
    np.testing.assert_allclose(con.clearance1, 0.04 - half[0], atol=1e-6)


def test_jaw_width_catches_thin_spike() -> None:
    """A spike beside the closing axis is missed by a point jaw but caught by a 1 cm jaw."""
    body = rectangle_sdf(G, tuple(CENTRE), (0.01, 0.01))
    spike_y = CENTRE[1] + 0.0055  # spans 2.5..8.5 mm off the axis: beside a point jaw, under a 1 cm jaw
    spike = rectangle_sdf(G, (CENTRE[0] - 0.016, spike_y), (0.007, 0.003))
    bank = SdfBank(union(body, spike), G)
    j1 = CENTRE - [0.044, 0.0]
    j2 = CENTRE + [0.044, 0.0]
    point = find_contacts(bank, j1, j2, GripperParams(jaw_width=0.0))
    wide = find_contacts(bank, j1, j2, GripperParams(jaw_width=0.01))
    assert point.c1[0] == pytest.approx(CENTRE[0] - 0.01, abs=0.05 * RES)  # body face
    # spike tip (the patch of lines touching within half a cell of the first touch sits on the
    # bilinearly rounded tip, a fraction of a cell behind its corner)
    assert wide.c1[0] == pytest.approx(CENTRE[0] - 0.023, abs=0.2 * RES)
    assert wide.c1[1] == pytest.approx(spike_y, abs=0.5 * RES)
    assert wide.c2[0] == pytest.approx(CENTRE[0] + 0.01, abs=0.05 * RES)  # other side: body face


def test_degenerate_cases_flagged() -> None:
    bank = SdfBank(disc_sdf(G, tuple(CENTRE), 0.02), G)
    gr = GripperParams()
    # jaws pass beside the object
    miss = find_contacts(bank, CENTRE + [-0.04, 0.035], CENTRE + [0.04, 0.035], gr)
    assert miss.no_contact and not miss.valid and np.all(np.isnan(miss.c1))
    # jaw 1 starts inside
    inside = find_contacts(bank, CENTRE + [-0.01, 0.0], CENTRE + [0.05, 0.0], gr)
    assert inside.start_inside and not inside.valid
    # opening exceeded (only when checked)
    wide = find_contacts(bank, CENTRE - [0.05, 0.0], CENTRE + [0.05, 0.0], gr)
    assert wide.opening_exceeded and not wide.valid and not wide.no_contact
    unchecked = find_contacts(bank, CENTRE - [0.05, 0.0], CENTRE + [0.05, 0.0], gr, check_opening=False)
    assert unchecked.valid


def test_jaws_off_grid_and_translation() -> None:
    """Jaws may start off the grid; shifting object and jaws by whole cells shifts the contacts."""
    bank = SdfBank(disc_sdf(G, (0.035, 0.0625), 0.02), G)
    j1, j2 = np.array([-0.01, 0.0625]), np.array([0.08, 0.0625])  # jaw 1 two cells off the grid
    con = find_contacts(bank, j1, j2, GripperParams())
    assert con.valid
    assert con.c1[0] == pytest.approx(0.015, abs=0.1 * RES)
    g2 = GridGeometry(0.1, -0.2, RES, 25, 25)
    shift = np.array([0.1, -0.2])
    bank2 = SdfBank(disc_sdf(g2, (0.035 + 0.1, 0.0625 - 0.2), 0.02), g2)
    con2 = find_contacts(bank2, j1 + shift, j2 + shift, GripperParams())
    np.testing.assert_allclose(con2.c1, con.c1 + shift, atol=1e-9)
    np.testing.assert_allclose(con2.n1, con.n1, atol=1e-6)
    # far off-grid (beyond the padding) uses the clamped path and still works
    far = find_contacts(bank, np.array([-0.045, 0.0625]), np.array([0.06, 0.0625]), GripperParams(max_opening=0.11))
    assert far.valid and far.c1[0] == pytest.approx(0.015, abs=0.1 * RES)


def test_batched_samples_match_single_evaluation() -> None:
    """(G, S) batches with a per-trial grid index equal one-by-one evaluation."""
    rng = np.random.default_rng(3)
    grids = np.stack([disc_sdf(G, tuple(CENTRE + rng.normal(0, 0.003, 2)), r) for r in (0.02, 0.025, 0.03)])
    bank = SdfBank(grids, G)
    u = _directions(4, rng)
    j1 = (CENTRE - 0.044 * u)[:, None, :]
    j2 = (CENTRE + 0.044 * u)[:, None, :]
    idx = np.arange(3)[None, :]
    con = find_contacts(bank, j1, j2, GripperParams(), index=idx)
    assert con.c1.shape == (4, 3, 2) and con.valid.shape == (4, 3)
    for gi in range(4):
        for s in range(3):
            single = find_contacts(SdfBank(grids[s], G), j1[gi, 0], j2[gi, 0], GripperParams())
            np.testing.assert_allclose(con.c1[gi, s], single.c1, atol=1e-9)
            np.testing.assert_allclose(con.n2[gi, s], single.n2, atol=1e-9)


def test_sample_normals_from_finite_differences() -> None:
    """Default bank normals come from the grid itself (what MC samples need), analytic gradient optional."""
    sdf = disc_sdf(G, tuple(CENTRE), 0.03)
    pts = CENTRE + 0.03 * _directions(50, np.random.default_rng(1))
    radial = (pts - CENTRE) / 0.03
    fd = SdfBank(sdf, G).normals_at(pts)
    assert np.min(np.sum(fd * radial, axis=1)) > 0.995
    wrong = np.zeros(G.shape + (2,))
    wrong[..., 1] = 1.0
    np.testing.assert_allclose(SdfBank(sdf, G, gradients=wrong).normals_at(pts), np.tile([0, 1.0], (50, 1)))
    np.testing.assert_allclose(bilinear(sdf, G, pts), 0.0, atol=0.05 * RES)


def test_perturbation_model() -> None:
    """ĝ1 ~ N(g1, σ² I) and ĝ2 − ĝ1 ~ N(g2 − g1, σ² I) (paper V-B)."""
    rng = np.random.default_rng(7)
    eps = rng.standard_normal((200000, 2, 2))
    g1, g2 = np.array([0.01, 0.02]), np.array([0.08, 0.03])
    p1, p2 = perturb_grasps(g1, g2, eps, 0.002)
    np.testing.assert_allclose(p1.mean(axis=0), g1, atol=3e-5)
    np.testing.assert_allclose(np.cov(p1.T), 0.002 ** 2 * np.eye(2), atol=2e-7)
    d = p2 - p1 - (g2 - g1)
    np.testing.assert_allclose(d.mean(axis=0), 0.0, atol=3e-5)
    np.testing.assert_allclose(np.cov(d.T), 0.002 ** 2 * np.eye(2), atol=2e-7)


def test_vanishing_gradient_gives_an_invalid_contact_not_an_antipodal_normal() -> None:
    """A contact where the SDF gradient vanishes has no normal: flagged ``no_normal``, NaN n, invalid."""
    sdf = rectangle_sdf(G, tuple(CENTRE), (0.015, 0.01))
    zero = np.zeros(G.shape + (2,))
    bank = SdfBank(sdf, G, gradients=zero)  # e.g. a posterior whose gradient is flat
    con = find_contacts(bank, CENTRE - [0.045, 0], CENTRE + [0.045, 0], GripperParams())
    assert not con.valid and con.no_normal and not con.no_contact
    assert np.all(np.isnan(con.n1)) and np.all(np.isnan(con.n2))
    assert np.all(np.isfinite(con.c1))  # the contact point itself is known
    # a gradient vanishing only at jaw 2's side invalidates the grasp too
    grad = np.stack(np.gradient(sdf, RES, axis=(1, 0)), axis=-1)
    grad[:, 13:] = 0.0
    con = find_contacts(SdfBank(sdf, G, gradients=grad), CENTRE - [0.045, 0], CENTRE + [0.045, 0], GripperParams())
    assert not con.valid and con.no_normal and np.all(np.isfinite(con.n1)) and np.all(np.isnan(con.n2))
    ok = find_contacts(SdfBank(sdf, G), CENTRE - [0.045, 0], CENTRE + [0.045, 0], GripperParams())
    assert ok.valid and not ok.no_normal


def test_empty_batch() -> None:
    bank = SdfBank(rectangle_sdf(G, tuple(CENTRE), (0.015, 0.01)), G)
    con = find_contacts(bank, np.zeros((0, 2)), np.zeros((0, 2)), GripperParams())
    assert con.valid.shape == (0,) and con.c1.shape == (0, 2)


def _dense_first_crossing(bank: SdfBank, a: np.ndarray, b: np.ndarray, step: float = 0.002) -> np.ndarray:
    """Reference: first f <= 0 along a -> b (cells) by dense sampling, (T,) distance in cells (NaN: none)."""
    d = b - a
    length = np.linalg.norm(d, axis=1)
    t = np.arange(0.0, length.max() + step, step)
    pts = a[:, None] + np.minimum(t[None], length[:, None])[..., None] * (d / length[:, None])[:, None]
    f = bank.values_cells(pts[..., 0], pts[..., 1])
    neg = f <= 0
    return np.where(neg.any(axis=1), t[np.argmax(neg, axis=1)], np.nan)


@pytest.mark.parametrize('seed', [0, 1])
def test_exact_crossings_find_slivers_a_march_steps_over(seed: int) -> None:
    """Exact crossings of the bilinear SDF: equal to dense sampling, independent of the march step.

    A rough random field (a GP-sample-like SDF with thin negative slivers) and random single-line
    jaws: the exact contact is where dense sampling (0.002 cell) first sees f <= 0, and a sampled
    march with a 1-cell step misses some of those crossings.
    """
    rng = np.random.default_rng(seed)
    base = rectangle_sdf(G, tuple(CENTRE), (0.02, 0.004))
    sdf = base + 0.004 * rng.standard_normal(G.shape)
    bank = SdfBank(sdf, G)
    u = _directions(400, rng)
    off = rng.uniform(-0.03, 0.03, (400, 1)) * np.stack([-u[:, 1], u[:, 0]], axis=1)
    j1, j2 = CENTRE - 0.045 * u + off, CENTRE + 0.045 * u + off
    thin = GripperParams(jaw_width=0.0)
    exact = find_contacts(bank, j1, j2, thin)
    ref = _dense_first_crossing(bank, G.to_cell(j1), G.to_cell(j2))
    ok = exact.valid
    out = ~exact.start_inside
    assert ok.sum() > 100 and np.array_equal(~exact.no_contact[out], np.isfinite(ref[out]))
    got = np.linalg.norm(G.to_cell(exact.c1[ok]) - G.to_cell(j1[ok]), axis=1)
    assert np.max(np.abs(got - ref[ok])) < 0.005  # cells
    assert np.max(np.abs(bank.values(exact.c1[ok]))) < 1e-6  # on the zero level set (m)
    # the march step is irrelevant for the exact method, but a 1-cell sampled march misses slivers
    coarse = find_contacts(bank, j1, j2, GripperParams(jaw_width=0.0, march_step_cells=2.0))
    np.testing.assert_allclose(coarse.c1[ok], exact.c1[ok], atol=1e-9)
    sampled = find_contacts(bank, j1, j2, GripperParams(jaw_width=0.0, exact_crossings=False))
    both = ok & sampled.valid
    moved = np.linalg.norm(sampled.c1[both] - exact.c1[both], axis=1) > 0.1 * RES
    assert moved.any()


def test_a_trials_contacts_do_not_depend_on_the_batch() -> None:
    """Trials on the grid get the same exact contacts whether or not the batch holds far off-grid jaws."""
    bank = SdfBank(rectangle_sdf(G, tuple(CENTRE), (0.015, 0.01), angle=0.3), G)
    rng = np.random.default_rng(3)
    u = _directions(50, rng)
    j1, j2 = CENTRE - 0.045 * u, CENTRE + 0.045 * u
    alone = find_contacts(bank, j1, j2, GripperParams())
    far = np.array([[-0.5, -0.5]])  # 100 cells off the grid
    mixed = find_contacts(bank, np.concatenate([j1, far]), np.concatenate([j2, far + [0.09, 0.0]]), GripperParams())
    np.testing.assert_array_equal(mixed.c1[:50], alone.c1)
    np.testing.assert_array_equal(mixed.n2[:50], alone.n2)
    assert mixed.no_contact[50]
