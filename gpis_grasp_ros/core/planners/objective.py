"""Eq. 6 on the mean shape (smoothed P̃_F, uncertainty penalty, antipodal and candidate-set constraints) as the
batch function the SCP minimises."""

from __future__ import annotations

import numpy as np

from gpis_grasp_ros.core.contacts import OBSTACLE_CONTACT_CELLS, find_contacts, perturb_grasps
from gpis_grasp_ros.core.objective_kernel import eq6_batch
from gpis_grasp_ros.core.planners.context import PlanningContext
from gpis_grasp_ros.core.quality import grasp_quality
from gpis_grasp_ros.core.sdf_bank import MIN_GRADIENT_NORM, bilinear

#: Length (m) of one unit of the SCP's variables: jaw positions, finite-difference steps, trust radii, step
#: tolerances and the length constraints are measured in it. Fixed in metres, so the optimisation is the same
#: on every planning grid (the SCP settings were tuned on 5 mm cells, where one unit was one cell).
SCP_UNIT_M = 0.005


class MeanGraspObjective:
    """Eq. 6 on the mean shape as a batch function for :func:`scp_minimize` (minimisation form).

    ``x = (x1, y1, x2, y2)`` / :data:`SCP_UNIT_M` (grid frame). Returns ``F = −P̃_F + λ(σ²(c1) + σ²(c2))``
    (σ² in m², λ per m², c on the mean shape for the unperturbed grasp; without contact the largest σ²) and
    constraints ``G <= 0``:
    opening, clearance of jaw 1 and 2 (all in SCP units), and with ``antipodal`` the three
    constraints of eq. 5 (see docs/planning.md).

    :meth:`details` makes one compiled call per batch (:func:`objective_kernel.eq6_batch`);
    :meth:`details_reference` is the same computation with numpy around :func:`contacts.find_contacts`,
    bit for bit the same results (``compiled=False`` makes :meth:`details` use it).
    """

    def __init__(self, ctx: PlanningContext, eps: np.ndarray, penalty: float, antipodal: bool,
                 compiled: bool = True) -> None:
        self.ctx = ctx
        self.eps = np.ascontiguousarray(eps, dtype=np.float64)  # (K_p, 2, 2)
        self.penalty = float(penalty)
        self.antipodal = antipodal
        self.n_constraints = 6 if antipodal else 3
        self.trials = 0
        self.compiled = compiled and ctx.gripper.exact_crossings  # the kernel implements the exact crossings
        self._kernel_args = self._bank_arguments() if self.compiled else ()

    def _bank_arguments(self) -> tuple:
        """The arguments of :func:`eq6_batch` after ``x`` and ``eps``: everything but the points."""
        ctx = self.ctx
        bank, g, p, grip = ctx.mean_bank, ctx.geometry, ctx.params, ctx.gripper
        gradients = bank.gradient_grids if bank.gradients_given else np.zeros((1, 2, 2, 2))
        obstacles = bank.obstacles if bank.obstacles is not None else np.zeros((2, 2))
        f64 = np.float64
        return (SCP_UNIT_M, float(ctx.sigma_g), float(g.origin_x), float(g.origin_y), float(g.resolution),
                bank.padded, bank.lipschitz, bank.border_positive, float(bank.pad),
                np.ascontiguousarray(grip.face_offsets(g) / g.resolution, dtype=f64), float(grip.patch_cells(g)),
                np.ascontiguousarray(gradients, dtype=f64), bool(bank.gradients_given), MIN_GRADIENT_NORM,
                np.ascontiguousarray(obstacles, dtype=f64), bank.obstacles is not None,
                OBSTACLE_CONTACT_CELLS * g.resolution, np.array(ctx.com, dtype=f64).reshape(1, 2),
                float(grip.friction_coef), float(ctx.rho), np.ascontiguousarray(ctx.variance, dtype=f64),
                float(ctx.max_variance), float(grip.max_opening), bool(self.antipodal),
                float(p.beta + 2.0 * p.constraint_tol), float(p.antipodal_alpha))

    @staticmethod
    def variables(jaw1: np.ndarray, jaw2: np.ndarray) -> np.ndarray:
        """SCP variables ``(..., 4)`` of jaws ``(..., 2)`` (m)."""
        return np.concatenate([np.asarray(jaw1, dtype=np.float64), np.asarray(jaw2, dtype=np.float64)],
                              axis=-1) / SCP_UNIT_M

    @staticmethod
    def jaws(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Jaws (m) of SCP variables ``x``."""
        return x[..., 0:2] * SCP_UNIT_M, x[..., 2:4] * SCP_UNIT_M

    def details(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """Objective (B,), constraints (B, m), smoothed P̃_F, uncertainty, nominal Q_F and validity of points
        ``x`` (B, 4)."""
        if not self.compiled:
            return self.details_reference(x)
        x = np.ascontiguousarray(np.atleast_2d(x), dtype=np.float64)
        b = x.shape[0]
        q = np.empty((b, self.eps.shape[0] + 1))
        unc = np.empty(b)
        cons = np.empty((b, self.n_constraints))
        valid = np.empty(b, dtype=bool)
        eq6_batch(x, self.eps, *self._kernel_args, q, unc, cons, valid)
        self.trials += q.size
        return self._finish(q, unc, cons, valid)

    def _finish(self, q: np.ndarray, unc: np.ndarray, cons: np.ndarray, valid: np.ndarray) -> dict[str, np.ndarray]:
        """The smoothed P̃_F (sigmoid of Q_F, mean over the perturbed trials) and the objective."""
        with np.errstate(over='ignore'):
            smooth = 1.0 / (1.0 + np.exp(-q[:, 1:] / self.ctx.params.smoothing_scale))
        pf = smooth.mean(axis=1) if self.eps.shape[0] else np.zeros(q.shape[0])
        objective = -pf + self.penalty * unc
        return {'objective': objective, 'constraints': cons, 'pf_smoothed': pf, 'uncertainty': unc,
                'q_nominal': q[:, 0], 'valid_nominal': valid}

    def details_reference(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """:meth:`details` by numpy around :func:`contacts.find_contacts` (the reference of the compiled path)."""
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
        ok = ~con.no_contact[:, 0]
        var = np.full((b, 2), ctx.max_variance)
        if ok.any():
            pts = np.stack([con.c1[ok, 0], con.c2[ok, 0]], axis=1)
            var[ok] = bilinear(ctx.variance, ctx.geometry, pts)
        unc = var.sum(axis=1)
        unit = SCP_UNIT_M
        width = np.linalg.norm(j2 - j1, axis=1)
        cons = [(width - ctx.gripper.max_opening) / unit, -con.clearance1[:, 0] / unit, -con.clearance2[:, 0] / unit]
        if self.antipodal:
            n1, n2 = con.n1[:, 0], con.n2[:, 0]
            # Eq. 5 on the contact line v = (c1 − c2)/‖c1 − c2‖ (see docs/planning.md).
            line = con.c1[:, 0] - con.c2[:, 0]
            dist = np.hypot(line[:, 0], line[:, 1])
            has_line = con.valid[:, 0] & (dist > 1e-9 * unit)
            v = line / np.where(has_line, dist, 1.0)[:, None]
            beta, alpha = ctx.params.beta + 2.0 * ctx.params.constraint_tol, ctx.params.antipodal_alpha
            c_alpha = np.where(has_line, np.sum((n1 + n2) ** 2, axis=1) - alpha, 4.0 - alpha)
            c_b1 = np.where(has_line, beta - np.sum(n1 * v, axis=1), 1.0 + beta)
            c_b2 = np.where(has_line, beta + np.sum(n2 * v, axis=1), 1.0 + beta)
            cons += [c_alpha, c_b1, c_b2]
        cons = np.stack(cons, axis=1)
        cons = np.where(np.isfinite(cons), cons, 10.0)
        valid = con.valid[:, 0] & (width <= ctx.gripper.max_opening * (1 + 1e-9))
        return self._finish(q, unc, cons, valid)

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = self.details(x)
        return d['objective'], d['constraints']
