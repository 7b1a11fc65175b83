"""gripper_sim_node: a simulated parallel-jaw gripper standing in for the PR2's.

Subscribes the bag's latched ground truth (``ground_truth/sdf``, ``ground_truth/center_of_mass``;
never read by segmentation, GPIS or planner) and serves ``execute_grasp``
(gpis_grasp_interfaces/ExecuteGrasp): each trial perturbs the jaws with the positioning noise
sigma_g (section V-B), closes them on the TRUE shape and checks force closure with the same
Ferrari-Canny code the planner uses.
"""

from __future__ import annotations

import threading

import numpy as np
from geometry_msgs.msg import PointStamped
from rclpy.node import Node

from gpis_grasp_interfaces.msg import FloatGrid
from gpis_grasp_interfaces.srv import ExecuteGrasp
from gpis_grasp_ros.core import contacts, planners
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS, declare, guarded, guarded_service, run_node

MAX_TRIALS = 100000


class GripperSimNode(Node):
    """Executes grasps on the ground-truth SDF of the replayed scene."""

    def __init__(self, **kwargs) -> None:
        super().__init__('gripper_sim_node', **kwargs)
        self.gripper = contacts.GripperParams(
            jaw_width=declare(self, 'jaw_width', 0.01, 'w_j: width of each jaw face (m)', low=0.0, high=0.2),
            max_opening=declare(self, 'max_opening', 0.09, 'w_g: maximum jaw opening (m)', low=0.005, high=0.5),
            friction_coef=declare(self, 'friction_coefficient', 0.5, 'gamma: Coulomb friction coefficient',
                             low=0.0, high=5.0),
            position_noise=declare(self, 'position_noise', 0.003,
                                   'sigma_g: std of the jaw positioning error (m) per axis', low=0.0, high=0.1),
            contact_patch=declare(self, 'contact_patch', 0.003,
                                  'pad compliance (m): surface points within this distance of the first touch '
                                  'share the contact (the planner uses half a GPIS cell)', low=1e-5, high=0.05),
        )
        self._lock = threading.Lock()
        self._sdf = None
        self._geometry = None
        self._com = None
        self.create_subscription(FloatGrid, 'ground_truth/sdf', guarded(self, 'ground_truth/sdf', self._on_sdf),
                                 LATCHED_QOS)
        self.create_subscription(PointStamped, 'ground_truth/center_of_mass',
                                 guarded(self, 'ground_truth/center_of_mass', self._on_com), LATCHED_QOS)
        self.create_service(ExecuteGrasp, 'execute_grasp', guarded_service(self, 'execute_grasp', self._on_execute))

    def _on_sdf(self, msg: FloatGrid) -> None:
        try:
            values, geometry = messages.float_grid_to_numpy(msg)
        except ValueError as exc:
            self.get_logger().warning(f'ignoring ground_truth/sdf: {exc}')
            return
        with self._lock:
            self._sdf, self._geometry = values.astype(np.float64), geometry
        self.get_logger().info(f'ground truth SDF received: {geometry.height}x{geometry.width} cells')

    def _on_com(self, msg: PointStamped) -> None:
        with self._lock:
            self._com = np.array([msg.point.x, msg.point.y])

    def _on_execute(self, request: ExecuteGrasp.Request, response: ExecuteGrasp.Response) -> ExecuteGrasp.Response:
        response.success = False
        with self._lock:
            true_sdf, geometry, com = self._sdf, self._geometry, self._com
        if true_sdf is None:
            response.message = ("no ground truth received yet on "
                                f"'{self.resolve_topic_name('ground_truth/sdf')}'")
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
            xy = np.array([pose.pose.position.x, pose.pose.position.y])
            if not np.all(np.isfinite(xy)):
                response.message = f'{name} position is not finite'
                return response
            jaws.append(xy)
        seed = int(request.seed) if request.seed else None
        successes = planners.execute_grasp_trials(true_sdf, geometry, jaws[0], jaws[1], self.gripper, trials,
                                                  np.random.default_rng(seed), center_of_mass=com)
        response.trials = trials
        response.successes = int(successes)
        response.success_rate = successes / trials
        response.success = True
        response.message = f'{successes}/{trials} trials in force closure on the true shape'
        return response


def main(args: list[str] | None = None) -> int:
    return run_node(GripperSimNode, args)


if __name__ == '__main__':
    main()
