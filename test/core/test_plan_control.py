"""Cooperative cancellation and progress of the planners (PlanControl / PlanProgress)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpis_grasp_ros.core.planners import PlanControl, PlannerParams, PlanProgress, plan
from support.synthetic_shapes import transparent_part_posterior

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
    r = plan('gp-gpis-opt', POST, PARAMS, seed=2, control=rec.control())
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
    a = plan('gp-gpis-opt', POST, PARAMS, seed=3, control=rec.control())
    b = plan('gp-gpis-opt', POST, PARAMS, seed=3)
    assert a.success and a.stopped == '' and b.stopped == ''
    np.testing.assert_array_equal(a.jaw1, b.jaw1)
    assert a.p_f == b.p_f
    done = [c.restarts_done for c in rec.calls]  # one report per finished restart, heartbeats repeat a count
    assert done == sorted(done) and sorted(set(done) - {0}) == list(range(1, PARAMS.n_initial_grasps + 1))
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


# ---- stop checks inside one SCP iteration (all restarts advance together) ----

class _Stop(Exception):
    pass


def _rowwise(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A smooth row-wise test problem: minimise ‖x − 1‖² subject to ‖x‖² <= 2."""
    f = np.sum((points - 1.0) ** 2, axis=1) + 0.1 * np.sin(points).sum(axis=1)
    return f, (np.sum(points ** 2, axis=1) - 2.0)[:, None]


def test_scp_polls_between_evaluation_batches_and_results_do_not_depend_on_it() -> None:
    from gpis_grasp_ros.core.scp import ScpSettings, scp_minimize
    x0 = np.random.default_rng(0).uniform(-2, 2, (200, 4))
    rows = [0]
    gaps: list[int] = []
    last = [0]

    def fun(p: np.ndarray):
        rows[0] += p.shape[0]
        return _rowwise(p)

    def poll() -> None:
        gaps.append(rows[0] - last[0])
        last[0] = rows[0]

    base = scp_minimize(_rowwise, x0, ScpSettings(max_iterations=30))
    chunked = scp_minimize(fun, x0, ScpSettings(max_iterations=30, eval_chunk=16), poll=poll)
    np.testing.assert_array_equal(base.x, chunked.x)
    np.testing.assert_array_equal(base.iterations, chunked.iterations)
    # the first finite differences alone are 200 x 4 points: at least 50 polls before the first QP,
    # and never more than one batch of 16 points between two polls
    assert max(gaps) <= 16 and len(gaps) >= 50 + chunked.qp_solves


def test_a_poll_that_raises_while_the_qp_is_solved_stops_at_once() -> None:
    import threading

    from gpis_grasp_ros.core.scp import _polled
    release = threading.Event()
    calls = [0]

    def slow() -> str:
        release.wait(30.0)
        return 'done'

    def poll() -> None:
        calls[0] += 1
        if calls[0] == 3:
            raise _Stop

    with pytest.raises(_Stop):
        _polled(poll, 0.001, slow)  # returns only through the poll: the solve is still blocked
    assert calls[0] == 3 and not release.is_set()
    release.set()
    assert _polled(lambda: None, 0.001, lambda a, b: a + b, 2, 3) == 5
    assert _polled(None, 0.001, lambda: 'direct') == 'direct'


def test_stop_mid_iteration_with_many_restarts(monkeypatch: pytest.MonkeyPatch) -> None:
    from gpis_grasp_ros.core import planners
    rows = [0]
    details = planners.MeanGraspObjective.details

    def counting(self, x):
        rows[0] += np.atleast_2d(x).shape[0]
        return details(self, x)

    monkeypatch.setattr(planners.MeanGraspObjective, 'details', counting)
    seen: list[int] = []
    progress: list[PlanProgress] = []

    def should_stop() -> str | None:
        seen.append(rows[0])
        return 'timeout' if len(seen) >= 40 else None

    params = PlannerParams(n_shape_samples=300, n_grasp_samples=300, n_initial_grasps=200)
    control = PlanControl(should_stop=should_stop, on_progress=progress.append)
    r = plan('gp-gpis-opt', POST, params, seed=5, control=control)
    assert r.stopped == 'timeout' and not r.success and len(seen) == 40
    # 40 polls cover the 1 + 4 evaluations of each of the 200 restarts (8 batches) and a few
    # iterations, with at most one batch of SCP_EVAL_CHUNK points (32 restarts' worth) between polls, plus the
    # one-point progress evaluation of a restart that finished as the best so far (_ScpMonitor)
    assert rows[0] >= 1000 and max(np.diff(seen)) <= planners.SCP_EVAL_CHUNK + 1
    assert (progress[-1].restarts_done if progress else 0) < params.n_initial_grasps


def test_many_restarts_same_result_with_a_control() -> None:
    params = PlannerParams(n_shape_samples=300, n_grasp_samples=300, n_initial_grasps=40)
    a = plan('gp-gpis-opt', POST, params, seed=7, control=PlanControl())
    b = plan('gp-gpis-opt', POST, params, seed=7)
    np.testing.assert_array_equal(a.jaw1, b.jaw1)
    np.testing.assert_array_equal(a.jaw2, b.jaw2)
    assert a.p_f == b.p_f and a.objective == b.objective and a.iterations == b.iterations


def test_heartbeat_reports_a_long_gap_once_and_keeps_the_counts() -> None:
    from gpis_grasp_ros.core.planners.result import HEARTBEAT_S, Tracker

    rec = Recorder(stop_after=None)
    tracker = Tracker(rec.control(), total=3)
    tracker.heartbeat()  # just started: nothing to report
    assert rec.calls == []
    tracker.last_report -= 2 * HEARTBEAT_S  # the SCP ran a long iteration with no restart finished
    tracker.heartbeat()
    tracker.heartbeat()  # reported a moment ago: not again
    assert [(c.restarts_done, c.restarts_total) for c in rec.calls] == [(0, 3)]
    tracker.step(1.0, 0.5)
    assert [(c.restarts_done, c.best_objective) for c in rec.calls][-1] == (1, 1.0)
