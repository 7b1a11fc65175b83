"""Calibration metrics of the benchmark (ECE, Brier score, reliability bins) on analytic cases."""

from __future__ import annotations

import numpy as np
import pytest

from gpis_grasp_ros.tools.benchmark import calibration as cal


def _exact_counts(rate: np.ndarray, trials: int) -> np.ndarray:
    """Success counts that realise ``rate`` exactly (rates on the 1/trials lattice)."""
    s = rate * trials
    assert np.allclose(s, np.round(s))
    return np.round(s)


def test_perfectly_calibrated_predictions_have_ece_at_the_sampling_floor() -> None:
    rng = np.random.default_rng(0)
    p = rng.uniform(0, 1, 4000)
    n = 50
    s = rng.binomial(n, p)
    ece = cal.expected_calibration_error(p, s, n)
    null_mean, null_p95 = cal.null_ece(p, n, np.random.default_rng(1), repeats=100)
    # Sampling error of a bin mean: sqrt(p(1-p) / (n * N_b)) <= 0.5 / sqrt(50 * 400) ~ 0.0035.
    assert ece < 0.01
    assert null_mean < 0.01 and ece <= 2 * null_p95
    # Exact outcomes (no sampling at all): ECE is 0 to rounding.
    q = np.round(p * 100) / 100
    assert cal.expected_calibration_error(q, _exact_counts(q, 100), 100) == pytest.approx(0.0, abs=1e-12)


def test_known_offset_gives_known_ece_and_brier() -> None:
    rng = np.random.default_rng(2)
    q = np.round(rng.uniform(0.2, 0.95, 1000) * 100) / 100
    rate = q - 0.1  # over-confident by exactly 0.1 everywhere
    s = _exact_counts(np.round(rate * 100) / 100, 100)
    assert cal.expected_calibration_error(q, s, 100) == pytest.approx(0.1, abs=1e-9)
    r = s / 100
    expected_brier = np.mean((q - r) ** 2 + r * (1 - r))
    assert cal.brier_score(q, s, 100) == pytest.approx(expected_brier, rel=1e-12)
    summary = cal.summarise([{'sim_successes': a, 'sim_trials': 100, **{k: b for k, _ in cal.PREDICTORS}}
                             for a, b in zip(s, q, strict=True)], null_repeats=5)
    assert summary['p_f']['bias'] == pytest.approx(0.1, abs=1e-9)


def test_quadratic_miscalibration_matches_the_integral() -> None:
    """True success probability p² for predictions p ~ U(0, 1): per bin [a, b] the gap is
    (a + b) / 2 − (a² + ab + b²) / 3, so ECE = mean over the 10 bins of that gap."""
    rng = np.random.default_rng(3)
    p = rng.uniform(0, 1, 200_000)
    n = 200
    s = rng.binomial(n, p ** 2)
    edges = np.linspace(0, 1, 11)
    a, b = edges[:-1], edges[1:]
    expected = np.mean((a + b) / 2 - (a * a + a * b + b * b) / 3)
    assert cal.expected_calibration_error(p, s, n) == pytest.approx(expected, abs=3e-3)
    # Brier per execution: E[(p - y)^2] = E[p^2 - 2 p^3 + p^2] = 2/3 - 1/2 = 1/6.
    assert cal.brier_score(p, s, n) == pytest.approx(1 / 6, abs=2e-3)


def test_brier_score_of_a_constant_prediction() -> None:
    # Outcome rate 0.3 predicted as 0.3: Brier = 0.3 * 0.7; predicted as 1: (1 - 0.3)^2 + 0.21 = 0.7.
    assert cal.brier_score([0.3] * 4, [3] * 4, 10) == pytest.approx(0.21)
    assert cal.brier_score([1.0] * 4, [3] * 4, 10) == pytest.approx(0.7)


def test_reliability_bins_and_edges() -> None:
    r = cal.reliability([0.0, 0.05, 0.95, 1.0, 0.55], [0, 1, 9, 10, 5], 10)
    assert list(r.count) == [2, 0, 0, 0, 0, 1, 0, 0, 0, 2]  # 1.0 falls in the last bin
    assert r.mean_pred[0] == pytest.approx(0.025) and r.observed[0] == pytest.approx(0.05)
    assert r.observed[9] == pytest.approx(0.95) and np.isnan(r.observed[1])


@pytest.mark.parametrize('pred, succ, trials', [([1.2], [1], 2), ([0.5], [3], 2), ([0.5, 0.2], [1], 2),
                                                ([np.nan], [0], 2), ([0.5], [0], 0)])
def test_invalid_inputs_are_refused(pred: list, succ: list, trials: int) -> None:
    with pytest.raises(ValueError):
        cal.expected_calibration_error(pred, succ, trials)


def test_spread_by_value_covers_the_range_without_repeats() -> None:
    rng = np.random.default_rng(4)
    values = np.concatenate([np.zeros(500), rng.uniform(0, 1, 300), np.ones(200)])
    idx = cal.spread_by_value(values, 50)
    assert len(set(idx.tolist())) == 50
    v = values[idx]
    assert v.min() == 0.0 and v.max() == 1.0
    # Evenly spread: every tenth of [0, 1] holds some of the picks.
    assert np.all(np.histogram(v, bins=10, range=(0, 1))[0] > 0)
    assert len(cal.spread_by_value(values[:5], 50)) == 5


class _Disc:
    """A disc's exact SDF (m) as the true shape: ``values_at(xy)``."""

    def __init__(self, centre: tuple[float, float], radius: float) -> None:
        self.centre, self.radius = np.asarray(centre), radius

    def values_at(self, xy: np.ndarray) -> np.ndarray:
        return np.linalg.norm(np.asarray(xy) - self.centre, axis=-1) - self.radius


@pytest.mark.parametrize('offset_cells, sd_cells', [(0.5, 0.25), (-0.3, 0.1), (0.0, 1.0)])
def test_gp_z_scores_of_a_shifted_mean_with_known_sigma(offset_cells: float, sd_cells: float) -> None:
    from gpis_grasp_ros.core.gpis import GpisPosterior, KernelParams
    from gpis_grasp_ros.core.grid import GridGeometry

    res = 0.004
    g = GridGeometry(0.0, 0.0, res, 25, 25)
    truth = _Disc((0.05, 0.047), 0.03)
    sdf = truth.values_at(g.cell_centers())
    # mean = truth shifted by `offset` (the mean shape dilated by it), sigma known: z = offset / sigma everywhere
    mean = sdf - offset_cells * res
    post = GpisPosterior(g, mean, np.full(g.shape, (sd_cells * res) ** 2), np.zeros(g.shape + (2,)),
                         np.zeros((g.width * g.height, 1)), KernelParams(1e-4, 0.01, -0.01))
    z = cal.gp_z_scores(post, truth)
    assert z['gp_bias_near_surface_cells'] == pytest.approx(-offset_cells, abs=1e-9)
    assert z['gp_sd_near_surface_cells'] == pytest.approx(sd_cells, rel=1e-9)
    assert z['gp_z_rms_near_surface'] == pytest.approx(abs(offset_cells) / sd_cells, rel=1e-9)
    assert z['gp_coverage95_near_surface'] == (1.0 if abs(offset_cells) / sd_cells < 1.96 else 0.0)
    # "near the surface" = within 2 cells of the true surface: a ring of the disc's cells, not the whole grid
    near = np.abs(sdf) < 2 * res
    assert 0 < near.sum() < sdf.size / 2
