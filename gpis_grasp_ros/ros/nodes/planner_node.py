"""planner_node: serves ``plan_grasp`` (gpis_grasp_interfaces/GraspPlan) on the latest GPIS.

Subscribes ``gpis/model`` (latched), plans with GP-GPIS-OPT or a baseline (paper sections VI,
VII-B) in a worker thread with a ``planning_timeout``, answers with stamped jaw poses in the
sensor frame (metres), and publishes ``grasp/markers`` (RViz) and ``grasp/image`` (the grasp drawn
on the GPIS-Blur image).
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import Image
from visualization_msgs.msg import MarkerArray

from gpis_grasp_interfaces.msg import GpisModel
from gpis_grasp_interfaces.srv import GraspPlan
from gpis_grasp_ros.core import contacts, planners
from gpis_grasp_ros.core.blur import gpis_blur
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.ros import conversions
from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS, declare, guarded, guarded_service, run_node
from gpis_grasp_ros.viz import images as viz

MAX_INITIAL_GRASPS = 1000
#: Methods whose request field num_initial_grasps means K heuristic grasp samples.
SAMPLING_METHODS = ('gp-m', 'gp-p')
MAX_GRASP_SAMPLES = 100000


class PlannerNode(Node):
    """Thin ROS wrapper around :func:`gpis_grasp_ros.core.planners.plan`."""

    def __init__(self, **kwargs) -> None:
        super().__init__('planner_node', **kwargs)
        self.method = declare(self, 'method', 'gp-gpis-opt', 'planner used when a request leaves method empty',
                              choices=list(planners.METHODS))
        self.num_initial_grasps = declare(self, 'num_initial_grasps', 20,
                                          'N_g: random initial grasps of GP-GPIS-OPT / GP-D / GP-U (paper: 20)',
                                          low=1, high=MAX_INITIAL_GRASPS)
        self.num_grasp_samples = declare(self, 'num_grasp_samples', 1000,
                                         'K: heuristic grasp samples of GP-M and GP-P (paper: 1000)',
                                         low=1, high=MAX_GRASP_SAMPLES)
        self.num_shape_samples = declare(self, 'num_shape_samples', 1000,
                                         'S: GPIS shape samples of the Monte-Carlo P_F estimate (paper: 1000)',
                                         low=10, high=100000)
        self.uncertainty_penalty = declare(self, 'uncertainty_penalty', 2.0,
                                           'lambda of eq. 4, on variance measured in grid cells^2 (paper: 2.0)',
                                           low=0.0, high=1000.0)
        self.jaw_width = declare(self, 'jaw_width', 0.01, 'w_j: width of each jaw face (m)', low=0.0, high=0.2)
        self.max_opening = declare(self, 'max_opening', 0.09, 'w_g: maximum jaw opening (m)', low=0.005, high=0.5)
        self.friction = declare(self, 'friction_coefficient', 0.5, 'gamma: Coulomb friction coefficient',
                                low=0.0, high=5.0)
        self.alpha = declare(self, 'antipodal_alpha', 0.5,
                             'alpha of eq. 5: bound on |n1 + n2|^2 of the antipodal constraint', low=0.0, high=4.0)
        self.position_noise_cells = declare(self, 'position_noise_cells', 0.5,
                                            'sigma_g: gripper positioning noise in grid cells (paper: sigma_g^2 = '
                                            '0.25 cells^2)', low=0.0, high=10.0)
        self.gp_p_adaptive = declare(self, 'gp_p_adaptive', True,
                                     'GP-P: successive-halving Monte Carlo (true) or every candidate on all S '
                                     'shape samples as in the paper (false); the final choice uses all S either way')
        self.planning_timeout = declare(self, 'planning_timeout', 60.0,
                                        'seconds after which plan_grasp answers success=false', low=0.1, high=3600.0)
        self.image_scale = declare(self, 'image_scale', 16, 'pixels per grid cell of grasp/image', low=1, high=64)

        self._lock = threading.Lock()
        self._model: GpisModel | None = None
        self._posterior = None
        self._blur: np.ndarray | None = None
        self._busy = threading.Lock()

        self._model_topic = 'gpis/model'
        self.create_subscription(GpisModel, self._model_topic, guarded(self, self._model_topic, self._on_model),
                                 LATCHED_QOS,
                                 callback_group=MutuallyExclusiveCallbackGroup())
        self.marker_pub = self.create_publisher(MarkerArray, 'grasp/markers', LATCHED_QOS)
        self.image_pub = self.create_publisher(Image, 'grasp/image', LATCHED_QOS)
        self.create_service(GraspPlan, 'plan_grasp', guarded_service(self, 'plan_grasp', self._on_plan),
                            callback_group=ReentrantCallbackGroup())
        self.get_logger().info(f"waiting for a GPIS on '{self.resolve_topic_name(self._model_topic)}'; "
                               f"serving '{self.resolve_service_name('plan_grasp')}'")

    # ------------------------------------------------------------------ model input
    def _on_model(self, msg: GpisModel) -> None:
        try:
            posterior = messages.gpis_model_to_posterior(msg)
        except ValueError as exc:
            self.get_logger().warning(f'ignoring malformed GpisModel: {exc}')
            return
        blur = gpis_blur(posterior, n_samples=200, rng=np.random.default_rng(0))
        with self._lock:
            self._model, self._posterior, self._blur = msg, posterior, blur
        g = posterior.geometry
        self.get_logger().info(f'GPIS received: {g.height}x{g.width} cells of {g.resolution * 1000:.1f} mm '
                               f"in '{g.frame_id}'")

    def has_model(self) -> bool:
        """Whether a GPIS model has been received and is ready for planning."""
        with self._lock:
            return self._posterior is not None

    # ------------------------------------------------------------------ service
    def _validate(self, request: GraspPlan.Request) -> tuple[str, int, float] | str:
        try:
            method = planners.canonical_method((request.method or self.method).strip().lower())
        except ValueError:
            return f"unknown method '{request.method}'; valid: {', '.join(planners.METHODS)}"
        sampling = method in SAMPLING_METHODS
        default_n = self.num_grasp_samples if sampling else self.num_initial_grasps
        limit = MAX_GRASP_SAMPLES if sampling else MAX_INITIAL_GRASPS
        n = int(request.num_initial_grasps) or int(default_n)
        if n > limit:
            return f'num_initial_grasps={request.num_initial_grasps} is too large for {method} (at most {limit})'
        lam = float(request.uncertainty_penalty)
        if math.isnan(lam) or math.isinf(lam):
            return f'uncertainty_penalty must be a finite number, got {lam}'
        if lam < 0:
            lam = float(self.uncertainty_penalty)
        return method, n, lam

    def _on_plan(self, request: GraspPlan.Request, response: GraspPlan.Response) -> GraspPlan.Response:
        response.success = False
        checked = self._validate(request)
        if isinstance(checked, str):
            response.message = checked
            return response
        method, n, lam = checked
        with self._lock:
            model, posterior, blur = self._model, self._posterior, self._blur
        if posterior is None:
            response.message = ("no GPIS received yet: waiting for a gpis_grasp_interfaces/GpisModel on "
                                f"'{self.resolve_topic_name(self._model_topic)}'")
            return response
        seed = int(request.seed) if request.seed else int(np.random.SeedSequence().entropy % (2 ** 32))
        params = self._planner_params(posterior, n, lam, sampling=method in SAMPLING_METHODS)
        if not self._busy.acquire(blocking=False):
            response.message = 'planner busy with another request (or a timed-out plan still running); retry later'
            return response
        outcome: dict = {}

        def work() -> None:
            try:
                outcome['result'] = planners.plan(method, posterior, params, seed=seed)
            except Exception as exc:  # reported to the caller, never kills the node
                outcome['error'] = exc
            finally:
                self._busy.release()

        start = time.perf_counter()
        worker = threading.Thread(target=work, name='grasp-planning', daemon=True)
        worker.start()
        worker.join(self.planning_timeout)
        if worker.is_alive():
            response.message = (f'planning with {method} exceeded planning_timeout={self.planning_timeout:.1f} s; '
                                'try fewer initial grasps / samples or a larger timeout')
            response.planning_time = time.perf_counter() - start
            return response
        if 'error' in outcome:
            response.message = f'{method} failed: {outcome["error"]}'
            self.get_logger().error(response.message)
            return response
        result = outcome['result']
        conversions.fill_grasp_plan_response(response, result, model.header, z=posterior.geometry.z)
        if result.success:
            self._publish_visuals(result, posterior, blur, model.header)
        self.get_logger().info(f'{method}: {response.message} (P_F={result.p_f:.2f}, {result.planning_time:.2f} s)')
        return response

    def _planner_params(self, posterior, n: int, lam: float, sampling: bool):
        gripper = contacts.GripperParams(jaw_width=self.jaw_width, max_opening=self.max_opening,
                                         friction_coef=self.friction, position_noise_cells=self.position_noise_cells)
        return planners.PlannerParams(
            gripper=gripper, antipodal_alpha=self.alpha,
            n_initial_grasps=self.num_initial_grasps if sampling else n,
            n_grasp_samples=n if sampling else self.num_grasp_samples,
            n_shape_samples=self.num_shape_samples, uncertainty_penalty=lam, gp_p_adaptive=self.gp_p_adaptive)

    def _publish_visuals(self, result, posterior, blur, header) -> None:
        bank = contacts.SdfBank(posterior.mean[None], posterior.geometry, posterior.gradient[None])
        con = contacts.find_contacts(bank, result.jaw1, result.jaw2, contacts.GripperParams(jaw_width=self.jaw_width),
                                     check_opening=False)
        touches = np.stack([np.reshape(con.c1, (-1, 2))[0], np.reshape(con.c2, (-1, 2))[0]])
        if not bool(np.ravel(con.valid)[0]):
            touches = None
        self.marker_pub.publish(conversions.grasp_markers(result, header, posterior.geometry, self.jaw_width,
                                                          contacts_xy=touches))
        overlay = viz.grasp_overlay(blur, posterior.geometry, [result], scale=self.image_scale,
                                    jaw_width_m=self.jaw_width)
        self.image_pub.publish(messages.numpy_to_image(conversions.RclpyFactory(), overlay, 'rgb8',
                                                          messages.header(conversions.RclpyFactory(),
                                                                             messages.stamp_to_ns(header.stamp),
                                                                             header.frame_id)))


def main(args: list[str] | None = None) -> int:
    return run_node(PlannerNode, args)


if __name__ == '__main__':
    main()
