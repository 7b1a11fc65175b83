"""Evaluation of a real capture with ground truth: segmentation as segmentation_node runs it, GPIS, a planner,
simulated executions on the true shape (``import-rgbd --evaluate`` and ``evaluate-real``).

:func:`prepare_real` segments the scene and fits the GPIS once (:class:`RealFit`); :func:`evaluate_grasp`
plans one method with one seed on it and executes the grasp on the truth, through the camera frame
(plan grid → camera → ground-truth grid).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.core.noise_model import SensorModel
from gpis_grasp_ros.core.pipeline import posterior_from_grids
from gpis_grasp_ros.core.planners import PlannerParams, plan
from gpis_grasp_ros.core.sensing import SensingParams, SensingResult
from gpis_grasp_ros.data.bags import load_bag
from gpis_grasp_ros.sim.execution import ExecutionOutcome
from gpis_grasp_ros.tools.evaluation.tasks import SceneFit, fit_scene
from gpis_grasp_ros.tools.evaluation.truth import TrueShape

#: SDF noise variance (m^2) of every cell when planning on the ground truth (``oracle``): a near-certain shape
ORACLE_NOISE_M2 = 1e-6


@dataclass
class RealEvaluation:
    """Figures of one imported capture (see :func:`evaluate_bag`)."""

    bag: str
    occupancy_iou: float  # target occupancy (>= 0.5) vs the ground truth, on the segmentation grid
    mean_shape_iou: float  # GPIS mean shape {mean < 0} vs the ground truth
    successes: int  # of ``trials`` simulated executions of the GP-GPIS-OPT grasp in force closure on the truth
    trials: int
    p_f: float
    jaw_clearance_m: float  # smallest distance (m) from a jaw centre to another object seen on the table
    #                          (evidence more than 1 cm outside the true target)
    objects_seen: int
    tilt_deg: float
    message: str = ''
    outcome: ExecutionOutcome | None = None  # how the executions failed (None: no grasp)
    #: smallest distance (m) from a jaw centre to another object of the truth (its obstacle distance there; negative:
    #: the jaw is inside one), inf when the truth has no other object, NaN without a grasp
    true_clearance_m: float = float('nan')


@dataclass
class RealFit:
    """A segmented capture with its GPIS and its truth on the planning grid: what every grasp of it shares."""

    name: str
    fit: SceneFit
    true_shape: TrueShape
    truth: np.ndarray  # bool, the true shape at the planning grid's cell centres
    true_obstacles: np.ndarray | None  # bool, the truth's other objects at the planning cell centres (None: none)
    occupancy_iou: float
    mean_shape_iou: float
    others: np.ndarray  # (K, 2) planning-grid feet of the other objects seen (fragments of the target removed)
    gripper: GripperParams
    _oracle: Any = None

    def posterior(self, oracle: bool = False) -> Any:
        """The perceived posterior, or (``oracle``) the truth's occupancy sampled at the planning grid's cell
        centres (0 or 100), every cell trained with :data:`ORACLE_NOISE_M2`, with the truth's other objects sampled
        there as its obstacles (the world the perception would give at best)."""
        if not oracle:
            return self.fit.posterior
        if self._oracle is None:
            g = self.fit.sensing.geometry
            obstacles = None if self.true_obstacles is None else np.where(self.true_obstacles, 100, 0).astype(np.int8)
            self._oracle = posterior_from_grids(np.where(self.truth, 100, 0).astype(np.int8),
                                                np.full(g.shape, ORACLE_NOISE_M2), g, obstacles=obstacles)
        return self._oracle


def _other_objects_xy(result: SensingResult) -> np.ndarray:
    """Table-plane feet (grid x, y in m) of the evidence pixels of objects other than the target."""
    other = (result.labels_px > 0) & ~result.object_mask & np.isfinite(result.mean_depth)
    pts = result.intrinsics.rays()[other] * result.mean_depth[other][:, None]
    feet = pts - (pts @ result.table.n + result.table.offset_m)[:, None] * result.table.n
    return result.geometry.from_sensor(feet)[0]


def sensing_params(target_px: tuple[float, float], sensor: str = 'realsense_d400',
                   grid_size: int = SensingParams.grid_size,
                   clear_body_height_m: float = 0.0) -> SensingParams:
    """segmentation_node's parameters for ``target:=pixel`` at ``target_px`` (pixels of the scene's image)."""
    return SensingParams(sensor=SensorModel.named(sensor), target='pixel', target_point=tuple(target_px),
                         grid_size=int(grid_size), clear_body_height_m=float(clear_body_height_m))


def prepare_real(scene: Any, params: SensingParams, name: str = '') -> RealFit:
    """Segment ``scene`` (with ground truth), fit the GPIS, sample the truth at the planning grid and find the
    other objects seen. Raises ValueError when the scene has no truth or segmentation refuses the target."""
    if scene.true_sdf is None or scene.true_geometry is None:
        raise ValueError(f'{name}: no ground truth in the bag')
    fit = fit_scene(scene, params)
    posterior, result = fit.posterior, fit.sensing
    g = result.geometry
    true_shape = TrueShape(scene.true_sdf, scene.true_geometry, g, obstacles=scene.true_obstacles)
    truth = true_shape.values_at(g.cell_centers()) < 0
    true_obstacles = true_shape.obstacles_at(g.cell_centers())
    true_obstacles = None if true_obstacles is None else true_obstacles < 0
    mean_shape = posterior.mean < 0

    def iou(a: np.ndarray) -> float:
        return float((a & truth).sum() / max((a | truth).sum(), 1))

    others = _other_objects_xy(result)  # other objects seen, minus fragments of the true target (1 cm)
    if len(others):
        others = others[~(true_shape.values_at(others) < 0.01)]
    return RealFit(name, fit, true_shape, truth, true_obstacles, iou(result.occupancy >= 0.5), iou(mean_shape), others,
                   PlannerParams().gripper)  # the planner's (metric) gripper executes


def evaluate_grasp(rf: RealFit, method: str, seed: int, trials: int = 20, oracle: bool = False,
                   planner: PlannerParams | None = None) -> RealEvaluation:
    """Plan ``method`` with ``seed`` on the perceived shape (or the truth, ``oracle``) and execute the grasp
    ``trials`` times on the truth (execution seed ``seed``). The IoUs are the perceived ones."""
    planner = PlannerParams() if planner is None else planner
    result = rf.fit.sensing
    grasp = plan(method, rf.posterior(oracle), planner, seed=seed)
    if not grasp.success:
        return RealEvaluation(rf.name, rf.occupancy_iou, rf.mean_shape_iou, 0, trials, float('nan'), float('nan'),
                              result.objects_seen, result.table.tilt_deg, grasp.message)
    outcome = rf.true_shape.execute_outcome(grasp.jaw1, grasp.jaw2, rf.gripper, trials, np.random.default_rng(seed))
    others = rf.others
    clearance = (float(min(np.linalg.norm(others - np.asarray(j), axis=1).min() for j in (grasp.jaw1, grasp.jaw2)))
                 if len(others) else float('inf'))
    true_d = rf.true_shape.obstacles_at(np.stack([grasp.jaw1, grasp.jaw2]))
    true_clearance = float('inf') if true_d is None else float(true_d.min())
    return RealEvaluation(rf.name, rf.occupancy_iou, rf.mean_shape_iou, outcome.closed, trials, float(grasp.p_f),
                          clearance, result.objects_seen, result.table.tilt_deg, grasp.message, outcome, true_clearance)


def evaluate_bag(path: str | Path, target_px: tuple[float, float], sensor: str = 'realsense_d400',
                 trials: int = 20, seed: int = 0, oracle: bool = False, grid_size: int = SensingParams.grid_size,
                 method: str = 'gp-gpis-opt', clear_body_height_m: float = 0.0,
                 uncertainty_penalty: float | None = None) -> RealEvaluation:
    """Segment an imported capture as segmentation_node does (one frame, ``target:=pixel``), fit the
    GPIS, plan GP-GPIS-OPT (or ``method``, one of :data:`~gpis_grasp_ros.core.planners.METHODS`) and execute it
    ``trials`` times on the bag's ground truth (through the camera frame: plan grid → camera → ground-truth grid).

    ``oracle``: plan on the ground truth itself instead of the perceived shape - its occupancy sampled at
    the planning grid's cell centres (0 or 100), every cell trained with ``ORACLE_NOISE_M2`` - the best any
    perception can give the planner at the grid's resolution. The IoUs are still the perceived ones.
    ``grid_size``: forced M of the M x M planning grid (segmentation_node's ``grid_size``; 0 = from the target's
    extent and the cell size); ``clear_body_height_m``: a clear target body's known height (m; segmentation_node's
    ``clear_body_height``, 0 = the priors); ``uncertainty_penalty``: λ of eq. 4/6 per m² of SDF variance
    (planner_node's ``uncertainty_penalty``; None = its default)."""
    return evaluate_seeds(path, target_px, [seed], sensor, trials, oracle, grid_size, method, clear_body_height_m,
                          uncertainty_penalty)[0]


def evaluate_seeds(path: str | Path, target_px: tuple[float, float], seeds: Sequence[int],
                   sensor: str = 'realsense_d400', trials: int = 20, oracle: bool = False,
                   grid_size: int = SensingParams.grid_size,
                   method: str = 'gp-gpis-opt', clear_body_height_m: float = 0.0,
                   uncertainty_penalty: float | None = None) -> list[RealEvaluation]:
    """:func:`evaluate_bag` for each planner and execution seed of ``seeds``: the capture is segmented and the
    GPIS fitted once."""
    planner = PlannerParams() if uncertainty_penalty is None else PlannerParams(
        uncertainty_penalty=float(uncertainty_penalty))  # checked before the segmentation
    params = sensing_params(target_px, sensor, grid_size, clear_body_height_m)
    rf = prepare_real(load_bag(path, frames=1), params, str(path))
    return [evaluate_grasp(rf, method, seed, trials, oracle, planner) for seed in seeds]
