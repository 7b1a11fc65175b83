"""Eq. 6 on the mean shape (smoothed P̃_F, uncertainty penalty, antipodal and candidate-set constraints) as the
batch function the SCP minimises."""

from __future__ import annotations

import numpy as np

from gpis_grasp_ros.core.contacts import find_contacts, perturb_grasps
from gpis_grasp_ros.core.planners.context import PlanningContext
from gpis_grasp_ros.core.quality import grasp_quality
from gpis_grasp_ros.core.sdf_bank import bilinear


class MeanGraspObjective:
    """Eq. 6 on the mean shape as a batch function for :func:`scp_minimize` (minimisation form).

    ``x = (col1, row1, col2, row2)`` (cells). Returns ``F = −P̃_F + λ(σ²(c1) + σ²(c2))`` (σ² in
    cells², c on the mean shape for the unperturbed grasp) and constraints ``G <= 0``:
    opening (cells), clearance of jaw 1 and 2 (cells), and with ``antipodal`` the three
    constraints of eq. 5 (see docs/planning.md).
    """

    def __init__(self, ctx: PlanningContext, eps: np.ndarray, penalty: float, antipodal: bool) -> None:
        self.ctx = ctx
        self.eps = np.asarray(eps, dtype=np.float64)  # (K_p, 2, 2)
        self.penalty = float(penalty)
        self.antipodal = antipodal
        self.n_constraints = 6 if antipodal else 3
        self.trials = 0

    def jaws(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        g = self.ctx.geometry
        return g.to_metric(x[..., 0:2]), g.to_metric(x[..., 2:4])

    def details(self, x: np.ndarray) -> dict[str, np.ndarray]:
        ctx = self.ctx
        x = np.atleast_2d(x)
        j1, j2 = self.jaws(x)
        b = x.shape[0]
        zero = np.zeros((1, 2, 2))
        eps = np.concatenate([zero, self.eps], axis=0)[None]  # trial 0 is the unperturbed grasp
        g1, g2 = perturb_grasps(j1[:, None], j2[:, None], eps, ctx.sigma_g)
        con = find_contacts(ctx.mean_bank, g1, g2, ctx.gripper, check_opening=False)
        self.trials += g1.shape[0] * g1.shape[1]
        q = grasp_quality(con, ctx.com, ctx.gripper, ctx.rho)
        with np.errstate(over='ignore'):
            smooth = 1.0 / (1.0 + np.exp(-q[:, 1:] / ctx.params.smoothing_scale))
        pf = smooth.mean(axis=1) if self.eps.shape[0] else np.zeros(b)
        ok = ~con.no_contact[:, 0]
        var = np.full((b, 2), ctx.max_variance_cells)
        if ok.any():
            pts = np.stack([con.c1[ok, 0], con.c2[ok, 0]], axis=1)
            var[ok] = bilinear(ctx.variance_cells, ctx.geometry, pts)
        unc = var.sum(axis=1)
        objective = -pf + self.penalty * unc
        res = ctx.res
        width = np.linalg.norm(j2 - j1, axis=1)
        cons = [(width - ctx.gripper.max_opening) / res, -con.clearance1[:, 0] / res, -con.clearance2[:, 0] / res]
        if self.antipodal:
            n1, n2 = con.n1[:, 0], con.n2[:, 0]
            # Eq. 5 on the contact line v = (c1 − c2)/‖c1 − c2‖ (see docs/planning.md).
            line = con.c1[:, 0] - con.c2[:, 0]
            dist = np.hypot(line[:, 0], line[:, 1])
            has_line = con.valid[:, 0] & (dist > 1e-9 * res)
            v = line / np.where(has_line, dist, 1.0)[:, None]
            beta, alpha = ctx.params.beta + 2.0 * ctx.params.constraint_tol, ctx.params.antipodal_alpha
            c_alpha = np.where(has_line, np.sum((n1 + n2) ** 2, axis=1) - alpha, 4.0 - alpha)
            c_b1 = np.where(has_line, beta - np.sum(n1 * v, axis=1), 1.0 + beta)
            c_b2 = np.where(has_line, beta + np.sum(n2 * v, axis=1), 1.0 + beta)
            cons += [c_alpha, c_b1, c_b2]
        cons = np.stack(cons, axis=1)
        cons = np.where(np.isfinite(cons), cons, 10.0)
        valid = con.valid[:, 0] & (width <= ctx.gripper.max_opening * (1 + 1e-9))
        return {'objective': objective, 'constraints': cons, 'pf_smoothed': pf, 'uncertainty': unc,
                'q_nominal': q[:, 0], 'valid_nominal': valid}

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = self.details(x)
        return d['objective'], d['constraints']
