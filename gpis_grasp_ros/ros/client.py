"""A small blocking client for manipulation code (in the spirit of nav2_simple_commander).

    client = GraspPlannerClient()                 # a node spinning in its own background thread
    if not client.wait_until_ready(timeout=30.0):
        raise RuntimeError('no planner or no GPIS model')
    grasp = client.plan(method='gp-gpis-opt', seed=1, timeout=60.0)
    if grasp.success:
        in_base = client.to_frame(grasp, camera_to_base)   # geometry_msgs/TransformStamped
        trial = client.execute(grasp, trials=20)           # gripper_sim_node, when running
    client.close()

``plan`` uses the ``plan_grasp`` action by default (feedback, ``cancel()`` from another thread or from the
feedback callback) or the ``plan_grasp`` service (``use_action=False``). Service clients keep the deep
history :data:`~gpis_grasp_ros.ros.nodes.common.SERVICE_QOS` the nodes' services use (the action's goal,
result and cancel services too): every client of a service receives the answers to all its callers, and
with rclpy's default depth of 10 a client loses its own answer when 10 others arrive before it takes it.
A plain rclpy client should be made the same way: ``create_client(GraspPlan, 'plan_grasp',
qos_profile=SERVICE_QOS)``. An answer the
middleware lost is asked for again: a service call is re-sent after :data:`ASK_AGAIN` s (with the same
seed, chosen here when the caller gave 0, so planner_node joins the plan in progress or answers from
its kept answers instead of planning twice); an action goal is sent again likewise with the same goal id
(the action server takes a goal id once: a repeat it already holds is answered "not accepted", which
here means "accepted before", and the result is asked for by that id), and its result is requested
again likewise. Every
method returns plain dataclasses; nothing raises on a refused or failed
request (``success`` is false and ``message`` says why). No tf2: :meth:`to_frame` applies a caller-given
``TransformStamped`` with numpy quaternion maths.
"""

from __future__ import annotations

import random
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from action_msgs.msg import GoalStatus
from geometry_msgs.msg import PointStamped, PoseStamped, TransformStamped
from rclpy.action import ActionClient
from rclpy.action.client import ClientGoalHandle
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from unique_identifier_msgs.msg import UUID

from gpis_grasp_interfaces.action import PlanGrasp
from gpis_grasp_interfaces.msg import GpisModel
from gpis_grasp_interfaces.srv import ExecuteGrasp, GraspPlan
from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS, SERVICE_QOS

#: Fields copied from a GraspPlan response / PlanGrasp result into :class:`PlanResult`.
_RESULT_FIELDS = ('success', 'message', 'method', 'jaw1', 'jaw2', 'grasp_pose', 'contact1', 'contact2', 'width',
                  'jaw_separation', 'grasp_height', 'probability_force_closure',
                  'probability_force_closure_std_error', 'ferrari_canny_on_mean', 'objective', 'planning_time',
                  'iterations')
#: Seconds without an answer after which a request is sent again (then every last value).
ASK_AGAIN = (2.0, 4.0, 8.0, 16.0)
_STATUS = {GoalStatus.STATUS_SUCCEEDED: 'succeeded', GoalStatus.STATUS_ABORTED: 'aborted',
           GoalStatus.STATUS_CANCELED: 'canceled', GoalStatus.STATUS_UNKNOWN: 'refused'}


@dataclass
class PlanResult:
    """A planned grasp: the GraspPlan response fields (poses in the GPIS model's frame, m) and how it ended.

    ``status``: 'succeeded', 'aborted', 'canceled' (action), 'answered' (service), 'timeout', 'refused'."""

    success: bool = False
    message: str = ''
    method: str = ''
    jaw1: PoseStamped = field(default_factory=PoseStamped)
    jaw2: PoseStamped = field(default_factory=PoseStamped)
    grasp_pose: PoseStamped = field(default_factory=PoseStamped)
    contact1: PointStamped = field(default_factory=PointStamped)
    contact2: PointStamped = field(default_factory=PointStamped)
    width: float = float('nan')
    jaw_separation: float = float('nan')
    grasp_height: float = float('nan')
    probability_force_closure: float = float('nan')
    probability_force_closure_std_error: float = float('nan')
    ferrari_canny_on_mean: float = float('nan')
    objective: float = float('nan')
    planning_time: float = 0.0
    iterations: int = 0
    status: str = ''

    @classmethod
    def from_message(cls, msg: Any, status: str) -> PlanResult:
        return cls(**{name: getattr(msg, name) for name in _RESULT_FIELDS}, status=status)


@dataclass
class ExecuteResult:
    """Outcome of simulated executions on gripper_sim_node (``success`` = the request was executed)."""

    success: bool
    message: str
    trials: int = 0
    successes: int = 0
    success_rate: float = 0.0


@dataclass
class FramedGrasp:
    """A grasp's jaw poses, centre and contacts expressed in another frame (:meth:`GraspPlannerClient.to_frame`)."""

    frame_id: str
    jaw1: PoseStamped
    jaw2: PoseStamped
    grasp_pose: PoseStamped
    contact1: PointStamped
    contact2: PointStamped


# ------------------------------------------------------------------------------------------ quaternion maths
def _quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (x, y, z, w) quaternions."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz])


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vector ``v`` by the unit quaternion ``q`` (x, y, z, w)."""
    u, w = q[:3], q[3]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def _transform_parts(transform: TransformStamped) -> tuple[np.ndarray, np.ndarray]:
    t = transform.transform.translation
    r = transform.transform.rotation
    q = np.array([r.x, r.y, r.z, r.w], dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not np.isfinite(norm) or norm < 1e-9:
        raise ValueError('transform.rotation is not a valid quaternion')
    return np.array([t.x, t.y, t.z], dtype=np.float64), q / norm


def transform_pose(pose: PoseStamped, transform: TransformStamped) -> PoseStamped:
    """``pose`` (in ``transform.child_frame_id``) in ``transform.header.frame_id``: p' = R p + t, q' = q_T q."""
    t, q = _transform_parts(transform)
    p, o = pose.pose.position, pose.pose.orientation
    xyz = _rotate(q, np.array([p.x, p.y, p.z])) + t
    rot = _quat_multiply(q, np.array([o.x, o.y, o.z, o.w]))
    out = PoseStamped()
    out.header.stamp = pose.header.stamp
    out.header.frame_id = transform.header.frame_id
    out.pose.position.x, out.pose.position.y, out.pose.position.z = (float(v) for v in xyz)
    (out.pose.orientation.x, out.pose.orientation.y, out.pose.orientation.z,
     out.pose.orientation.w) = (float(v) for v in rot)
    return out


def transform_point(point: PointStamped, transform: TransformStamped) -> PointStamped:
    """``point`` (in ``transform.child_frame_id``) in ``transform.header.frame_id``."""
    t, q = _transform_parts(transform)
    p = point.point
    xyz = _rotate(q, np.array([p.x, p.y, p.z])) + t
    out = PointStamped()
    out.header.stamp = point.header.stamp
    out.header.frame_id = transform.header.frame_id
    out.point.x, out.point.y, out.point.z = (float(v) for v in xyz)
    return out


# ------------------------------------------------------------------------------------------ the client
class GraspPlannerClient(Node):
    """Blocking calls to planner_node (``plan_grasp`` action / service) and gripper_sim_node (``execute_grasp``).

    The node spins in its own background thread (a multi-threaded executor), so every method may be
    called from the caller's thread without spinning; ``cancel()`` may be called from another thread
    or from a feedback callback while :meth:`plan` waits.
    """

    def __init__(self, node_name: str = 'grasp_planner_client', namespace: str = '', **kwargs: Any) -> None:
        super().__init__(node_name, namespace=namespace, **kwargs)
        group = ReentrantCallbackGroup()
        self._plan_service = self.create_client(GraspPlan, 'plan_grasp', qos_profile=SERVICE_QOS,
                                                callback_group=group)
        self._execute_service = self.create_client(ExecuteGrasp, 'execute_grasp', qos_profile=SERVICE_QOS,
                                                   callback_group=group)
        self._plan_action = ActionClient(self, PlanGrasp, 'plan_grasp', callback_group=group,
                                         goal_service_qos_profile=SERVICE_QOS, result_service_qos_profile=SERVICE_QOS,
                                         cancel_service_qos_profile=SERVICE_QOS)
        self._model_topic = 'gpis/model'
        self._model_received = threading.Event()
        self._model: GpisModel | None = None
        self.create_subscription(GpisModel, self._model_topic, self._on_model, LATCHED_QOS, callback_group=group)
        self._goal_lock = threading.Lock()
        self._goal_handle: Any = None
        self._executor = MultiThreadedExecutor(num_threads=4, context=self.context)
        self._executor.add_node(self)
        self._spinner = threading.Thread(target=self._spin, name=f'{node_name}-spin', daemon=True)
        self._spinner.start()

    def _spin(self) -> None:
        try:
            self._executor.spin()
        except Exception:  # noqa: BLE001 - the context was shut down under the executor
            pass

    def _on_model(self, msg: GpisModel) -> None:
        self._model = msg
        self._model_received.set()

    @property
    def model(self) -> GpisModel | None:
        """The latest GPIS model seen on ``gpis/model`` (None before the first)."""
        return self._model

    # ------------------------------------------------------------------ readiness
    def wait_until_ready(self, timeout: float = 30.0, use_action: bool = True) -> bool:
        """Wait until planner_node serves ``plan_grasp`` (action or service) and a GPIS model was published
        on ``gpis/model`` (a publisher and a message). False when ``timeout`` s pass first."""
        end = time.monotonic() + timeout

        def left() -> float:
            return max(0.0, end - time.monotonic())

        if use_action:
            if not self._plan_action.wait_for_server(timeout_sec=left()):
                return False
        elif not self._plan_service.wait_for_service(timeout_sec=left()):
            return False
        while self.count_publishers(self._model_topic) == 0:
            if left() <= 0:
                return False
            time.sleep(0.02)
        return self._model_received.wait(left())

    # ------------------------------------------------------------------ planning
    def plan(self, method: str = '', seed: int = 0, num_initial_grasps: int = 0, uncertainty_penalty: float = -1.0,
             timeout: float | None = None, feedback_callback: Callable[[Any], None] | None = None,
             use_action: bool = True) -> PlanResult:
        """Plan a grasp on the latest GPIS (request fields as in GraspPlan.srv: empty method / 0 / negative =
        the node's parameter; seed 0 = nondeterministic). ``timeout`` s (None = wait for the answer): past it
        the action goal is cancelled and the result has status 'timeout'. ``feedback_callback`` receives each
        PlanGrasp.Feedback (action only).

        A request sent right after a model was published is planned on it: planner_node waits up to its
        ``model_wait`` s for a model it is still taking before it answers 'no GPIS received yet'."""
        fields = dict(method=str(method), seed=int(seed), num_initial_grasps=int(num_initial_grasps),
                      uncertainty_penalty=float(uncertainty_penalty))
        if use_action:
            return self._plan_by_action(PlanGrasp.Goal(**fields), timeout, feedback_callback)
        return self._plan_by_service(GraspPlan.Request(**fields), timeout)

    def _plan_by_service(self, request: GraspPlan.Request, timeout: float | None) -> PlanResult:
        end = None if timeout is None else time.monotonic() + timeout
        if not self._plan_service.wait_for_service(timeout_sec=_remaining(end, 10.0)):
            return PlanResult(message='plan_grasp service not available', status='refused')
        if not request.seed:  # a seed of our own: asking again is then the same request
            request.seed = random.SystemRandom().randrange(1, 2 ** 32)
        answer = _ask(lambda: self._plan_service.call_async(request), self._plan_service.remove_pending_request,
                      _remaining(end, None))
        if answer is None:
            return PlanResult(message=f'no answer from plan_grasp within {timeout} s', status='timeout')
        return PlanResult.from_message(answer, 'answered')

    def _plan_by_action(self, goal: PlanGrasp.Goal, timeout: float | None,
                        feedback_callback: Callable[[Any], None] | None) -> PlanResult:
        end = None if timeout is None else time.monotonic() + timeout
        if not self._plan_action.wait_for_server(timeout_sec=_remaining(end, 10.0)):
            return PlanResult(message='plan_grasp action server not available', status='refused')
        on_feedback = None if feedback_callback is None else (lambda msg: feedback_callback(msg.feedback))
        handle = self._send_goal(goal, on_feedback, _remaining(end, None))
        if handle is None:
            return PlanResult(message=f'plan_grasp goal not accepted within {timeout} s', status='timeout')
        if not handle.accepted:
            return PlanResult(message='plan_grasp goal rejected', status='refused')
        with self._goal_lock:
            self._goal_handle = handle
        try:
            answer = _ask(handle.get_result_async, lambda _f: None, _remaining(end, None))
            if answer is None:
                self._cancel(handle, 5.0)
                _ask(handle.get_result_async, lambda _f: None, 5.0)  # answered at the next checkpoint
                return PlanResult(message=f'planning did not finish within {timeout} s; goal cancelled',
                                  status='timeout')
            if answer.status == GoalStatus.STATUS_UNKNOWN:  # a repeat "not accepted" that was a real rejection
                return PlanResult(message='plan_grasp goal rejected (the server does not know it)', status='refused')
            return PlanResult.from_message(answer.result, _STATUS.get(answer.status, f'status {answer.status}'))
        finally:
            with self._goal_lock:
                if self._goal_handle is handle:
                    self._goal_handle = None

    def _send_goal(self, goal: PlanGrasp.Goal, on_feedback: Any, timeout: float | None) -> Any:
        """Send ``goal``, again with the same goal id after each :data:`ASK_AGAIN` delay while no reply came;
        the goal handle (None when ``timeout`` s pass first). A repeat the server answers "not accepted" is
        one it holds already (rclpy's action server takes each goal id once): its handle is made here."""
        goal_id = UUID(uuid=list(uuid.uuid4().bytes))
        first: list[Any] = []

        def send() -> Any:
            future = self._plan_action.send_goal_async(goal, feedback_callback=on_feedback, goal_uuid=goal_id)
            first.append(future)
            return future

        reply = _ask_future(send, lambda _f: None, timeout)
        if reply is None:
            return None
        handle = reply.result()
        if handle.accepted or reply is first[0]:
            return handle
        accepted = PlanGrasp.Impl.SendGoalService.Response(accepted=True)
        return ClientGoalHandle(self._plan_action, goal_id, accepted)

    def cancel(self, timeout: float = 5.0) -> bool:
        """Cancel the goal :meth:`plan` is waiting for; True when the planner accepted the cancel."""
        with self._goal_lock:
            handle = self._goal_handle
        return handle is not None and self._cancel(handle, timeout)

    @staticmethod
    def _cancel(handle: Any, timeout: float) -> bool:
        future = handle.cancel_goal_async()
        return _wait(future, timeout) and bool(future.result().goals_canceling)

    # ------------------------------------------------------------------ execution
    def execute(self, grasp: Any, trials: int = 10, seed: int = 0, timeout: float = 60.0) -> ExecuteResult:
        """Execute ``grasp`` (anything with ``jaw1``, ``jaw2`` PoseStamped: a :class:`PlanResult`, a GraspPlan
        response) ``trials`` times on gripper_sim_node's ``execute_grasp`` (0 → 10 trials; seed 0 =
        nondeterministic)."""
        if not self._execute_service.wait_for_service(timeout_sec=min(timeout, 10.0)):
            return ExecuteResult(False, 'execute_grasp service not available (is gripper_sim_node running?)')
        request = ExecuteGrasp.Request(jaw1=grasp.jaw1, jaw2=grasp.jaw2, trials=int(trials), seed=int(seed))
        future = self._execute_service.call_async(request)
        if not _wait(future, timeout):
            self._execute_service.remove_pending_request(future)
            return ExecuteResult(False, f'no answer from execute_grasp within {timeout} s')
        r = future.result()
        return ExecuteResult(bool(r.success), str(r.message), int(r.trials), int(r.successes), float(r.success_rate))

    # ------------------------------------------------------------------ frames
    @staticmethod
    def to_frame(grasp: Any, transform: TransformStamped) -> FramedGrasp:
        """The grasp's jaw poses, centre and contacts in ``transform.header.frame_id``.

        ``transform`` maps ``transform.child_frame_id`` (the grasp's frame, the GPIS model's camera frame)
        into ``header.frame_id`` (TF's convention, e.g. a lookup of base_link ← camera)."""
        frame = grasp.jaw1.header.frame_id
        if transform.child_frame_id and frame and transform.child_frame_id != frame:
            raise ValueError(f"the grasp is in '{frame}' but the transform maps '{transform.child_frame_id}' into "
                             f"'{transform.header.frame_id}'")
        return FramedGrasp(frame_id=transform.header.frame_id,
                           jaw1=transform_pose(grasp.jaw1, transform), jaw2=transform_pose(grasp.jaw2, transform),
                           grasp_pose=transform_pose(grasp.grasp_pose, transform),
                           contact1=transform_point(grasp.contact1, transform),
                           contact2=transform_point(grasp.contact2, transform))

    # ------------------------------------------------------------------ shutdown
    def close(self) -> None:
        """Stop the background executor and destroy the node (the context stays the caller's)."""
        self._executor.shutdown(timeout_sec=2.0)
        self._plan_action.destroy()
        self.destroy_node()
        self._spinner.join(timeout=5.0)


def _remaining(end: float | None, cap: float | None) -> float | None:
    """Seconds left until ``end`` (None = unbounded), at most ``cap``."""
    if end is None:
        return cap
    left = max(0.0, end - time.monotonic())
    return left if cap is None else min(left, cap)


def _ask(send: Callable[[], Any], forget: Callable[[Any], Any], timeout: float | None) -> Any:
    """``send()`` a request (→ future), again after each :data:`ASK_AGAIN` delay while no answer came; the first
    answer (None when ``timeout`` s pass first). ``forget(future)`` drops the requests still pending."""
    future = _ask_future(send, forget, timeout)
    return None if future is None else future.result()


def _ask_future(send: Callable[[], Any], forget: Callable[[Any], Any], timeout: float | None) -> Any:
    """:func:`_ask`, returning the first future answered (None when ``timeout`` s pass first)."""
    end = None if timeout is None else time.monotonic() + timeout
    answered = threading.Event()
    futures: list[Any] = []
    try:
        for attempt in range(10 ** 6):
            future = send()
            futures.append(future)
            future.add_done_callback(lambda _f: answered.set())
            delay = ASK_AGAIN[min(attempt, len(ASK_AGAIN) - 1)]
            if answered.wait(_remaining(end, delay)):
                return next(f for f in futures if f.done())
            if end is not None and time.monotonic() >= end:
                return None
        return None
    finally:
        for future in futures:
            if not future.done():
                forget(future)


def _wait(future: Any, timeout: float | None) -> bool:
    """Wait for an rclpy future completed by the background executor; True when done."""
    done = threading.Event()
    future.add_done_callback(lambda _f: done.set())
    return done.wait(timeout) and future.done()


__all__ = ['ExecuteResult', 'FramedGrasp', 'GraspPlannerClient', 'PlanResult', 'transform_point', 'transform_pose']
