"""Grasp planners on a GPIS posterior (paper sections VI and VII-B), one function per method.

Every planner returns a :class:`GraspResult`; :func:`plan` dispatches by name:

* ``'gp-m'``  — GP-M: best Q_F on the mean SDF among K heuristic samples (VII-B).
* ``'gp-p'``  — GP-P: best Monte-Carlo P_F among K heuristic samples × S shape samples.
* ``'gp-d'``  — GP-D: maximise P̃_F on the mean SDF with finite differences (no penalty).
* ``'gp-u'``  — GP-U: GP-D plus the uncertainty penalty λ (eq. 4).
* ``'gp-gpis-opt'`` / ``'gp-g'`` — GP-GPIS-OPT, Algorithm 1: N_g heuristic initial grasps, each
  refined by SCP on eq. 6 with the antipodal constraints (eq. 5); best objective wins.
* ``'gp-gpis-opt-reranked'`` — beyond the paper: GP-GPIS-OPT's N_g local optima re-scored by
  Monte-Carlo P_F (an independent sample set); the best P_F wins.

Design decisions (where the paper is silent or ambiguous):

* **Units.** Jaws are metric (x, y) in the grid/sensor frame. The optimiser works in grid cells
  (x = (col1, row1, col2, row2)) so trust region, finite-difference step and penalties are
  resolution-independent. The paper's λ multiplies σ² of a GPIS whose SDF was in cells, so the
  penalty is ``λ (σ²(c1) + σ²(c2)) / resolution²`` with σ² in m² (``uncertainty_penalty`` λ is per
  cell², default 2.0 as in the paper).
* **P̃_F (VI-A)** is the probability of force closure on the *mean* SDF under grasp perturbation
  only. Estimated with K_p = ``n_perturbations`` (32) fixed standard-normal draws (common random
  numbers: the same draws at every point, so finite differences see a deterministic function;
  an SCP run to convergence fits those draws, and with K_p = 16 converged optima on the
  transparent-part test scene reached P̃_F ≈ 0.94 on the 16 draws but 0.90 on 4000 fresh ones
  and a Monte-Carlo P_F of 0.68; 32 draws keep the optimum honest at ~1.2x the cost)
  and a smoothed indicator ``sigmoid(Q_F / smoothing_scale)`` instead of 1[Q_F > 0] (degenerate
  trials count 0). Contacts move continuously with the jaws (bilinear SDF, continuous contact
  patch), so P̃_F is smooth enough for finite differences. The smoothing scale 0.02 is ~6 % of the
  Q_F of an ideal antipodal grasp (γ/sqrt(2 + γ²) = 0.33 for γ = 0.5).
* **Constraints (eq. 5/6)**, evaluated at the unperturbed grasp on the mean shape, on the
  *contact line* ``v̂ = (c1 − c2)/‖c1 − c2‖``: ``‖n1 + n2‖² <= α``, ``n1ᵀv̂ >= β``,
  ``−n2ᵀv̂ >= β``. Eq. 5 writes v = ĝ1 − ĝ2, which for point contacts on the approach line is the
  contact line; with the jaw-patch contact model (:mod:`contacts`) the contacts lie off the jaw
  axis (up to ~25° on the shipped bags), and the guarantee "β = cos(arctan γ) ⇒ force closure"
  (Nguyen: the line through the contacts inside both friction cones) holds only for the contact
  line, so that is what is constrained. The paper's ``β‖v‖²`` mixes units (n is unit, v is a
  length); with unit normals the meaningful form is ``n1ᵀv >= β‖v‖``, i.e. the angle between each
  normal and the contact line is at most arctan γ. β is tightened by 2·``constraint_tol`` so a
  grasp feasible to ``constraint_tol`` still has both angles strictly inside the friction cone:
  every *feasible* local optimum is in force closure on the mean shape (Q_F > 0; property test
  over all shipped bags in ``test/core/test_antipodal_guarantee.py``). Two more constraints
  make the grasp a member of the candidate set 𝒢 and physically executable: the opening
  ``‖g1 − g2‖ <= w_g`` and jaw clearance (both jaw faces start in free space of the mean shape,
  SDF >= 0). A grasp with no valid contact on the mean (no contact, jaw inside, coincident
  contacts or a vanishing SDF gradient at a contact) gets the worst value of each antipodal
  constraint.
* **α = 0.5.** With ‖n1‖ = ‖n2‖ = 1, ‖n1 + n2‖² = 4 sin²(φ/2) where φ is the angle between n1 and
  −n2. The β constraints alone allow φ up to 2 arctan γ = 53° (both normals tilted to the limit in
  opposite senses — a wedge that friction only barely holds); α = 0.5 caps φ at 41°, so the α
  constraint is active only for such wedge-like grasps.
* **Initial grasps (Algorithm 1, line 7).** "Valid" = contacts on the mean shape, both jaw faces
  in free space, opening <= w_g. 4 N_g valid heuristic grasps are drawn and N_g kept by
  farthest-point sampling in grasp space, so the restarts cover the object rather than repeat
  near-identical grasps (the heuristic picks among a few hundred surface points). The SCP runs
  in lock-step for all restarts (one batched objective call and one call of the exact
  active-set QP solver for all restarts per iteration; eq. 6 on the perturbed jaws uses the
  compiled contact kernel of :mod:`contact_kernel`) until each restart meets the convergence
  test of :mod:`scp` — step tolerance
  ``scp_step_tol_cells`` (0.05 cell, a tenth of σ_g) with objective tolerance
  ``scp_objective_tol`` (1e-4), or a stationary model (``scp_model_tol``), or a trust box below
  ``trust_radius_min_cells`` — or the cap ``max_scp_iterations`` (100, a safeguard; on the
  shipped bags the longest run takes ~50 QP solves). ``RestartInfo`` reports per restart
  whether it converged, why it stopped, its eq. 6 history per iteration and any failed QP;
  the opening constraint, satisfied to
  ``constraint_tol``, is then made exact by shrinking the jaws about their centre. Feasible local
  optima take precedence over infeasible ones when picking the best objective.
* **GP-D / GP-U (VII-B).** Our reading of "optimizes P_F on the mean SDF with finite differences":
  the same SCP/finite-difference optimiser from N_g = ``n_initial_grasps`` (20) valid heuristic
  initial grasps, as the paper uses N_g = 20 for GP-G, GP-D and GP-U, with only the
  candidate-set constraints (opening, clearance) — no antipodal constraints (GP-D: λ = 0; GP-U:
  the λ penalty). ``'gp-d-single'`` / ``'gp-u-single'`` are extras (not in the paper) that run
  from ONE initial grasp, to show what the restarts contribute.
* **Cancellation and progress.** Every planner takes an optional :class:`PlanControl`: its
  ``should_stop`` is polled after every SCP iteration, after every finished restart and before
  every Monte-Carlo chunk of about 8k trials (a few ms each on a 25 x 25 grid); inside an SCP
  iteration, which advances all N_g restarts together, also between batches of
  :data:`SCP_EVAL_CHUNK` eq. 6 evaluations and every 20 ms while the batched QP is solved (so a
  stop takes effect within ~0.1 s even for N_g = 1000; results are the same with or without a
  control), and
  ``on_progress`` gets a :class:`PlanProgress` after each restart (or GP-M candidate chunk, or
  GP-P halving round). A stopped plan returns ``success=False``, ``message='stopped: <reason>'``
  and ``stopped=<reason>``.
* **GP-P adaptive Monte Carlo** (successive halving, cf. adaptive sampling [22]): all K
  candidates are scored on the first ~S/η^(R−1) shape samples, the best 1/η (by P̂_F, ties by
  Q_F on the mean) are scored on more samples, and so on; the last round uses all S samples,
  so the final choice is by full S-sample P_F. ``gp_p_adaptive=False`` scores every candidate
  on all S samples (the paper's brute force).
* **Reported P_F.** Every method's final ``p_f`` comes from the same routine on the same
  *evaluation* sample set (S shapes and perturbations drawn from a dedicated random stream of
  the seed, independent of any sample used for selection), so methods are comparable and GP-P's
  estimate carries no winner's-curse bias. ``planning_time`` is the (wall-clock) time to choose the grasp,
  ``planning_cpu_time`` the CPU time of the process over the same span (less sensitive to other
  jobs on a shared machine); ``evaluation_time`` the time of that final estimate.
* **Seeding.** ``np.random.SeedSequence(seed)`` is split into independent streams (candidate
  sampling, perturbation draws, selection samples, evaluation samples); the same seed and the
  same posterior give the same grasp.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from gpis_grasp_ros.core.contacts import GripperParams, SdfBank, bilinear, find_contacts, perturb_grasps
from gpis_grasp_ros.core.gpis import GpisPosterior
from gpis_grasp_ros.core.gpis import center_of_mass as sdf_center_of_mass
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.quality import (
    ShapeSamples,
    draw_shape_samples,
    force_closure_successes,
    grasp_quality,
    probability_force_closure,
    torque_scale,
)
from gpis_grasp_ros.core.scp import ScpProgress, ScpResult, ScpSettings, scp_minimize

METHODS = ('gp-gpis-opt', 'gp-gpis-opt-reranked', 'gp-p', 'gp-m', 'gp-d', 'gp-u', 'gp-d-single', 'gp-u-single')
ALIASES = {'gp-g': 'gp-gpis-opt', 'gp-g-reranked': 'gp-gpis-opt-reranked'}


@dataclass(frozen=True)
class PlannerParams:
    """Planner settings. Lengths in metres unless the name says cells."""

    gripper: GripperParams = field(default_factory=GripperParams)
    n_initial_grasps: int = 20  # N_g (restarts of GP-GPIS-OPT, GP-D and GP-U)
    n_grasp_samples: int = 1000  # K heuristic candidates of GP-M / GP-P
    n_shape_samples: int = 1000  # S shape samples for Monte-Carlo P_F
    uncertainty_penalty: float = 2.0  # λ, per cell² of SDF variance (eq. 4)
    antipodal_alpha: float = 0.5  # α of eq. 5
    antipodal_beta: float | None = None  # β of eq. 5; None -> cos(arctan γ)
    n_perturbations: int = 32  # K_p common-random-number perturbations for P̃_F (see the module docstring)
    smoothing_scale: float = 0.02  # Q_F scale of the sigmoid replacing 1[Q_F > 0] in P̃_F
    fd_step_cells: float = 0.2  # finite-difference step of the SCP, cells
    trust_radius_cells: float = 1.0  # initial SCP trust box half-width, cells
    trust_radius_min_cells: float = 0.05  # step tolerance: no improving step above it -> converged
    trust_radius_max_cells: float = 3.0
    max_scp_iterations: int = 100  # QP solves per restart (a cap; runs stop at the convergence test)
    scp_step_tol_cells: float = 0.05  # step tolerance of the convergence test (∞-norm, cells)
    scp_objective_tol: float = 1e-4  # objective tolerance: merit change of an accepted step
    scp_model_tol: float = 1e-5  # predicted merit improvement below which the model is stationary
    scp_quasi_newton: bool = False  # damped-BFGS curvature in the SCP model (else linear + proximal term)
    constraint_tol: float = 1e-3
    gp_p_adaptive: bool = True  # successive halving for GP-P
    gp_p_halving_rate: int = 4  # η
    gp_p_min_samples: int = 16  # samples per candidate in the first round
    max_sampling_rounds: int = 20  # heuristic batches tried when looking for valid initial grasps
    seed: int | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.uncertainty_penalty) and self.uncertainty_penalty >= 0):
            raise ValueError(f'uncertainty penalty λ must be a finite number >= 0 (per cell² of SDF variance), '
                             f'got {self.uncertainty_penalty}')

    @property
    def beta(self) -> float:
        """β of eq. 5 (default cos(arctan γ))."""
        return self.gripper.beta if self.antipodal_beta is None else float(self.antipodal_beta)

    def penalty_per_m2(self, geometry: GridGeometry) -> float:
        """λ expressed per m² of SDF variance on ``geometry`` (λ_cells / resolution²)."""
        return self.uncertainty_penalty / geometry.resolution ** 2

    @staticmethod
    def penalty_from_per_m2(penalty_per_m2: float, geometry: GridGeometry) -> float:
        """Convert a λ given per m² of variance (e.g. a service request) to this class's per-cell² λ."""
        return float(penalty_per_m2) * geometry.resolution ** 2


@dataclass
class RestartInfo:
    """One SCP run of an optimising planner (jaws in m; objective of eq. 6, to maximise).

    ``converged`` the run met the convergence test of :mod:`scp` (``reason`` says which test, or
    why it stopped: iteration cap, constraints violated at the maximum penalty, failed QPs);
    ``iterations`` QP solves; ``objective_history`` the eq. 6 value at the start and after every
    SCP iteration (before the final opening fix, so its last entry can differ from
    ``objective`` by the shrink); ``qp_failures``/``qp_status`` failed QP solves and the last
    failure status ('' if none); ``initial_feasible`` whether the initial grasp met every
    constraint; ``feasible`` whether the returned grasp does.
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


@dataclass
class GraspResult:
    """Planned parallel-jaw grasp (all planners). Positions in m in the grid/sensor frame.

    ``axis`` unit closing direction jaw1 → jaw2; ``width`` ‖jaw2 − jaw1‖ (m); ``q_mean`` Q_F on
    the mean SDF (NaN if the grasp is degenerate there); ``p_f`` ± ``p_f_std_error`` the
    Monte-Carlo P_F on the evaluation samples; ``objective`` the method's own criterion (Q_F for
    GP-M, selection P̂_F for GP-P, eq. 4/6 value for the optimisers, MC P_F when re-ranked);
    ``iterations`` total SCP iterations (0 for sampling planners).
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
    planning_cpu_time: float = float('nan')  # CPU time (s, process-wide) of the planning part (less load-dependent)


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


def _never_stop() -> str | None:
    return None


@dataclass
class PlanControl:
    """Cooperative cancellation and progress of one :func:`plan` call.

    ``should_stop`` is polled between SCP iterations and restarts, inside an SCP iteration between
    evaluation batches and during the QP solve, and between Monte-Carlo sample chunks (every few
    tens of milliseconds at most); a non-empty reason (e.g. ``'timeout'``,
    ``'cancelled'``, ``'shutting down'``) stops the plan, which then returns
    ``GraspResult(success=False, message='stopped: <reason>', stopped=<reason>)``.
    ``on_progress`` is called after each finished restart/chunk.
    """

    should_stop: Callable[[], str | None] = _never_stop
    on_progress: Callable[[PlanProgress], None] | None = None


class _Stopped(Exception):
    """Raised at a checkpoint when the PlanControl asks to stop (caught by the planner entry points)."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class _Tracker:
    """Progress and stop bookkeeping of one plan call (no-op without a PlanControl)."""

    def __init__(self, control: PlanControl | None, total: int = 0) -> None:
        self.control = control
        self.cpu_start = time.process_time()  # CPU time (s, all threads) at the start of the plan
        self.total = int(total)
        self.done = 0
        self.best_objective = float('nan')
        self.best_p_f = float('nan')

    def check(self) -> None:
        """Raise :class:`_Stopped` if the control asks to stop."""
        if self.control is None:
            return
        reason = self.control.should_stop()
        if reason:
            raise _Stopped(str(reason))

    def step(self, best_objective: float | None = None, best_p_f: float | None = None) -> None:
        """One more restart/chunk finished: report progress, then check for a stop."""
        self.done += 1
        if best_objective is not None:
            self.best_objective = float(best_objective)
        if best_p_f is not None:
            self.best_p_f = float(best_p_f)
        if self.control is not None and self.control.on_progress is not None:
            self.control.on_progress(PlanProgress(self.done, self.total, self.best_objective, self.best_p_f))
        self.check()


class PlanningContext:
    """Everything the planners precompute from a posterior (mean-shape bank, COM, ρ, σ_g, surface)."""

    def __init__(self, posterior: GpisPosterior, params: PlannerParams) -> None:
        self.posterior = posterior
        self.params = params
        self.geometry: GridGeometry = posterior.geometry
        self.res = self.geometry.resolution
        self.gripper = params.gripper
        self.sigma_g = self.gripper.sigma_g(self.geometry)
        self.mean_bank = SdfBank(posterior.mean, self.geometry, gradients=posterior.gradient)
        self.com = posterior.center_of_mass()
        self.rho = torque_scale(posterior.mean, self.geometry, self.com)
        self.variance_cells = np.asarray(posterior.variance, dtype=np.float64) / self.res ** 2
        self.max_variance_cells = float(np.max(self.variance_cells))
        self.surface = mean_surface_points(posterior.mean, self.geometry)

    # -- evaluation on the mean shape -------------------------------------------------------
    def mean_quality(self, jaw1: np.ndarray, jaw2: np.ndarray) -> np.ndarray:
        """Q_F on the mean SDF of unperturbed grasps ``(..., 2)``; −inf when degenerate."""
        con = find_contacts(self.mean_bank, jaw1, jaw2, self.gripper)
        return grasp_quality(con, self.com, self.gripper, self.rho)


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
    normal = ctx.mean_bank.normals_at(p)
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
        vals[a:b] = ctx.mean_bank.values_cells(uv[a:b, 0, None] + t[None] * u[a:b, 0, None],
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
    normal = ctx.mean_bank.normals_at(p)
    tangent = np.stack([-normal[:, 1], normal[:, 0]], axis=1)
    p = p + rng.uniform(-0.5, 0.5, (n, 1)) * ctx.res * tangent
    for _ in range(2):
        grad = ctx.mean_bank.gradients_at(p)
        g2 = np.sum(grad * grad, axis=1)
        step = np.where(g2 > 1e-6, ctx.mean_bank.values(p) / np.maximum(g2, 1e-6), 0.0)
        p = p - np.clip(step, -ctx.res, ctx.res)[:, None] * grad
    return p


def _valid_on_mean(ctx: PlanningContext, jaw1: np.ndarray, jaw2: np.ndarray) -> np.ndarray:
    return find_contacts(ctx.mean_bank, jaw1, jaw2, ctx.gripper).valid


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
    check = checkpoint if checkpoint is not None else _never_stop
    want = max(n, oversample * n)
    j1s, j2s = [], []
    found = 0
    for _ in range(ctx.params.max_sampling_rounds):
        check()
        j1, j2 = sample_heuristic_grasps(ctx, max(2 * want, 16), rng, checkpoint=check)
        check()
        ok = _valid_on_mean(ctx, j1, j2)
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


class MeanGraspObjective:
    """Eq. 6 on the mean shape as a batch function for :func:`scp_minimize` (minimisation form).

    ``x = (col1, row1, col2, row2)`` (cells). Returns ``F = −P̃_F + λ(σ²(c1) + σ²(c2))`` (σ² in
    cells², c on the mean shape for the unperturbed grasp) and constraints ``G <= 0``:
    opening (cells), clearance of jaw 1 and 2 (cells), and with ``antipodal`` the three
    constraints of eq. 5 (see the module docstring).
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
            # Eq. 5 on the contact line v = (c1 − c2)/‖c1 − c2‖ (see the module docstring).
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


# ------------------------------------------------------------------------------------------
# Helpers shared by the planners
# ------------------------------------------------------------------------------------------

def _streams(seed: int | None) -> dict[str, np.random.Generator]:
    names = ('candidates', 'perturbations', 'selection', 'evaluation')
    children = np.random.SeedSequence(seed).spawn(len(names))
    return {k: np.random.default_rng(c) for k, c in zip(names, children, strict=True)}


def _empty_result(method: str, message: str, t_start: float, seed: int | None, **kw) -> GraspResult:
    nan2 = np.full(2, np.nan)
    return GraspResult(method=method, success=False, message=message, jaw1=nan2.copy(), jaw2=nan2.copy(),
                       center=nan2.copy(), axis=nan2.copy(), width=float('nan'), q_mean=float('nan'), p_f=0.0,
                       p_f_std_error=0.0, objective=float('nan'), planning_time=time.perf_counter() - t_start,
                       seed=seed, **kw)


def _finish(ctx: PlanningContext, method: str, jaw1: np.ndarray, jaw2: np.ndarray, objective: float,
            t_start: float, rngs: dict[str, np.random.Generator], seed: int | None, message: str = '',
            tracker: _Tracker | None = None, **kw) -> GraspResult:
    """Fill a GraspResult: geometry of the grasp, Q_F on the mean, evaluation P_F."""
    planning_time = time.perf_counter() - t_start
    planning_cpu_time = float('nan') if tracker is None else time.process_time() - tracker.cpu_start
    jaw1 = np.asarray(jaw1, dtype=np.float64).reshape(2)
    jaw2 = np.asarray(jaw2, dtype=np.float64).reshape(2)
    width = float(np.linalg.norm(jaw2 - jaw1))
    axis = (jaw2 - jaw1) / width if width > 0 else np.array([1.0, 0.0])
    q = float(ctx.mean_quality(jaw1, jaw2))
    t_eval = time.perf_counter()
    samples = evaluation_samples(ctx, rngs['evaluation'])
    est = probability_force_closure(jaw1[None], jaw2[None], samples, ctx.gripper, ctx.sigma_g,
                                    checkpoint=None if tracker is None else tracker.check)
    valid = bool(_valid_on_mean(ctx, jaw1, jaw2))
    # Success: the grasp is executable on the mean shape, or (GP-P) it closes on some shape samples.
    success = valid or bool(est.p[0] > 0)
    if not valid:
        note = 'grasp is degenerate on the mean shape (no contact, jaw in collision or opening > w_g)'
        message = f'{message}; {note}' if message else note
    return GraspResult(method=method, success=success, message=message or 'ok', jaw1=jaw1, jaw2=jaw2,
                       center=0.5 * (jaw1 + jaw2), axis=axis, width=width,
                       q_mean=q if np.isfinite(q) else float('nan'), p_f=float(est.p[0]),
                       p_f_std_error=float(est.std_error[0]), objective=float(objective),
                       planning_time=planning_time, evaluation_time=time.perf_counter() - t_eval, seed=seed,
                       planning_cpu_time=planning_cpu_time, **kw)


def evaluation_samples(ctx: PlanningContext, rng: np.random.Generator) -> ShapeSamples:
    """The S shape samples (and perturbation draws) on which every method's final P_F is estimated."""
    return draw_shape_samples(ctx.posterior, ctx.params.n_shape_samples, rng, rho=ctx.rho)


#: Points per batch of eq. 6 evaluations inside an SCP iteration (a stop check between batches:
#: 128 points = 32 restarts' finite differences, tens of ms on a 25 x 25 grid; the values do not
#: depend on the batching).
SCP_EVAL_CHUNK = 128


def _scp_settings(params: PlannerParams) -> ScpSettings:
    return ScpSettings(fd_step=params.fd_step_cells, trust_radius_init=params.trust_radius_cells,
                       trust_radius_min=params.trust_radius_min_cells,
                       trust_radius_max=params.trust_radius_max_cells, max_iterations=params.max_scp_iterations,
                       constraint_tol=params.constraint_tol, penalty_init=10.0, penalty_factor=10.0,
                       penalty_max=1e3, improve_tol=params.scp_model_tol, step_tol=params.scp_step_tol_cells,
                       objective_tol=params.scp_objective_tol, accept_ratio=0.1, trust_shrink=0.3, trust_expand=2.0,
                       prox=1e-8, prox_rel=0.1, osqp_eps=1e-4, osqp_max_iter=4000,
                       quasi_newton=params.scp_quasi_newton, trust_expand_from_step=True, prox_penalty_weight=0.01,
                       osqp_rho=0.1, osqp_rho_interval=25, eval_chunk=SCP_EVAL_CHUNK)


def _optimise(ctx: PlanningContext, method: str, n_starts: int, penalty: float, antipodal: bool,
              rngs: dict[str, np.random.Generator], t_start: float, seed: int | None,
              rerank: bool = False, tracker: _Tracker | None = None) -> GraspResult:
    """Shared body of GP-D, GP-U, GP-GPIS-OPT (and its re-ranked variant)."""
    params = ctx.params
    tracker = _Tracker(None) if tracker is None else tracker
    tracker.check()
    j1, j2 = sample_valid_grasps(ctx, n_starts, rngs['candidates'], checkpoint=tracker.check)
    if j1.shape[0] == 0:
        return _empty_result(method, 'no valid initial grasp found on the mean shape', t_start, seed)
    tracker.total = j1.shape[0]
    g = ctx.geometry
    x0 = np.concatenate([g.to_cell(j1), g.to_cell(j2)], axis=1)
    eps = rngs['perturbations'].standard_normal((params.n_perturbations, 2, 2))
    objective = MeanGraspObjective(ctx, eps, penalty, antipodal)
    pad = ctx.mean_bank.pad
    lower = np.full(4, -float(pad))
    upper = np.array([g.width - 1 + pad, g.height - 1 + pad] * 2, dtype=np.float64)
    monitor = _ScpMonitor(objective, tracker, x0.shape[0], params.constraint_tol)
    poll = tracker.check if tracker.control is not None else None
    res: ScpResult = scp_minimize(objective, x0, _scp_settings(params), lower=lower, upper=upper, monitor=monitor,
                                  poll=poll)
    feasible0 = _chunked_details(objective, x0, tracker)['constraints'].max(axis=1) <= params.constraint_tol
    # The opening constraint holds to constraint_tol; make it exact (a grasp wider than w_g is not
    # in the candidate set and would fail every Monte-Carlo trial): shrink about the centre.
    x_opt = res.x.copy()
    a, b = x_opt[:, 0:2], x_opt[:, 2:4]
    width = np.linalg.norm(b - a, axis=1)
    w_max = ctx.gripper.max_opening / ctx.res
    shrink = np.where(width > w_max, w_max / np.maximum(width, 1e-12), 1.0)[:, None]
    centre = 0.5 * (a + b)
    x_opt = np.concatenate([centre + (a - centre) * shrink, centre + (b - centre) * shrink], axis=1)
    det = _chunked_details(objective, x_opt, tracker)
    value = -det['objective']  # eq. 6 is a maximisation
    feasible = (det['constraints'].max(axis=1) <= params.constraint_tol) & det['valid_nominal']
    o1, o2 = objective.jaws(x_opt)
    restarts = [RestartInfo(initial_jaw1=j1[i], initial_jaw2=j2[i], jaw1=o1[i], jaw2=o2[i], objective=float(value[i]),
                            pf_smoothed=float(det['pf_smoothed'][i]), feasible=bool(feasible[i]),
                            converged=bool(res.converged[i]), reason=res.reason[i], iterations=int(res.iterations[i]),
                            evaluations=int(res.evaluations[i]), objective_history=-res.objective_history[i],
                            qp_failures=int(res.qp_failures[i]), qp_status=res.qp_status[i],
                            initial_feasible=bool(feasible0[i]))
                for i in range(res.x.shape[0])]
    # Algorithm 1: keep the best objective; feasible local optima take precedence.
    rank_value = np.where(feasible, value, value - 1e6)
    best = int(np.argmax(rank_value))
    chosen_value = float(value[best])
    infeasible_note = 'no restart satisfied all constraints; returning the best objective'
    message = '' if feasible[best] else infeasible_note
    if rerank:
        samples = draw_shape_samples(ctx.posterior, params.n_shape_samples, rngs['selection'], rho=ctx.rho)
        est = probability_force_closure(o1, o2, samples, ctx.gripper, ctx.sigma_g, checkpoint=tracker.check)
        for i, info in enumerate(restarts):
            info.p_f = float(est.p[i])
        # Feasible local optima still take precedence (as in Algorithm 1), then MC P_F, then eq. 6.
        best = int(np.lexsort((value, est.p, feasible))[-1])
        chosen_value = float(est.p[best])
        message = '' if feasible[best] else infeasible_note
    if restarts[best].qp_failures and not restarts[best].converged:
        note = f'chosen restart {restarts[best].reason}: {restarts[best].qp_failures} QP subproblem(s) failed'
        message = f'{message}; {note}' if message else note
    return _finish(ctx, method, o1[best], o2[best], chosen_value, t_start, rngs, seed, message, tracker=tracker,
                   iterations=int(res.iterations.sum()), converged=bool(res.converged[best]),
                   feasible=bool(feasible[best]), n_candidates=res.x.shape[0], restarts=restarts)


def _chunked_details(objective: MeanGraspObjective, x: np.ndarray, tracker: _Tracker) -> dict[str, np.ndarray]:
    """:meth:`MeanGraspObjective.details` in batches of :data:`SCP_EVAL_CHUNK` rows, a stop check before each."""
    parts = []
    for start in range(0, x.shape[0], SCP_EVAL_CHUNK):
        tracker.check()
        parts.append(objective.details(x[start:start + SCP_EVAL_CHUNK]))
    if len(parts) == 1:
        return parts[0]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


class _ScpMonitor:
    """Turns SCP iterations into PlanControl progress (one call per finished restart) and stop checks."""

    def __init__(self, objective: MeanGraspObjective, tracker: _Tracker, n: int, tol: float) -> None:
        self.objective = objective
        self.tracker = tracker
        self.tol = tol
        self.running = np.ones(n, dtype=bool)
        self.best_rank = -np.inf

    def __call__(self, prog: ScpProgress) -> None:
        tr = self.tracker
        finished = np.flatnonzero(self.running & ~prog.active)
        self.running = prog.active.copy()
        for i in finished:
            value = -float(prog.fun[i])
            rank = value if np.max(prog.constraints[i], initial=-np.inf) <= self.tol else value - 1e6
            if rank > self.best_rank:
                self.best_rank = rank
                pf = float(self.objective.details(prog.x[i:i + 1])['pf_smoothed'][0]) \
                    if tr.control is not None and tr.control.on_progress is not None else float('nan')
                tr.step(value, pf)
            else:
                tr.step()
        tr.check()


# ------------------------------------------------------------------------------------------
# The planners
# ------------------------------------------------------------------------------------------

def _prepare(posterior: GpisPosterior, params: PlannerParams | None, seed: int | None):
    params = PlannerParams() if params is None else params
    seed = params.seed if seed is None else seed
    return PlanningContext(posterior, params), _streams(seed), seed


def _stoppable(method: str):
    """Decorator: a planner body ``f(ctx, rngs, seed, t0, tracker)`` → public planner with PlanControl."""

    def wrap(body):
        def planner(posterior: GpisPosterior, params: PlannerParams | None = None, seed: int | None = None,
                    control: PlanControl | None = None) -> GraspResult:
            t0 = time.perf_counter()
            tracker = _Tracker(control)
            try:
                tracker.check()
                ctx, rngs, seed_used = _prepare(posterior, params, seed)
                return body(ctx, rngs, seed_used, t0, tracker)
            except _Stopped as stop:
                seed_used = (PlannerParams() if params is None else params).seed if seed is None else seed
                return _empty_result(method, f'stopped: {stop.reason}', t0, seed_used, stopped=stop.reason)

        planner.__name__ = body.__name__.lstrip('_')
        planner.__qualname__ = planner.__name__
        planner.__doc__ = body.__doc__
        return planner

    return wrap


@_stoppable('gp-gpis-opt')
def _plan_gp_gpis_opt(ctx, rngs, seed, t0, tracker) -> GraspResult:
    """GP-GPIS-OPT (Algorithm 1): N_g SCP runs on eq. 6 with the antipodal constraints."""
    return _optimise(ctx, 'gp-gpis-opt', ctx.params.n_initial_grasps, ctx.params.uncertainty_penalty, True, rngs,
                     t0, seed, tracker=tracker)


@_stoppable('gp-gpis-opt-reranked')
def _plan_gp_gpis_opt_reranked(ctx, rngs, seed, t0, tracker) -> GraspResult:
    """GP-GPIS-OPT whose N_g local optima are re-scored by Monte-Carlo P_F (beyond the paper)."""
    return _optimise(ctx, 'gp-gpis-opt-reranked', ctx.params.n_initial_grasps, ctx.params.uncertainty_penalty, True,
                     rngs, t0, seed, rerank=True, tracker=tracker)


@_stoppable('gp-d')
def _plan_gp_d(ctx, rngs, seed, t0, tracker) -> GraspResult:
    """GP-D: maximise P̃_F on the mean SDF by finite differences from N_g initial grasps (λ = 0)."""
    return _optimise(ctx, 'gp-d', ctx.params.n_initial_grasps, 0.0, False, rngs, t0, seed, tracker=tracker)


@_stoppable('gp-u')
def _plan_gp_u(ctx, rngs, seed, t0, tracker) -> GraspResult:
    """GP-U: GP-D plus the uncertainty penalty λ (eq. 4), N_g initial grasps."""
    return _optimise(ctx, 'gp-u', ctx.params.n_initial_grasps, ctx.params.uncertainty_penalty, False, rngs, t0,
                     seed, tracker=tracker)


@_stoppable('gp-d-single')
def _plan_gp_d_single(ctx, rngs, seed, t0, tracker) -> GraspResult:
    """GP-D from ONE initial grasp (extra, not in the paper: isolates what the restarts contribute)."""
    return _optimise(ctx, 'gp-d-single', 1, 0.0, False, rngs, t0, seed, tracker=tracker)


@_stoppable('gp-u-single')
def _plan_gp_u_single(ctx, rngs, seed, t0, tracker) -> GraspResult:
    """GP-U from ONE initial grasp (extra, not in the paper)."""
    return _optimise(ctx, 'gp-u-single', 1, ctx.params.uncertainty_penalty, False, rngs, t0, seed, tracker=tracker)


#: Candidates per progress chunk of GP-M.
GP_M_CHUNK = 250


@_stoppable('gp-m')
def _plan_gp_m(ctx, rngs, seed, t0, tracker) -> GraspResult:
    """GP-M: the heuristic candidate with the highest Q_F on the mean SDF."""
    j1, j2 = sample_heuristic_grasps(ctx, ctx.params.n_grasp_samples, rngs['candidates'])
    if j1.shape[0] == 0:
        return _empty_result('gp-m', 'the mean shape has no surface on the grid', t0, seed)
    starts = range(0, j1.shape[0], GP_M_CHUNK)
    tracker.total = len(starts)
    q = np.empty(j1.shape[0])
    for s0 in starts:
        q[s0:s0 + GP_M_CHUNK] = ctx.mean_quality(j1[s0:s0 + GP_M_CHUNK], j2[s0:s0 + GP_M_CHUNK])
        tracker.step(float(np.max(q[:s0 + GP_M_CHUNK])))
    best = int(np.argmax(q))
    if not np.isfinite(q[best]):
        return _empty_result('gp-m', 'no heuristic candidate is valid on the mean shape', t0, seed,
                             n_candidates=j1.shape[0])
    return _finish(ctx, 'gp-m', j1[best], j2[best], float(q[best]), t0, rngs, seed, tracker=tracker,
                   n_candidates=j1.shape[0])


@_stoppable('gp-p')
def _plan_gp_p(ctx, rngs, seed, t0, tracker) -> GraspResult:
    """GP-P: the heuristic candidate with the highest Monte-Carlo P_F (K candidates × S shapes)."""
    p = ctx.params
    j1, j2 = sample_heuristic_grasps(ctx, p.n_grasp_samples, rngs['candidates'])
    if j1.shape[0] == 0:
        return _empty_result('gp-p', 'the mean shape has no surface on the grid', t0, seed)
    samples = draw_shape_samples(ctx.posterior, p.n_shape_samples, rngs['selection'], rho=ctx.rho)
    tracker.check()
    tiebreak = ctx.mean_quality(j1, j2)
    best, p_hat = select_by_monte_carlo(ctx, j1, j2, samples, tiebreak, tracker=tracker)
    return _finish(ctx, 'gp-p', j1[best], j2[best], p_hat, t0, rngs, seed, tracker=tracker, n_candidates=j1.shape[0])


plan_gp_gpis_opt = _plan_gp_gpis_opt
plan_gp_gpis_opt_reranked = _plan_gp_gpis_opt_reranked
plan_gp_d = _plan_gp_d
plan_gp_u = _plan_gp_u
plan_gp_d_single = _plan_gp_d_single
plan_gp_u_single = _plan_gp_u_single
plan_gp_m = _plan_gp_m
plan_gp_p = _plan_gp_p


def select_by_monte_carlo(ctx: PlanningContext, jaw1: np.ndarray, jaw2: np.ndarray, samples: ShapeSamples,
                          tiebreak: np.ndarray, tracker: _Tracker | None = None) -> tuple[int, float]:
    """Index of the candidate with the highest Monte-Carlo P_F, and that P̂_F (full sample set).

    Successive halving when ``gp_p_adaptive`` (see the module docstring), else brute force.
    ``tracker`` (internal) gets one progress step per round and a stop check per sample chunk.
    """
    tracker = _Tracker(None) if tracker is None else tracker
    p = ctx.params
    n_s = samples.n
    k = jaw1.shape[0]
    eta = max(2, int(p.gp_p_halving_rate))
    if p.gp_p_adaptive and n_s > p.gp_p_min_samples and k > 1:
        rounds = 1 + max(0, math.ceil(math.log(n_s / max(1, p.gp_p_min_samples), eta) - 1e-9))
        rounds = min(rounds, 1 + max(0, math.ceil(math.log(k, eta))))
    else:
        rounds = 1
    alive = np.arange(k)
    succ = np.zeros(k, dtype=np.int64)
    used = 0
    tracker.total = rounds
    for r in range(rounds):
        n_r = n_s if r == rounds - 1 else max(1, math.ceil(n_s / eta ** (rounds - 1 - r)))
        succ[alive] += force_closure_successes(jaw1[alive], jaw2[alive], samples, ctx.gripper, ctx.sigma_g,
                                               start=used, stop=n_r, checkpoint=tracker.check)
        used = n_r
        lead = float(succ[alive].max(initial=0) / max(n_r, 1))
        tracker.step(lead, lead)
        if r < rounds - 1:
            keep = max(1, math.ceil(alive.size / eta))
            order = np.lexsort((-tiebreak[alive], -succ[alive]))
            alive = alive[order[:keep]]
    order = np.lexsort((-tiebreak[alive], -succ[alive]))
    best = int(alive[order[0]])
    return best, float(succ[best] / n_s)


_PLANNERS = {
    'gp-gpis-opt': plan_gp_gpis_opt,
    'gp-gpis-opt-reranked': plan_gp_gpis_opt_reranked,
    'gp-p': plan_gp_p,
    'gp-m': plan_gp_m,
    'gp-d': plan_gp_d,
    'gp-u': plan_gp_u,
    'gp-d-single': plan_gp_d_single,
    'gp-u-single': plan_gp_u_single,
}


def canonical_method(method: str) -> str:
    """Canonical planner name of ``method`` (aliases resolved); ValueError if unknown."""
    name = (method or 'gp-gpis-opt').strip().lower()
    name = ALIASES.get(name, name)
    if name not in _PLANNERS:
        valid = ', '.join(list(METHODS) + sorted(ALIASES))
        raise ValueError(f'unknown grasp planner {method!r}; valid names: {valid}')
    return name


def plan(method: str, posterior: GpisPosterior, params: PlannerParams | None = None,
         seed: int | None = None, control: PlanControl | None = None) -> GraspResult:
    """Plan a grasp with the named method (see :data:`METHODS`; 'gp-g' is an alias of 'gp-gpis-opt').

    ``control`` (optional) makes the plan cooperatively cancellable and reports progress (see
    :class:`PlanControl`); ``None`` runs to the end without callbacks.
    """
    return _PLANNERS[canonical_method(method)](posterior, params, seed, control)


def execute_grasp_trials(true_sdf: np.ndarray, true_geometry: GridGeometry, jaw1: np.ndarray, jaw2: np.ndarray,
                         gripper: GripperParams, trials: int, rng: np.random.Generator,
                         center_of_mass: np.ndarray | None = None) -> int:
    """Number of force-closure successes of ``trials`` executions of grasp (jaw1, jaw2) (m) on a true SDF.

    Each trial perturbs the jaws with σ_g (V-B), closes them on ``true_sdf`` (m, on
    ``true_geometry``, which may differ from the planning grid — everything is metric) and checks
    Q_F > 0 with normals from the true SDF's finite differences. σ_g is
    ``gripper.position_noise`` when set (resolve it on the planning grid with
    ``GripperParams.resolved``), else ``position_noise_cells`` cells of ``true_geometry``.
    ``center_of_mass`` (m) defaults to that of {true_sdf < 0}. A commanded opening above w_g
    fails every trial.
    """
    jaw1 = np.asarray(jaw1, dtype=np.float64).reshape(2)
    jaw2 = np.asarray(jaw2, dtype=np.float64).reshape(2)
    if trials <= 0 or np.linalg.norm(jaw2 - jaw1) > gripper.max_opening * (1 + 1e-9) + 1e-12:
        return 0
    sdf = np.asarray(true_sdf, dtype=np.float64)
    bank = SdfBank(sdf, true_geometry)
    com = sdf_center_of_mass(sdf[None], true_geometry)[0] if center_of_mass is None else np.asarray(center_of_mass)
    rho = torque_scale(sdf, true_geometry, com)
    eps = rng.standard_normal((int(trials), 2, 2))
    g1, g2 = perturb_grasps(jaw1, jaw2, eps, gripper.sigma_g(true_geometry))
    con = find_contacts(bank, g1, g2, gripper, check_opening=False)
    q = grasp_quality(con, com, gripper, rho)
    return int(np.count_nonzero(q > 0))


__all__ = [
    'METHODS', 'GraspResult', 'MeanGraspObjective', 'PlanControl', 'PlanProgress', 'PlannerParams', 'PlanningContext',
    'RestartInfo', 'canonical_method', 'evaluation_samples', 'execute_grasp_trials', 'mean_surface_points', 'plan',
    'plan_gp_d', 'plan_gp_d_single', 'plan_gp_gpis_opt', 'plan_gp_gpis_opt_reranked', 'plan_gp_m', 'plan_gp_p',
    'plan_gp_u', 'plan_gp_u_single',
    'sample_heuristic_grasps', 'sample_valid_grasps', 'select_by_monte_carlo',
]
