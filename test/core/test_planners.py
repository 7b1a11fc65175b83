"""Grasp planners (paper VI, VII-B) on synthetic GPIS posteriors with a "transparent" uncertain part."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpis_grasp_ros.core.contacts import find_contacts
from gpis_grasp_ros.core.gpis import GpisPosterior, KernelParams
from gpis_grasp_ros.core.planners import (
    METHODS,
    GraspResult,
    PlannerParams,
    PlanningContext,
    plan,
    sample_heuristic_grasps,
    sample_valid_grasps,
)
from gpis_grasp_ros.core.planners.objective import MeanGraspObjective
from gpis_grasp_ros.core.quality import draw_shape_samples, probability_force_closure
from gpis_grasp_ros.core.sdf_bank import SdfBank, bilinear
from support.synthetic_shapes import (
    certain_rectangle_posterior,
    gradient_of,
    make_geometry,
    make_posterior,
    rectangle_sdf,
    smooth_region_weight,
    transparent_part_posterior,
)

POST, UNCERTAIN = transparent_part_posterior()
PARAMS = PlannerParams()


@pytest.fixture(scope='module')
def results() -> dict[str, GraspResult]:
    return {m: plan(m, POST, PARAMS, seed=11) for m in ('gp-m', 'gp-p', 'gp-gpis-opt', 'gp-gpis-opt-reranked')}


def _contact_variance_cells(res: GraspResult) -> np.ndarray:
    bank = SdfBank(POST.mean, POST.geometry, gradients=POST.gradient)
    con = find_contacts(bank, res.jaw1, res.jaw2, PARAMS.gripper)
    pts = np.stack([con.c1, con.c2])
    return bilinear(POST.variance, POST.geometry, pts) / POST.geometry.resolution ** 2


def test_uncertainty_aware_planners_beat_gp_m(results: dict[str, GraspResult]) -> None:
    """GP-G and GP-P avoid the transparent part and reach a higher P_F than GP-M (Table I, Fig. 4)."""
    m, p, g = results['gp-m'], results['gp-p'], results['gp-gpis-opt']
    assert np.max(_contact_variance_cells(m)) > 1.0  # GP-M grasps the (uncertain) transparent part
    for r in (p, g):
        assert np.max(_contact_variance_cells(r)) < 0.1  # both contacts on the well-observed body
    assert p.p_f > m.p_f + 0.2 and p.p_f >= 0.8
    # GP-G maximises eq. 6 (P̃_F on the mean shape minus λσ² at the nominal contacts); run to
    # convergence its optimum need not be the P_F optimum (shape uncertainty next to the contacts
    # is not in eq. 6): on this scene (seed 11) it still clearly beats GP-M (0.68 vs 0.54; other seeds
    # 0.80-0.92), and re-ranking its optima by P_F is never worse.
    assert g.p_f > m.p_f + 0.1 and g.p_f >= 0.65
    assert results['gp-gpis-opt-reranked'].p_f >= g.p_f - 0.01


def test_gp_g_satisfies_antipodal_constraints(results: dict[str, GraspResult]) -> None:
    r = results['gp-gpis-opt']
    assert r.success and r.feasible
    bank = SdfBank(POST.mean, POST.geometry, gradients=POST.gradient)
    con = find_contacts(bank, r.jaw1, r.jaw2, PARAMS.gripper)
    assert con.valid
    v = (r.jaw1 - r.jaw2) / np.linalg.norm(r.jaw1 - r.jaw2)
    tol = PARAMS.constraint_tol
    assert np.sum((con.n1 + con.n2) ** 2) <= PARAMS.antipodal_alpha + tol
    assert con.n1 @ v >= PARAMS.beta - tol
    assert -con.n2 @ v >= PARAMS.beta - tol
    assert r.width <= PARAMS.gripper.max_opening + 1e-12
    assert min(con.clearance1, con.clearance2) >= -tol * POST.geometry.resolution
    assert r.iterations > 0 and len(r.restarts) == PARAMS.n_initial_grasps
    assert max(x.objective for x in r.restarts if x.feasible) == pytest.approx(r.objective)


def test_results_fully_filled(results: dict[str, GraspResult]) -> None:
    for name, r in results.items():
        assert r.method == name and r.success and r.message == 'ok'
        for arr in (r.jaw1, r.jaw2, r.center, r.axis):
            assert arr.shape == (2,) and np.all(np.isfinite(arr))
        assert np.linalg.norm(r.axis) == pytest.approx(1.0)
        np.testing.assert_allclose(r.jaw1 + r.width * r.axis, r.jaw2, atol=1e-12)
        np.testing.assert_allclose(r.center, 0.5 * (r.jaw1 + r.jaw2))
        assert 0.0 <= r.p_f <= 1.0 and r.p_f_std_error == pytest.approx(math.sqrt(r.p_f * (1 - r.p_f) / 1000))
        assert np.isfinite(r.q_mean) and np.isfinite(r.objective)
        assert r.planning_time > 0 and r.evaluation_time > 0 and r.seed == 11
    assert results['gp-m'].objective == pytest.approx(results['gp-m'].q_mean)
    rer = results['gp-gpis-opt-reranked']
    assert rer.objective == pytest.approx(max(x.p_f for x in rer.restarts))


def test_same_seed_same_grasp_and_common_evaluation() -> None:
    params = PlannerParams(n_shape_samples=200, n_grasp_samples=200, n_initial_grasps=6)
    for method in ('gp-gpis-opt', 'gp-p', 'gp-m', 'gp-u'):
        a = plan(method, POST, params, seed=3)
        b = plan(method, POST, params, seed=3)
        np.testing.assert_array_equal(a.jaw1, b.jaw1)
        np.testing.assert_array_equal(a.jaw2, b.jaw2)
        assert a.p_f == b.p_f
    c = plan('gp-m', POST, params, seed=4)
    assert not np.array_equal(c.jaw1, plan('gp-m', POST, params, seed=3).jaw1)
    # params.seed is used when no seed is passed
    seeded = PlannerParams(n_shape_samples=200, n_grasp_samples=200, seed=3)
    np.testing.assert_array_equal(plan('gp-m', POST, seeded).jaw1, plan('gp-m', POST, params, seed=3).jaw1)


def test_gp_d_and_gp_u_multi_start_and_single_start_extras() -> None:
    params = PlannerParams(n_shape_samples=200, n_initial_grasps=8)
    for method, starts in (('gp-d', 8), ('gp-u', 8), ('gp-d-single', 1), ('gp-u-single', 1)):
        r = plan(method, POST, params, seed=5)
        assert r.method == method and len(r.restarts) == starts
        assert r.iterations >= 1 and np.isfinite(r.objective)
        assert r.width <= params.gripper.max_opening + 1e-12
    # on a certain rectangle the local optimiser reaches force closure
    rect = certain_rectangle_posterior()
    r = plan('gp-d', rect, params, seed=1)
    assert r.success and r.p_f > 0.9 and r.objective > 0.9


def test_dispatcher_names() -> None:
    params = PlannerParams(n_shape_samples=50, n_grasp_samples=50, n_initial_grasps=2)
    assert plan('gp-m', POST, params, seed=1).method == 'gp-m'
    for wrong in ('gp-x', 'gp-g', 'GP-M'):  # canonical names only
        with pytest.raises(ValueError) as err:
            plan(wrong, POST, params)
        for name in METHODS:
            assert name in str(err.value)


def test_heuristic_sampler_geometry() -> None:
    ctx = PlanningContext(POST, PARAMS)
    j1, j2 = sample_heuristic_grasps(ctx, 400, np.random.default_rng(0))
    width = np.linalg.norm(j2 - j1, axis=1)
    np.testing.assert_allclose(width, PARAMS.gripper.max_opening)
    # the grasp line is centred on the interior chord of the mean shape along it
    u = (j2 - j1) / width[:, None]
    centre = 0.5 * (j1 + j2)
    t = np.linspace(-0.08, 0.08, 641)
    vals = ctx.mean_bank.values(centre[:, None, :] + t[None, :, None] * u[:, None, :])
    neg = vals < 0
    assert neg.any(axis=1).all()
    lo = t[np.argmax(neg, axis=1)]
    hi = t[len(t) - 1 - np.argmax(neg[:, ::-1], axis=1)]
    assert np.max(np.abs(lo + hi)) < 2 * 0.25 * 0.005 + 1e-9
    # valid initial grasps are valid on the mean shape and diverse
    v1, v2 = sample_valid_grasps(ctx, 20, np.random.default_rng(1))
    assert v1.shape == (20, 2) and find_contacts(ctx.mean_bank, v1, v2, PARAMS.gripper).valid.all()
    assert len({tuple(np.round(a, 6)) for a in v1}) == 20


def test_no_valid_grasp_reports_failure() -> None:
    g = make_geometry()
    big = make_posterior(rectangle_sdf(g, (0.0625, 0.0625), (0.055, 0.055)), g, 0.0005)  # wider than w_g
    params = PlannerParams(n_shape_samples=50, n_grasp_samples=100, n_initial_grasps=4, max_sampling_rounds=2)
    for method in ('gp-gpis-opt', 'gp-m'):
        r = plan(method, big, params, seed=0)
        assert not r.success and r.message and np.all(np.isnan(r.jaw1)) and r.p_f == 0.0


def test_no_feasible_restart_is_reported_by_both_gp_g_variants() -> None:
    """β > 1 cannot be met: GP-G and its re-ranked variant say so (and do not claim feasibility)."""
    params = PlannerParams(n_shape_samples=100, n_initial_grasps=4, antipodal_beta=1.5, max_scp_iterations=20)
    for method in ('gp-gpis-opt', 'gp-gpis-opt-reranked'):
        r = plan(method, POST, params, seed=2)
        assert not r.feasible and not any(x.feasible for x in r.restarts)
        assert 'no restart satisfied all constraints' in r.message


@pytest.mark.parametrize('lam', [-0.5, float('nan'), float('inf')])
def test_uncertainty_penalty_must_be_finite_and_non_negative(lam: float) -> None:
    """λ of eq. 4/6 weighs a penalty: a negative λ would reward variance, NaN / ∞ have no meaning."""
    with pytest.raises(ValueError, match='uncertainty penalty'):
        PlannerParams(uncertainty_penalty=lam)
    assert PlannerParams(uncertainty_penalty=0.0).uncertainty_penalty == 0.0


def _kron_factor(geometry, length_scale: float) -> np.ndarray:
    """Factor F (H*W, r) with F Fᵀ ≈ SE correlation over the cell centres, from the 1-D factors (separable)."""
    def axis_factor(n: int) -> np.ndarray:
        x = (np.arange(n) + 0.5) * geometry.resolution
        lam, vec = np.linalg.eigh(np.exp(-0.5 * (x[:, None] - x[None, :]) ** 2 / length_scale ** 2))
        keep = lam > 1e-9 * lam.max()
        return vec[:, keep] * np.sqrt(lam[keep])

    return np.kron(axis_factor(geometry.height), axis_factor(geometry.width))


def _metric_transparent_scene(m: int):
    """The transparent-part scene of ``transparent_part_posterior`` on an M x M grid over the same 12.5 cm: every
    length (shape, std 0.5 mm / 15 mm, correlation length 15 mm, blend width) in metres, so only M changes."""
    g = make_geometry(n=m, resolution=0.125 / m)
    body = rectangle_sdf(g, (0.040, 0.0625), (0.012, 0.008))
    part = rectangle_sdf(g, (0.078, 0.0625), (0.028, 0.030))
    weight = smooth_region_weight(part - 0.002, 0.01) * (body > 0.004)
    std = 0.0005 + (0.015 - 0.0005) * weight
    factor = std.reshape(-1, 1) * _kron_factor(g, 0.015)
    mean = np.minimum(body, part)
    return GpisPosterior(geometry=g, mean=mean, variance=np.sum(factor ** 2, axis=1).reshape(g.shape),
                         gradient=gradient_of(mean, g), cov_factor=factor,
                         params=KernelParams(signal_variance=0.015 ** 2, length_scale=0.015, prior_mean=-0.005))


def test_eq6_and_pf_do_not_depend_on_the_grid_resolution() -> None:
    """λ per m² of SDF variance, σ_g and every SCP length in metres: the same physical scene on M = 25, 50, 100
    gives the same eq. 6 terms and the same P_F for the same grasps, up to the grid's discretisation and the
    Monte-Carlo error (S = 400: std ≤ 0.025 per estimate). With λ per cell² the penalty grew as M²."""
    rng = np.random.default_rng(0)
    centre = np.array([0.040, 0.0625]) + rng.uniform(-0.006, 0.006, (40, 2))
    angle = rng.uniform(-0.5, 0.5, 40) + np.pi / 2 * (rng.uniform(size=40) < 0.5)
    axis = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    j1, j2 = centre - 0.04 * axis, centre + 0.04 * axis
    params = PlannerParams()
    terms = []
    for m in (25, 50, 100):
        ctx = PlanningContext(_metric_transparent_scene(m), params)
        eps = np.random.default_rng(1).standard_normal((params.n_perturbations, 2, 2))
        d = MeanGraspObjective(ctx, eps, params.uncertainty_penalty, True).details(
            MeanGraspObjective.variables(j1, j2))
        pf = probability_force_closure(j1, j2, draw_shape_samples(ctx.posterior, 400, np.random.default_rng(2)),
                                       ctx.gripper, ctx.sigma_g).p
        terms.append((params.uncertainty_penalty * d['uncertainty'], d['pf_smoothed'], pf))
    for penalty, smooth, pf in terms[1:]:
        # (a contact near where the body meets the uncertain part may land on the other one on another grid)
        assert np.mean(np.isclose(penalty, terms[0][0], rtol=0.05, atol=0.01)) >= 0.9  # per cell²: x 4 and x 16
        assert np.mean(np.abs(smooth - terms[0][1])) <= 0.05
        assert np.mean(np.abs(pf - terms[0][2])) <= 0.05 and abs(np.mean(pf - terms[0][2])) <= 0.02
