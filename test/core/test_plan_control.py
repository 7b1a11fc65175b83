"""Cooperative cancellation and progress of the planners (PlanControl / PlanProgress)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpis_grasp_ros.core.planners import PlanControl, PlannerParams, PlanProgress, plan
from synthetic_shapes import transparent_part_posterior

POST, _ = transparent_part_posterior()
PARAMS = PlannerParams(n_shape_samples=300, n_grasp_samples=300, n_initial_grasps=6)


class Recorder:
    """Records progress calls; asks to stop once ``stop_after`` restarts/chunks are done."""

    def __init__(self, stop_after: int | None, reason: str = 'cancelled') -> None:
        self.calls: list[PlanProgress] = []
        self.polls = 0
        self.stop_after = stop_after
        self.reason = reason

    def should_stop(self) -> str | None:
        self.polls += 1
        done = self.calls[-1].restarts_done if self.calls else 0
        return self.reason if self.stop_after is not None and done >= self.stop_after else None

    def control(self) -> PlanControl:
        return PlanControl(should_stop=self.should_stop, on_progress=self.calls.append)


def test_stop_after_second_restart() -> None:
    rec = Recorder(stop_after=2)
    r = plan('gp-g', POST, PARAMS, seed=2, control=rec.control())
    assert not r.success and r.stopped == 'cancelled' and r.message == 'stopped: cancelled'
    assert np.all(np.isnan(r.jaw1)) and r.method == 'gp-gpis-opt'
    assert rec.calls[-1].restarts_done == 2 and rec.calls[-1].restarts_total == PARAMS.n_initial_grasps
    assert [c.restarts_done for c in rec.calls] == [1, 2]
    # the first finished restart sets the best objective and its smoothed P_F
    assert np.isfinite(rec.calls[0].best_objective) and 0.0 <= rec.calls[0].best_p_f <= 1.0
    # polled at every SCP iteration, not only when a restart finishes
    assert rec.polls > len(rec.calls)


def test_progress_of_a_full_run_and_no_control_is_unchanged() -> None:
    rec = Recorder(stop_after=None)
    a = plan('gp-g', POST, PARAMS, seed=3, control=rec.control())
    b = plan('gp-g', POST, PARAMS, seed=3)
    assert a.success and a.stopped == '' and b.stopped == ''
    np.testing.assert_array_equal(a.jaw1, b.jaw1)
    assert a.p_f == b.p_f
    assert [c.restarts_done for c in rec.calls] == list(range(1, PARAMS.n_initial_grasps + 1))
    assert all(c.restarts_total == PARAMS.n_initial_grasps for c in rec.calls)
    # the best objective reported never decreases once a feasible restart has been seen, and the
    # last report is the best objective over the finished restarts (before the final opening fix)
    best = [c.best_objective for c in rec.calls]
    assert best[-1] == pytest.approx(a.objective, abs=0.05)


@pytest.mark.parametrize('method', ['gp-p', 'gp-m', 'gp-u', 'gp-gpis-opt-reranked'])
def test_every_planner_stops(method: str) -> None:
    rec = Recorder(stop_after=1, reason='timeout')
    r = plan(method, POST, PARAMS, seed=1, control=rec.control())
    assert not r.success and r.stopped == 'timeout' and r.message == 'stopped: timeout'
    assert rec.calls[-1].restarts_done == 1 and rec.calls[-1].restarts_total > 1


def test_stop_before_start_and_gp_p_progress() -> None:
    r = plan('gp-p', POST, PARAMS, seed=1, control=PlanControl(should_stop=lambda: 'shutting down'))
    assert r.stopped == 'shutting down' and not r.success
    rec = Recorder(stop_after=None)
    r = plan('gp-p', POST, PARAMS, seed=1, control=rec.control())
    assert r.success and rec.calls[-1].restarts_done == rec.calls[-1].restarts_total >= 2
    # GP-P reports the leading Monte-Carlo P̂_F of each round; the last round is the full-sample choice
    assert rec.calls[-1].best_p_f == pytest.approx(r.objective)
    assert all(0.0 <= c.best_p_f <= 1.0 and not math.isnan(c.best_objective) for c in rec.calls)
