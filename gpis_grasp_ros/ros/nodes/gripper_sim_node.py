"""gripper_sim_node: a simulated parallel-jaw gripper standing in for the PR2's.

Subscribes the bag's latched ground truth (``ground_truth/sdf``, ``ground_truth/center_of_mass`` and, when the
scene has other labelled objects, ``ground_truth/obstacles``, their signed distance on the SDF's grid, which the
jaws may neither start in nor close on; never read by segmentation, GPIS or planner) and serves ``execute_grasp``
(gpis_grasp_interfaces/ExecuteGrasp): each trial perturbs the jaws with the positioning noise
sigma_g (section V-B), closes them on the TRUE shape and checks force closure with the same
Ferrari-Canny code the planner uses. Jaw positions and the centre of mass are camera-frame points;
they are mapped into the ground-truth grid through the camera frame (``GridGeometry.from_sensor``:
orthogonal projection onto the true table plane), so grasps planned on a fitted, tilted table frame
are executed on tilted ground truth (head-camera bags) correctly.
"""

from __future__ import annotations

import sys
import threading
from typing import Any

import numpy as np
from geometry_msgs.msg import PointStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup

from gpis_grasp_interfaces.msg import FloatGrid
from gpis_grasp_interfaces.srv import ExecuteGrasp
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.ros import validation
from gpis_grasp_ros.ros.nodes.common import (
    LATCHED_QOS,
    SERVICE_QOS,
    GuardedNode,
    guarded,
    guarded_service,
    log_startup,
    run_node,
)
from gpis_grasp_ros.ros.nodes.shared_params import check_gripper, gripper_params
from gpis_grasp_ros.ros.params import ParamTable
from gpis_grasp_ros.sim.execution import execute_grasp_outcome

MAX_TRIALS = 100000
#: Jaws closer than this (m) are the same point: no grasp to execute.
MIN_JAW_SEPARATION = 1e-4


#: The simulated gripper: the planner's (the same defaults, so P_F predicts what this node executes).
PARAMETERS = ParamTable('gripper_sim_node', gripper_params(
    ('jaw_width', 'max_opening', 'friction_coefficient', 'position_noise', 'contact_patch')), checks=[check_gripper])


def build_gripper(v: dict[str, Any]) -> GripperParams:
    """Parameter values → :class:`GripperParams` (ValueError names the parameter)."""
    return GripperParams(**PARAMETERS.kwargs(v, GripperParams))


class GripperSimNode(GuardedNode):
    """Executes grasps on the ground-truth SDF of the replayed scene."""

    def __init__(self, **kwargs) -> None:
        super().__init__('gripper_sim_node', **kwargs)
        self.limits = validation.Limits()
        self.gripper: GripperParams = PARAMETERS.watch(self, build_gripper, self._apply_gripper)
        self._lock = threading.Lock()
        self._sdf = None
        self._geometry = None
        self._com = None
        self._obstacles = None  # (values, geometry) of ground_truth/obstacles
        work = MutuallyExclusiveCallbackGroup()  # apart from the parameter services (answered during trials)
        self.create_subscription(FloatGrid, 'ground_truth/sdf', guarded(self, 'ground_truth/sdf', self._on_sdf),
                                 LATCHED_QOS, callback_group=work)
        self.create_subscription(FloatGrid, 'ground_truth/obstacles',
                                 guarded(self, 'ground_truth/obstacles', self._on_obstacles), LATCHED_QOS,
                                 callback_group=work)
        self.create_subscription(PointStamped, 'ground_truth/center_of_mass',
                                 guarded(self, 'ground_truth/center_of_mass', self._on_com), LATCHED_QOS,
                                 callback_group=work)
        self.create_service(ExecuteGrasp, 'execute_grasp', guarded_service(self, 'execute_grasp', self._on_execute),
                            qos_profile=SERVICE_QOS, callback_group=work)
        log_startup(self, ['ground_truth/sdf', 'ground_truth/center_of_mass', 'ground_truth/obstacles'], [],
                    ['jaw_width', 'max_opening', 'friction_coefficient', 'position_noise'],
                    services=['execute_grasp'])

    def _apply_gripper(self, gripper: GripperParams) -> None:
        self.gripper = gripper

    def _true_grid(self, msg: FloatGrid, topic: str) -> tuple[np.ndarray, GridGeometry]:
        """A ground-truth FloatGrid's values (m, float64) and geometry; ValueError names what is wrong."""
        validation.check_stamp(msg.header, f'FloatGrid {topic}')
        validation.check_map_meta_data(msg.info, validation.Limits(max_grid_cells=4_000_000, min_resolution=1e-5,
                                                                   min_extent=self.gripper.jaw_width),
                                       f'FloatGrid {topic}')
        values, geometry = messages.float_grid_to_numpy(msg)
        if not np.isfinite(values).all():
            raise ValueError(f'FloatGrid {topic}.data has {int((~np.isfinite(values)).sum())} non-finite value(s)')
        return values.astype(np.float64), geometry

    def _on_sdf(self, msg: FloatGrid) -> None:
        try:
            values, geometry = self._true_grid(msg, 'ground_truth/sdf')
            if not (values < 0).any():
                raise ValueError('FloatGrid ground_truth/sdf.data has no cell inside the object (no value < 0)')
        except ValueError as exc:
            self.reject(f'ignoring ground_truth/sdf: {exc}')
            return
        with self._lock:
            self._sdf, self._geometry = values, geometry
        self.get_logger().info(f'ground truth SDF received: {geometry.height}x{geometry.width} cells')

    def _on_obstacles(self, msg: FloatGrid) -> None:
        try:
            values, geometry = self._true_grid(msg, 'ground_truth/obstacles')
        except ValueError as exc:
            self.reject(f'ignoring ground_truth/obstacles: {exc}')
            return
        with self._lock:
            self._obstacles = (values, geometry)
        self.get_logger().info(f'ground truth obstacles received: {int((values < 0).sum())} cells inside another '
                               'object')

    def _on_com(self, msg: PointStamped) -> None:
        try:
            xyz = validation.check_point(msg, 'PointStamped ground_truth/center_of_mass.point', self.limits)
            with self._lock:
                geometry = self._geometry
            if geometry is not None:  # within the grid's reach (checked again at execution otherwise)
                validation.check_on_grid(geometry.from_sensor(xyz)[0], geometry, 'ground_truth/center_of_mass')
        except ValueError as exc:
            self.reject(f'ignoring ground_truth/center_of_mass: {exc}')
            return
        with self._lock:
            self._com = np.asarray(xyz, dtype=np.float64)[:3]  # camera frame; into the truth grid at execution

    def _on_execute(self, request: ExecuteGrasp.Request, response: ExecuteGrasp.Response) -> ExecuteGrasp.Response:
        response.success = False
        gripper = self.gripper
        with self._lock:
            true_sdf, geometry, com, obstacles = self._sdf, self._geometry, self._com, self._obstacles
        if true_sdf is None:
            response.message = ("no ground truth received yet on "
                                f"'{self.resolve_topic_name('ground_truth/sdf')}'")
            return response
        if obstacles is not None:
            if obstacles[1] != geometry:
                og = obstacles[1]
                response.message = ("ground_truth/obstacles is not on the grid of ground_truth/sdf "
                                    f"({og.height}x{og.width} cells of {og.resolution:g} m against "
                                    f"{geometry.height}x{geometry.width} of {geometry.resolution:g} m, or elsewhere): "
                                    "not this ground truth's obstacles")
                return response
            obstacles = obstacles[0]
        # Camera-frame points → the truth grid's (x, y) in its own table plane (the planning grid's table
        # frame may differ slightly): orthogonal projection along the true table normal.
        com = None if com is None else geometry.from_sensor(com)[0]
        if com is not None:
            try:
                validation.check_on_grid(com, geometry, 'ground_truth/center_of_mass')
            except ValueError as exc:
                response.message = f'{exc}: not the centre of mass of this ground truth'
                return response
        trials = int(request.trials) or 10
        if trials > MAX_TRIALS:
            response.message = f'trials={trials} is too many (at most {MAX_TRIALS})'
            return response
        jaws = []
        for name, pose in (('jaw1', request.jaw1), ('jaw2', request.jaw2)):
            if pose.header.frame_id and geometry.frame_id and pose.header.frame_id != geometry.frame_id:
                response.message = (f"{name} is in frame '{pose.header.frame_id}' but the ground truth is in "
                                    f"'{geometry.frame_id}' (no TF lookup in the simulator)")
                return response
            try:
                xyz = validation.check_pose(pose, name, self.limits)
            except ValueError as exc:
                response.message = str(exc)
                return response
            jaws.append(geometry.from_sensor(np.asarray(xyz, dtype=np.float64)[:3])[0])
        separation = float(np.linalg.norm(jaws[1] - jaws[0]))
        if separation < MIN_JAW_SEPARATION:
            response.message = (f'jaw1 and jaw2 are {separation * 1000:.3g} mm apart: identical jaws are not a grasp '
                                f'(need at least {MIN_JAW_SEPARATION * 1000:g} mm)')
            return response
        seed = int(request.seed) if request.seed else None
        outcome = execute_grasp_outcome(true_sdf, geometry, jaws[0], jaws[1], gripper, trials,
                                        np.random.default_rng(seed), center_of_mass=com, obstacles=obstacles)
        response.trials = trials
        response.successes = outcome.closed
        response.success_rate = outcome.closed / trials
        response.success = True
        response.message = f'{outcome.describe()} on the true shape'
        return response


def main(args: list[str] | None = None) -> int:
    return run_node(GripperSimNode, args)


if __name__ == '__main__':
    sys.exit(main())
