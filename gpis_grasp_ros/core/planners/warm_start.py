"""Replanning from the previous plan: its local optima as the next plan's SCP starts.

A camera-rate loop plans again on every new frame burst of a scene that has barely changed. The previous
plan's converged local optima are then better starts for SCP than fresh heuristic grasps: each is at (or
next to) a local optimum of the new objective, and its run resumes with the ℓ1 penalty it ended with, so it
converges in a few iterations, and the plan tends to keep the optimum it had (docs/speed.md measures both).
The optima are kept in the sensor frame, so a table plane or a grid that moved between the frames moves
nothing in the world.

Only optima still valid on the new mean shape are used (contacts, jaws in free space, opening: an object
that moved leaves none and the plan starts cold), at most N_g - :data:`FRESH_SHARE` x N_g of them, best
first; fresh heuristic grasps fill the other starts, so every plan keeps exploring and a better optimum
one of them finds is a start of the next plan.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.planners.result import GraspResult
from gpis_grasp_ros.core.planners.sampling import sample_valid_grasps

if TYPE_CHECKING:
    from gpis_grasp_ros.core.planners.context import PlanningContext

#: Share of N_g that always starts from fresh heuristic grasps in a warm-started plan (rounded up).
FRESH_SHARE = 0.25

#: Planners that accept a warm start (the SCP planners; the sampling planners have no starts).
WARM_METHODS = ('gp-gpis-opt', 'gp-gpis-opt-reranked', 'gp-d', 'gp-u')


@dataclass(frozen=True)
class WarmStart:
    """A previous plan's converged local optima (best first) in the sensor frame (m), ``(n, 3)`` per jaw,
    and the ℓ1 penalty each run ended with (``(n,)``, > 0)."""

    jaw1: np.ndarray
    jaw2: np.ndarray
    penalty: np.ndarray | None = None  # None: every run starts at the SCP's initial penalty

    def __post_init__(self) -> None:
        for name in ('jaw1', 'jaw2'):
            a = np.asarray(getattr(self, name), dtype=np.float64)
            if a.ndim != 2 or a.shape[1] != 3 or not np.isfinite(a).all():
                raise ValueError(f'warm start {name} must be finite (n, 3) sensor-frame points, got shape {a.shape}')
            object.__setattr__(self, name, a)
        if self.jaw1.shape != self.jaw2.shape:
            raise ValueError(f'warm start jaws differ in shape: {self.jaw1.shape} and {self.jaw2.shape}')
        if self.penalty is not None:
            mu = np.asarray(self.penalty, dtype=np.float64)
            if mu.shape != (self.size,) or not (np.isfinite(mu) & (mu > 0)).all():
                raise ValueError(f'warm start penalty must be {self.size} positive numbers, got {mu}')
            object.__setattr__(self, 'penalty', mu)

    @property
    def size(self) -> int:
        return self.jaw1.shape[0]

    @classmethod
    def from_result(cls, result: GraspResult, geometry: GridGeometry) -> WarmStart | None:
        """The converged optima of ``result`` (planned on a posterior on ``geometry``): feasible ones first, then
        by objective; None when it has none (a sampling planner, a plan that found no start or none converged).
        A run stopped by the iteration cap or the penalty limit is no optimum to resume."""
        order = sorted((r for r in result.restarts if r.converged), key=lambda r: (not r.feasible, -r.objective))
        if not order:
            return None
        j1 = geometry.to_sensor(np.array([r.jaw1 for r in order], dtype=np.float64))
        j2 = geometry.to_sensor(np.array([r.jaw2 for r in order], dtype=np.float64))
        mu = np.array([r.penalty for r in order], dtype=np.float64)
        return cls(j1, j2, mu if np.isfinite(mu).all() and (mu > 0).all() else None)

    def on(self, geometry: GridGeometry) -> tuple[np.ndarray, np.ndarray]:
        """The optima as grid-frame jaws ``(n, 2)`` (m) of ``geometry`` (projected onto its table plane)."""
        return geometry.from_sensor(self.jaw1)[0], geometry.from_sensor(self.jaw2)[0]


def initial_grasps(ctx: PlanningContext, n: int, rng: np.random.Generator, warm: WarmStart | None,
                   checkpoint: Callable[[], None] | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Algorithm 1's ``n`` initial grasps: the warm start's optima valid on the mean shape (at most
    ``n - ceil(FRESH_SHARE n)``, best first), then fresh valid heuristic grasps; (jaw1, jaw2, initial penalty
    (the warm runs' own; NaN = the SCP's initial penalty), number of warm starts)."""
    if warm is None or warm.size == 0:
        j1, j2 = sample_valid_grasps(ctx, n, rng, checkpoint=checkpoint)
        return j1, j2, np.full(j1.shape[0], np.nan), 0
    w1, w2 = warm.on(ctx.geometry)
    ok = np.flatnonzero(ctx.valid_on_mean(w1, w2))[:max(0, n - math.ceil(FRESH_SHARE * n))]
    mu = np.full(ok.size, np.nan) if warm.penalty is None else warm.penalty[ok]
    f1, f2 = sample_valid_grasps(ctx, n - ok.size, rng, checkpoint=checkpoint) if n > ok.size else (
        np.zeros((0, 2)), np.zeros((0, 2)))
    return (np.concatenate([w1[ok], f1]), np.concatenate([w2[ok], f2]),
            np.concatenate([mu, np.full(f1.shape[0], np.nan)]), int(ok.size))
