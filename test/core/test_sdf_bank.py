"""SdfBank's compiled set-up (padding, finite-difference gradients) against the numpy reference, and the
lazily built coefficient records of the numpy path."""

from __future__ import annotations

import numpy as np
import pytest

from gpis_grasp_ros.core.contacts import find_contacts
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.planners import PlannerParams
from gpis_grasp_ros.core.planners.context import PlanningContext, evaluation_samples
from gpis_grasp_ros.core.quality import force_closure_successes
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
        ref = SdfBank(samples.bank.sdfs, post.geometry)
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
