"""What a planner returns (:class:`GraspResult`, :class:`RestartInfo`) and how a caller stops or follows it
(:class:`PlanControl`, :class:`PlanProgress`; :class:`Tracker` is the planners' side of that contract)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np


@dataclass
class RestartInfo:
    """One SCP run of an optimising planner (jaws in m; objective of eq. 6, to maximise).

    ``converged`` the run met the convergence test of :mod:`scp` (``reason`` says which test, or
    why it stopped: iteration cap, constraints violated at the maximum penalty, failed QPs);
    ``iterations`` QP solves; ``objective_history`` the eq. 6 value at the start and after every
    SCP iteration (before the final opening fix, so its last entry can differ from
    ``objective`` by the shrink); ``qp_failures``/``qp_status`` failed QP solves and the last
    failure status ('' if none); ``initial_feasible`` whether the initial grasp met every
    constraint; ``feasible`` whether the returned grasp does; ``warm`` whether it started at a previous
    plan's optimum.
    """

    initial_jaw1: np.ndarray
    initial_jaw2: np.ndarray
    jaw1: np.ndarray
    jaw2: np.ndarray
    objective: float
    pf_smoothed: float
    feasible: bool
    converged: bool
    reason: str
    iterations: int
    evaluations: int
    p_f: float = float('nan')  # Monte-Carlo P_F (re-ranked planner only)
    objective_history: np.ndarray = field(default_factory=lambda: np.zeros(0))  # eq. 6 value per SCP iteration
    initial_feasible: bool = False  # the initial grasp already met every constraint (to constraint_tol)
    qp_failures: int = 0  # QP subproblems the QP solver failed to solve during this run
    qp_status: str = ''  # last failed QP status ('' when every QP solved)
    warm: bool = False  # started from a previous plan's optimum (warm_start.WarmStart), not a fresh heuristic grasp
    penalty: float = float('nan')  # the ℓ1 penalty μ the run ended with (scp.ScpResult.penalty)


@dataclass
class GraspResult:
    """Planned parallel-jaw grasp (all planners). Positions in m in the grid/sensor frame.

    ``axis`` unit closing direction jaw1 → jaw2; ``width`` ‖jaw2 − jaw1‖ (m); ``q_mean`` Q_F on
    the mean SDF (NaN if the grasp is degenerate there); ``p_f`` ± ``p_f_std_error`` the
    Monte-Carlo P_F on the evaluation samples; ``objective`` the method's own criterion (Q_F for
    GP-M, selection P̂_F for GP-P, eq. 4/6 value for the optimisers, MC P_F when re-ranked);
    ``iterations`` total SCP iterations (0 for sampling planners); ``planning_time`` the search's wall time (s),
    ``evaluation_time`` what the final P_F took after it (the evaluation samples are drawn on another thread during
    the search, so mostly the Monte-Carlo test).
    """

    method: str
    success: bool
    message: str
    jaw1: np.ndarray
    jaw2: np.ndarray
    center: np.ndarray
    axis: np.ndarray
    width: float
    q_mean: float
    p_f: float
    p_f_std_error: float
    objective: float
    planning_time: float
    evaluation_time: float = 0.0
    iterations: int = 0
    converged: bool = False
    feasible: bool = False
    n_candidates: int = 0
    restarts: list[RestartInfo] = field(default_factory=list)
    seed: int | None = None
    stopped: str = ''  # reason a PlanControl stopped the plan ('' when it ran to the end)
    planning_cpu_time: float = float('nan')  # CPU time (s) of the planning part, the final P_F's sampling thread not
    # counted (less load-dependent than the wall time)


@dataclass(frozen=True)
class PlanProgress:
    """Progress of one :func:`plan` call, passed to :attr:`PlanControl.on_progress`.

    ``restarts_done``/``restarts_total`` count SCP restarts for the optimising planners and
    chunks of work for the sampling planners (GP-M: candidate chunks; GP-P: successive-halving
    rounds). ``best_objective`` the method's criterion of the best finished restart/chunk (eq. 6
    value, Q_F or P̂_F), ``best_p_f`` its probability of force closure (smoothed P̃_F on the
    mean for the optimisers, Monte-Carlo P̂_F for GP-P, NaN for GP-M); NaN when not known yet.
    """

    restarts_done: int
    restarts_total: int
    best_objective: float
    best_p_f: float


def never_stop() -> str | None:
    return None


@dataclass
class PlanControl:
    """Cooperative cancellation and progress of one :func:`plan` call.

    ``should_stop`` is polled between SCP iterations and restarts, inside an SCP iteration between
    evaluation batches and during the QP solve, and between Monte-Carlo sample chunks (every few
    tens of milliseconds at most); a non-empty reason (e.g. ``'timeout'``,
    ``'cancelled'``, ``'shutting down'``) stops the plan, which then returns
    ``GraspResult(success=False, message='stopped: <reason>', stopped=<reason>)``.
    ``on_progress`` is called after each finished restart/chunk, and at least every
    :data:`HEARTBEAT_S` during a long SCP while no restart finishes (the same counts: a caller sees the plan
    is alive and can cancel from its progress callback early).
    """

    should_stop: Callable[[], str | None] = never_stop
    on_progress: Callable[[PlanProgress], None] | None = None


#: Longest gap (s) between progress reports while an SCP runs (:meth:`Tracker.heartbeat`)
HEARTBEAT_S = 0.5


class Stopped(Exception):
    """Raised at a checkpoint when the PlanControl asks to stop (caught by the planner entry points)."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class Tracker:
    """Progress and stop bookkeeping of one plan call (no-op without a PlanControl)."""

    def __init__(self, control: PlanControl | None, total: int = 0) -> None:
        self.control = control
        self.cpu_start = time.process_time()  # CPU time (s, all threads) at the start of the plan
        self.total = int(total)
        self.done = 0
        self.best_objective = float('nan')
        self.best_p_f = float('nan')
        self.last_report = time.monotonic()

    def check(self) -> None:
        """Raise :class:`Stopped` if the control asks to stop."""
        if self.control is None:
            return
        reason = self.control.should_stop()
        if reason:
            raise Stopped(str(reason))

    def step(self, best_objective: float | None = None, best_p_f: float | None = None) -> None:
        """One more restart/chunk finished: report progress, then check for a stop."""
        self.done += 1
        if best_objective is not None:
            self.best_objective = float(best_objective)
        if best_p_f is not None:
            self.best_p_f = float(best_p_f)
        self._report()
        self.check()

    def heartbeat(self, period: float = HEARTBEAT_S) -> None:
        """Report progress (unchanged counts) when the last report is ``period`` s old, then check for a stop."""
        if time.monotonic() - self.last_report >= period:
            self._report()
        self.check()

    def _report(self) -> None:
        self.last_report = time.monotonic()
        if self.control is not None and self.control.on_progress is not None:
            self.control.on_progress(PlanProgress(self.done, self.total, self.best_objective, self.best_p_f))


def empty_result(method: str, message: str, t_start: float, seed: int | None, **kw) -> GraspResult:
    nan2 = np.full(2, np.nan)
    return GraspResult(method=method, success=False, message=message, jaw1=nan2.copy(), jaw2=nan2.copy(),
                       center=nan2.copy(), axis=nan2.copy(), width=float('nan'), q_mean=float('nan'), p_f=0.0,
                       p_f_std_error=0.0, objective=float('nan'), planning_time=time.perf_counter() - t_start,
                       seed=seed, **kw)

