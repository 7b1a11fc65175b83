"""SdfBank's compiled set-up (padding, finite-difference gradients, Lipschitz bounds, border tests) against the
numpy reference, banks built from sample deviations (float64: bit for bit; float32: the same force-closure
counts), and the lazily built coefficient records of the numpy path."""

from __future__ import annotations

import numpy as np
import pytest

from gpis_grasp_ros.core import contact_kernel
from gpis_grasp_ros.core.contacts import find_contacts
from gpis_grasp_ros.core.gpis import center_of_mass
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.planners import PlannerParams
from gpis_grasp_ros.core.planners.context import PlanningContext, evaluation_samples
from gpis_grasp_ros.core.quality import draw_shape_samples, force_closure_successes
from gpis_grasp_ros.core.sdf_bank import SdfBank, _coefficient_records, pad_extrapolated
from support.synthetic_shapes import disc_sdf, make_geometry


def _random_grids(b: int, h: int, w: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.normal(0.0, 0.01, (b, h, w)) + np.linspace(-0.02, 0.03, w)[None, None]


@pytest.mark.parametrize('shape', [(2, 2), (3, 7), (25, 25), (9, 4)])
@pytest.mark.parametrize('pad', [0, 1, 6])
def test_compiled_set_up_is_bit_identical_to_the_numpy_reference(shape, pad) -> None:
    g = GridGeometry(-0.01, 0.02, 0.0068770665, shape[1], shape[0])
    grids = _random_grids(5, *shape)
    bank = SdfBank(grids, g, pad_cells=pad)
    np.testing.assert_array_equal(bank.padded, pad_extrapolated(grids, pad, g.resolution))
    gy, gx = np.gradient(grids, g.resolution, axis=(1, 2))
    np.testing.assert_array_equal(bank.gradient_grids, np.stack([gx, gy], axis=-1))
    # the lazily built records are those the eager construction built
    rec = _coefficient_records(pad_extrapolated(grids, pad, g.resolution)).view(np.complex128).reshape(-1)
    np.testing.assert_array_equal(bank._coef_rec, rec)
    for k, gc in enumerate((gx, gy)):
        np.testing.assert_array_equal(bank._grad_rec[k], _coefficient_records(gc).view(np.complex128).reshape(-1))


def test_given_gradients_are_kept() -> None:
    g = GridGeometry(0.0, 0.0, 0.005, 6, 5)
    grid = _random_grids(1, 5, 6)[0]
    grad = np.random.default_rng(3).normal(size=(5, 6, 2))
    bank = SdfBank(grid, g, gradients=grad)
    np.testing.assert_array_equal(bank.gradient_grids[0], grad)
    with pytest.raises(ValueError, match='gradients must have shape'):
        SdfBank(grid, g, gradients=grad[:, :3])


def test_monte_carlo_bank_builds_no_records() -> None:
    """The compiled P_F path reads only the float64 grids: no coefficient records are built."""
    g = make_geometry(25, 0.005)
    grids = np.stack([disc_sdf(g, (0.06, 0.06), 0.02 + 0.001 * k) for k in range(8)])
    bank = SdfBank(grids, g)
    ctx_params = PlannerParams()
    find_contacts(bank, np.array([0.01, 0.06]), np.array([0.1, 0.06]), ctx_params.gripper,
                  index=np.arange(8))
    assert bank._records is None
    find_contacts(bank, np.array([0.01, 0.06]), np.array([0.1, 0.06]), ctx_params.gripper,
                  index=np.arange(8), compiled=False)
    assert bank._records is not None


def test_pf_on_shipped_bags_equals_reference_bank() -> None:
    """On every shipped top-down bag, force-closure decisions on the fast bank equal those on a bank whose
    grids come from the numpy reference (padding by fancy indexing, ``np.gradient``)."""
    from support.bag_posteriors import bag_posteriors

    params = PlannerParams(n_shape_samples=200)
    for name, post in bag_posteriors().items():
        ctx = PlanningContext(post, params)
        samples = evaluation_samples(ctx, np.random.default_rng(7))
        ref = SdfBank(samples.bank.sdfs, post.geometry, obstacles=samples.bank.obstacles)
        ref.padded = pad_extrapolated(samples.bank.sdfs, ref.pad, post.geometry.resolution)
        gy, gx = np.gradient(samples.bank.sdfs, post.geometry.resolution, axis=(1, 2))
        ref.gradient_grids = np.stack([gx, gy], axis=-1)
        ref_samples = type(samples)(ref, samples.com, samples.eps, samples.rho)
        rng = np.random.default_rng(11)
        centre = post.center_of_mass()
        theta = rng.uniform(0, np.pi, 16)
        u = np.stack([np.cos(theta), np.sin(theta)], axis=1)
        half = 0.5 * params.gripper.max_opening
        jaw1, jaw2 = centre - half * u, centre + half * u
        fast = force_closure_successes(jaw1, jaw2, samples, params.gripper, ctx.sigma_g)
        slow = force_closure_successes(jaw1, jaw2, ref_samples, params.gripper, ctx.sigma_g)
        np.testing.assert_array_equal(fast, slow, err_msg=name)


def _lipschitz_reference(padded: np.ndarray) -> np.ndarray:
    """The Lipschitz bound as first written: the largest of the 4 corners' rounded squared norms per cell."""
    top = padded[:, :-1, 1:] - padded[:, :-1, :-1]
    bottom = padded[:, 1:, 1:] - padded[:, 1:, :-1]
    left = padded[:, 1:, :-1] - padded[:, :-1, :-1]
    right = padded[:, 1:, 1:] - padded[:, :-1, 1:]
    corners = np.stack([top * top + left * left, top * top + right * right,
                        bottom * bottom + left * left, bottom * bottom + right * right])
    return np.sqrt(np.maximum(corners.max(axis=(0, 2, 3)), 0.0)) * (1.0 + 1e-9)


@pytest.mark.parametrize('shape', [(2, 2), (3, 7), (25, 25), (9, 4)])
@pytest.mark.parametrize('pad', [0, 1, 6])
def test_lipschitz_bounds_and_border_tests_built_with_the_grids(shape, pad) -> None:
    """The set-up pass's Lipschitz bounds equal the four-corner formula bit for bit (over scales 1e-5..10 m),
    and its border test the per-batch reference of the contact kernel."""
    g = GridGeometry(-0.01, 0.02, 0.0068770665, shape[1], shape[0])
    rng = np.random.default_rng(sum(shape) + pad)
    for scale in (1e-5, 1e-3, 1e-2, 10.0):
        grids = rng.normal(0.0, scale, (20,) + shape) + (0.3 * scale if scale < 1 else 0.0)
        bank = SdfBank(grids, g, pad_cells=pad)
        np.testing.assert_array_equal(bank.lipschitz, _lipschitz_reference(bank.padded))
        np.testing.assert_array_equal(bank.lipschitz, contact_kernel.lipschitz_bounds(bank.padded))
        np.testing.assert_array_equal(bank.border_positive, contact_kernel.border_positive(bank.padded))
    positive = SdfBank(np.abs(rng.normal(0.0, 0.01, (3,) + shape)) + 1e-4, g, pad_cells=pad)
    assert positive.border_positive.all()
    corner = np.abs(rng.normal(0.0, 0.01, (3,) + shape)) + 1e-4
    corner[1, -1, -1] = -1.0  # a corner deep inside the object: negative out to the padded grid's border
    assert SdfBank(corner, g, pad_cells=pad).border_positive.tolist() == [True, False, True]


def test_a_bank_from_deviations_is_the_bank_of_mean_plus_deviations() -> None:
    """float64 deviations: the same padded grids, gradients, bounds and border tests as ``SdfBank(mean + dev)``
    (bit for bit); float32 deviations: the same, of their float64 values."""
    g = GridGeometry(-0.01, 0.02, 0.005, 9, 6)
    rng = np.random.default_rng(4)
    mean = rng.normal(0.01, 0.01, g.shape)
    for dtype in (np.float64, np.float32):
        dev = rng.normal(0.0, 0.003, (30, mean.size)).astype(dtype)
        bank = SdfBank.from_deviations(mean, dev, g)
        ref = SdfBank(mean[None] + dev.astype(np.float64).reshape(30, *g.shape), g)
        for name in ('padded', 'gradient_grids', 'lipschitz', 'border_positive', 'sdfs'):
            np.testing.assert_array_equal(getattr(bank, name), getattr(ref, name), err_msg=name)
    with pytest.raises(ValueError, match='do not match the grid'):
        SdfBank.from_deviations(mean, np.zeros((4, 3)), g)


def test_float64_shape_samples_are_the_posterior_samples_and_float32_ones_round_them() -> None:
    """draw_shape_samples(float64) is SdfBank(posterior.sample) on the same stream, with the same perturbation
    draws after it; float32 samples use that stream too and differ from it by the float32 product's rounding."""
    from support.bag_posteriors import bag_posteriors

    post = bag_posteriors()['A_tape_dispenser']
    rng = np.random.default_rng(3)
    ref_sdfs = post.sample(300, rng)
    ref_eps = rng.standard_normal((300, 2, 2))
    a = draw_shape_samples(post, 300, np.random.default_rng(3), precision=np.float64)
    b = draw_shape_samples(post, 300, np.random.default_rng(3), precision=np.float32)
    np.testing.assert_array_equal(a.bank.sdfs, ref_sdfs)
    np.testing.assert_array_equal(a.bank.padded, SdfBank(ref_sdfs, post.geometry).padded)
    np.testing.assert_array_equal(a.eps, ref_eps)
    np.testing.assert_array_equal(b.eps, ref_eps)
    spread = float(np.abs(ref_sdfs - post.mean[None]).max())
    assert 0 < np.abs(b.bank.sdfs - ref_sdfs).max() < 1e-5 * spread  # float32 rounding of the deviations only
    assert a._com is None and b._com is None  # the centres of mass are computed only when asked for
    np.testing.assert_allclose(a.com, center_of_mass(ref_sdfs, post.geometry))


def test_float32_samples_give_the_float64_force_closure_counts_on_every_shipped_bag() -> None:
    """Same seeds, S = 1000, 24 grasps per bag near the centre of mass at random angles: the float32 samples'
    force-closure counts equal the float64 ones (measured: 0 of 1.15 M trials differ over the 16 top-down and
    head bags and 3 seeds, docs/speed.md); allowed here: 1 trial per grasp (a P_F difference of 0.001, far
    inside the Monte-Carlo standard error of up to 0.016 at S = 1000)."""
    from support.bag_posteriors import bag_posteriors

    params = PlannerParams()
    differing = 0
    for name, post in bag_posteriors().items():
        ctx = PlanningContext(post, params)
        rng = np.random.default_rng(11)
        theta = rng.uniform(0, np.pi, 24)
        u = np.stack([np.cos(theta), np.sin(theta)], axis=1)
        centre = post.center_of_mass() + rng.normal(0.0, 0.004, (24, 2))
        half = 0.5 * params.gripper.max_opening
        jaw1, jaw2 = centre - half * u, centre + half * u
        counts = [force_closure_successes(jaw1, jaw2, draw_shape_samples(post, 1000, np.random.default_rng(5),
                                                                         ctx.rho, precision), params.gripper,
                                          ctx.sigma_g) for precision in (np.float64, np.float32)]
        assert np.abs(counts[0] - counts[1]).max() <= 1, name
        assert counts[0].sum() > 0, name
        differing += int(np.abs(counts[0] - counts[1]).sum())
    assert differing <= 2


@pytest.mark.parametrize('shape', [(2, 2), (3, 7), (25, 25)])
@pytest.mark.parametrize('pad', [0, 6])
def test_normals_from_the_values_equal_the_normals_from_the_gradient_grids(shape, pad) -> None:
    """The compiled normals of a finite-difference bank, evaluated at the contacts from the padded values, are
    those interpolated from its gradient grids (``np.gradient``) bit for bit, at random contacts including the
    grid's border, points off it (clamped), NaN contacts and a flat grid (no normal)."""
    g = GridGeometry(-0.01, 0.02, 0.0068770665, shape[1], shape[0])
    grids = _random_grids(6, *shape, seed=9)
    grids[5] = 0.01  # flat: zero gradient everywhere
    bank = SdfBank(grids, g, pad_cells=pad)
    assert not bank.gradients_given
    rng = np.random.default_rng(1)
    t = 400
    c = np.stack([rng.uniform(-1.0, shape[1], (2, t)), rng.uniform(-1.0, shape[0], (2, t))], axis=-1)
    c[:, :40, 0] = rng.choice([0.0, shape[1] - 1.0], (2, 40))  # on the border columns
    c[0, 40:50] = np.nan
    index = rng.integers(0, 6, t).astype(np.intp)
    fast, ref = np.empty((2, t, 2)), np.empty((2, t, 2))
    contact_kernel.unit_normals_from_values(bank.padded, bank.pad, g.resolution, index, c, 1e-6, fast)
    gy, gx = np.gradient(grids, g.resolution, axis=(1, 2))
    contact_kernel.unit_normals(np.stack([gx, gy], axis=-1), index, c, 1e-6, ref)
    np.testing.assert_array_equal(fast, ref)
    assert np.all(fast[:, index == 5] == 0) and np.all(fast[0, 40:50] == 0)
    assert np.all(np.abs(np.linalg.norm(fast[:, index != 5], axis=-1)[:, 50:] - 1) < 1e-12)


@pytest.mark.parametrize('kind', ['lower', 'full', 'tall'])
def test_float32_deviations_of_a_triangular_factor_equal_the_general_product(kind) -> None:
    """A square lower-triangular factor (a full-rank basis' QR triangle) is multiplied by TRMM, any other by
    GEMM: both give L eps on the float64 stream within float32 rounding, and the triangle's upper zeros are
    never read (a NaN put there after detection would show)."""
    from gpis_grasp_ros.core.gpis import KernelParams
    from gpis_grasp_ros.core.gpis.posterior import GpisPosterior

    g = GridGeometry(0.0, 0.0, 0.004, 6, 5)
    n = g.width * g.height
    rng = np.random.default_rng(8)
    factor = {'lower': np.tril(rng.normal(0.0, 1e-3, (n, n))), 'full': rng.normal(0.0, 1e-3, (n, n)),
              'tall': rng.normal(0.0, 1e-3, (n, n - 7))}[kind]
    post = GpisPosterior(g, np.zeros(g.shape), np.ones(g.shape), np.zeros(g.shape + (2,)), factor,
                         KernelParams(1e-4, 0.02, 0.0))
    ref = post.sample_deviations(200, np.random.default_rng(2))
    out = post.sample_deviations(200, np.random.default_rng(2), np.float32)
    assert post._cov_factor_lower == (kind == 'lower')
    assert out.dtype == np.float32 and out.shape == ref.shape and out.flags['C_CONTIGUOUS']
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-6 * np.abs(ref).max())
    if kind == 'lower':
        post._cov_factor_t32[np.triu_indices(n, 1)] = np.nan
        again = post.sample_deviations(200, np.random.default_rng(2), np.float32)
        np.testing.assert_array_equal(again, out)
