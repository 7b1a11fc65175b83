"""Heuristic candidate grasps on the mean shape (paper VII-B) and the valid, spread-out initial grasps of
Algorithm 1 (line 7)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.planners.result import never_stop

if TYPE_CHECKING:
    from gpis_grasp_ros.core.planners.context import PlanningContext


def mean_surface_points(mean: np.ndarray, geometry: GridGeometry) -> np.ndarray:
    """Zero crossings (m) of the mean SDF on the grid edges (linear interpolation), ``(P, 2)``."""
    centers = geometry.cell_centers()
    pts = []
    for a, b, pa, pb in ((mean[:, :-1], mean[:, 1:], centers[:, :-1], centers[:, 1:]),
                         (mean[:-1, :], mean[1:, :], centers[:-1, :], centers[1:, :])):
        cross = (a < 0) != (b < 0)
        fa, fb = a[cross], b[cross]
        t = fa / (fa - fb)
        pts.append(pa[cross] + t[:, None] * (pb[cross] - pa[cross]))
    return np.concatenate(pts, axis=0) if pts else np.zeros((0, 2))


def sample_heuristic_grasps(ctx: PlanningContext, n: int, rng: np.random.Generator,
                            checkpoint: Callable[[], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Heuristic candidate grasps of VII-B, ``(n, 2)`` jaws each (m).

    A point p on the mean surface (:func:`surface_sample`); a direction u, with
    probability 1/2 the surface normal at p and otherwise toward the centre of mass; the jaws on
    the line p + t u, centred on the line's interior chord (from the first to the last point
    where μ < 0, sampled every half cell over the whole grid) and w_g apart.
    """
    if ctx.surface.shape[0] == 0 or n <= 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    p = surface_sample(ctx, n, rng)
    normal = ctx.shape_bank.normals_at(p)
    to_com = ctx.com - p
    dist = np.linalg.norm(to_com, axis=1, keepdims=True)
    to_com = np.where(dist > 1e-9, to_com / np.where(dist > 1e-9, dist, 1.0), normal)
    use_normal = rng.random(n) < 0.5
    u = np.where(use_normal[:, None], normal, to_com)
    bad = np.linalg.norm(u, axis=1) < 0.5
    theta = rng.uniform(0, 2 * np.pi, n)
    u[bad] = np.stack([np.cos(theta[bad]), np.sin(theta[bad])], axis=1)
    g = ctx.geometry
    half = math.hypot(g.width, g.height)  # cells: covers the grid from any surface point
    t = np.arange(-half, half + 0.25, 0.5)
    uv = g.to_cell(p)
    vals = np.empty((n, t.size))
    for a in range(0, n, 1024):  # batches (a stop check between them); the values are row-wise
        if checkpoint is not None:
            checkpoint()
        b = a + 1024
        vals[a:b] = ctx.shape_bank.values_cells(uv[a:b, 0, None] + t[None] * u[a:b, 0, None],
                                               uv[a:b, 1, None] + t[None] * u[a:b, 1, None])
    neg = vals < 0
    has = neg.any(axis=1)
    t_lo = t[np.argmax(neg, axis=1)]
    t_hi = t[neg.shape[1] - 1 - np.argmax(neg[:, ::-1], axis=1)]
    mid = np.where(has, 0.5 * (t_lo + t_hi), 0.0) * ctx.res
    centre = p + mid[:, None] * u
    half_open = 0.5 * ctx.gripper.max_opening
    return centre - half_open * u, centre + half_open * u


def surface_sample(ctx: PlanningContext, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points (m) spread uniformly over the zero level set of the mean SDF.

    A random zero crossing on a grid edge, moved by up to half a cell along the local tangent,
    then projected back onto μ = 0 with two Newton steps along the gradient: a continuous
    distribution over the contour rather than a handful of discrete edge points.
    """
    p = ctx.surface[rng.integers(ctx.surface.shape[0], size=n)]
    normal = ctx.shape_bank.normals_at(p)
    tangent = np.stack([-normal[:, 1], normal[:, 0]], axis=1)
    p = p + rng.uniform(-0.5, 0.5, (n, 1)) * ctx.res * tangent
    for _ in range(2):
        grad = ctx.shape_bank.gradients_at(p)
        g2 = np.sum(grad * grad, axis=1)
        step = np.where(g2 > 1e-6, ctx.shape_bank.values(p) / np.maximum(g2, 1e-6), 0.0)
        p = p - np.clip(step, -ctx.res, ctx.res)[:, None] * grad
    return p


def _grasp_distance(a1: np.ndarray, a2: np.ndarray, b1: np.ndarray, b2: np.ndarray) -> np.ndarray:
    """Distance between unordered jaw pairs (m), broadcasting."""
    same = np.linalg.norm(a1 - b1, axis=-1) + np.linalg.norm(a2 - b2, axis=-1)
    swap = np.linalg.norm(a1 - b2, axis=-1) + np.linalg.norm(a2 - b1, axis=-1)
    return np.minimum(same, swap)


def sample_valid_grasps(ctx: PlanningContext, n: int, rng: np.random.Generator,
                        oversample: int = 4, checkpoint: Callable[[], None] | None = None
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``n`` heuristic grasps valid on the mean shape (contacts, jaws in free space, opening).

    ``oversample * n`` valid heuristic grasps are drawn and ``n`` of them kept by farthest-point
    sampling in grasp space (first pick random), so that the restarts of Algorithm 1 cover the
    object instead of repeating near-identical initial grasps. ``checkpoint`` (may raise to stop)
    is called between sampling rounds and every 64 farthest-point picks.
    """
    check = checkpoint if checkpoint is not None else never_stop
    want = max(n, oversample * n)
    j1s, j2s = [], []
    found = 0
    for _ in range(ctx.params.max_sampling_rounds):
        check()
        j1, j2 = sample_heuristic_grasps(ctx, max(2 * want, 16), rng, checkpoint=check)
        check()
        ok = ctx.valid_on_mean(j1, j2)
        j1s.append(j1[ok])
        j2s.append(j2[ok])
        found += int(ok.sum())
        if found >= want:
            break
    if found == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    j1 = np.concatenate(j1s)[:want]
    j2 = np.concatenate(j2s)[:want]
    if j1.shape[0] <= n:
        return j1, j2
    chosen = [int(rng.integers(j1.shape[0]))]
    dmin = _grasp_distance(j1, j2, j1[chosen[0]], j2[chosen[0]])
    for i in range(n - 1):
        if i % 64 == 63:
            check()
        k = int(np.argmax(dmin))
        chosen.append(k)
        dmin = np.minimum(dmin, _grasp_distance(j1, j2, j1[k], j2[k]))
    return j1[chosen], j2[chosen]
