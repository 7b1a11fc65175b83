"""The compiled eq. 6 batch (core.objective_kernel) against its numpy reference
(MeanGraspObjective.details_reference): bit for bit on analytic shapes, with obstacles, with finite-difference
normals, on random and degenerate jaws, and the planners' results with either path."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from gpis_grasp_ros.core.planners import PlannerParams, PlanningContext, plan, sample_valid_grasps
from gpis_grasp_ros.core.planners.objective import MeanGraspObjective
from support.synthetic_shapes import (
    disc_sdf,
    make_geometry,
    make_posterior,
    rectangle_sdf,
    transparent_part_posterior,
)

PARAMS = PlannerParams()
KEYS = ('objective', 'constraints', 'pf_smoothed', 'uncertainty', 'q_nominal', 'valid_nominal')


def _posteriors() -> dict[str, object]:
    post, _ = transparent_part_posterior()
    g = make_geometry(40, 0.003, origin=(-0.06, 0.02))
    disc = make_posterior(disc_sdf(g, (0.0, 0.08), 0.025), g, 0.2 * g.resolution)
    gs = make_geometry(25, 0.0015)  # a 37.5 mm grid: the 90 mm opening reaches far beyond it
    small = make_posterior(disc_sdf(gs, (0.019, 0.018), 0.01), gs, 0.1 * gs.resolution)
    bar = make_posterior(rectangle_sdf(g, (-0.01, 0.08), (0.03, 0.006), angle=0.4), g, 0.5 * g.resolution)
    return {
        'transparent part': post,
        'disc': disc,
        'disc, finite-difference normals': replace(disc, gradient=None),
        'bar beside a box (obstacle)': replace(bar, obstacles=rectangle_sdf(g, (-0.01, 0.1), (0.02, 0.005))),
        'small disc (lines leave the grid)': small,
    }


POSTERIORS = _posteriors()


def _jaws(ctx: PlanningContext, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Valid grasps on the mean, the same moved at random, random pairs over (and beyond) the grid, and
    degenerate cases: coincident jaws, an opening wider than w_g, jaws far away."""
    g = ctx.geometry
    j1, j2 = sample_valid_grasps(ctx, n, rng)
    lo = np.array([g.origin_x, g.origin_y]) - 0.02
    hi = lo + np.array(g.size_m) + 0.04
    r1, r2 = rng.uniform(lo, hi, (n, 2)), rng.uniform(lo, hi, (n, 2))
    moved1, moved2 = j1 + rng.normal(0.0, 0.004, j1.shape), j2 + rng.normal(0.0, 0.004, j2.shape)
    centre = 0.5 * (lo + hi)
    special1 = np.array([centre, centre - [0.06, 0.0], lo - 0.5, centre])
    special2 = np.array([centre, centre + [0.06, 0.0], lo - 0.4, centre + [1e-14, 0.0]])
    return (np.concatenate([j1, moved1, r1, special1]), np.concatenate([j2, moved2, r2, special2]))


@pytest.mark.parametrize('name', list(POSTERIORS))
@pytest.mark.parametrize('antipodal', [True, False])
def test_compiled_batch_equals_the_numpy_reference_bit_for_bit(name: str, antipodal: bool) -> None:
    ctx = PlanningContext(POSTERIORS[name], PARAMS)
    rng = np.random.default_rng(3)
    eps = rng.standard_normal((PARAMS.n_perturbations, 2, 2))
    j1, j2 = _jaws(ctx, rng, 60)
    x = MeanGraspObjective.variables(j1, j2)
    fast = MeanGraspObjective(ctx, eps, PARAMS.uncertainty_penalty, antipodal)
    ref = MeanGraspObjective(ctx, eps, PARAMS.uncertainty_penalty, antipodal, compiled=False)
    assert fast.compiled and not ref.compiled
    a, b = fast.details(x), ref.details(x)
    for key in KEYS:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key, strict=True)
    assert fast.trials == ref.trials == x.shape[0] * (PARAMS.n_perturbations + 1)
    # the cases the test means to cover occur: invalid trials, a failed nominal grasp, feasible points
    assert np.isneginf(a['q_nominal']).any() and not a['valid_nominal'].all()
    assert (a['constraints'].max(axis=1) <= 0).any()
    # one point at a time gives the same values (each row depends on its own point only)
    one = fast.details(x[:5])
    for k in range(5):
        row = fast.details(x[k])
        for key in KEYS:
            np.testing.assert_array_equal(row[key][0], one[key][k], err_msg=key)


def test_obstacle_contacts_are_flagged_by_the_compiled_batch() -> None:
    """On the bar beside a box some nominal grasps touch the box: invalid on both paths alike."""
    post = POSTERIORS['bar beside a box (obstacle)']
    ctx = PlanningContext(post, PARAMS)
    # closing across the bar and the box lying above it: jaw 2 meets the box first
    xs = np.linspace(-0.03, 0.01, 9)
    j1 = np.stack([xs, np.full(9, 0.05)], axis=1)
    j2 = np.stack([xs, np.full(9, 0.125)], axis=1)
    x = MeanGraspObjective.variables(j1, j2)
    eps = np.zeros((0, 2, 2))
    fast = MeanGraspObjective(ctx, eps, 0.0, True).details(x)
    ref = MeanGraspObjective(ctx, eps, 0.0, True, compiled=False).details(x)
    for key in KEYS:
        np.testing.assert_array_equal(fast[key], ref[key], err_msg=key)
    assert not fast['valid_nominal'].any()
    free = PlanningContext(replace(post, obstacles=None), PARAMS)  # without the box the same grasps hold the bar
    assert MeanGraspObjective(free, eps, 0.0, True).details(x)['valid_nominal'].all()


def test_empty_batch() -> None:
    ctx = PlanningContext(POSTERIORS['disc'], PARAMS)
    eps = np.random.default_rng(0).standard_normal((4, 2, 2))
    d = MeanGraspObjective(ctx, eps, 1.0, True).details(np.zeros((0, 4)))
    assert d['objective'].shape == (0,) and d['constraints'].shape == (0, 6)


@pytest.mark.parametrize('method', ['gp-gpis-opt', 'gp-d'])
def test_planners_plan_the_same_on_either_path(method: str, monkeypatch: pytest.MonkeyPatch) -> None:
    post = POSTERIORS['transparent part']
    fast = plan(method, post, PARAMS, seed=4)
    monkeypatch.setattr(MeanGraspObjective, 'details', MeanGraspObjective.details_reference)
    ref = plan(method, post, PARAMS, seed=4)
    np.testing.assert_array_equal(fast.jaw1, ref.jaw1)
    np.testing.assert_array_equal(fast.jaw2, ref.jaw2)
    assert fast.p_f == ref.p_f and fast.objective == ref.objective
    for a, b in zip(fast.restarts, ref.restarts, strict=True):
        np.testing.assert_array_equal(a.objective_history, b.objective_history)
