"""GraspPlannerClient against the real nodes (launch-free): a bag replayed into segmentation_node →
gpis_node → planner_node, gripper_sim_node on the bag's ground truth; plan by action and by service,
cancel, execute, frames, and a timeout when no model comes. The first plan is sent as soon as the
client has seen the model (no wait for planner_node to take it)."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import TransformStamped
from rclpy.parameter import Parameter

from gpis_grasp_ros.ros.client import GraspPlannerClient, transform_pose
from gpis_grasp_ros.ros.nodes.gpis_node import GpisNode
from gpis_grasp_ros.ros.nodes.gripper_sim_node import GripperSimNode
from gpis_grasp_ros.ros.nodes.planner_node import PlannerNode
from gpis_grasp_ros.ros.nodes.segmentation_node import SegmentationNode
from gpis_grasp_ros.ros.player import BagPlayer
from support.rosutil import RosHarness

BAG = Path(__file__).resolve().parents[2] / 'bags' / 'A_tape_dispenser.mcap'


@pytest.fixture(scope='module')
def loop():
    ros = RosHarness(threads=4)
    ctx = ros.context
    ros.add(SegmentationNode(context=ctx, parameter_overrides=[Parameter('input_reliability', value='reliable')]))
    ros.add(GpisNode(context=ctx, parameter_overrides=[Parameter('blur_samples', value=100)]))
    planner = ros.add(PlannerNode(context=ctx, parameter_overrides=[
        Parameter('num_shape_samples', value=200), Parameter('num_initial_grasps', value=4)]))
    ros.add(GripperSimNode(context=ctx))
    client = GraspPlannerClient(context=ctx)
    player = BagPlayer(ros.node('player'), BAG, rate=0.0, reliable=True, wait_for_subscribers=5.0)
    player.play_once(blocking=True)
    assert client.wait_until_ready(timeout=90.0), 'no GPIS model from the bag'
    yield client
    assert planner.has_model()
    client.close()
    player.destroy()
    ros.close()


def test_plan_by_action_with_feedback(loop):  # the first plan, right after wait_until_ready
    feedback = []
    result = loop.plan(method='gp-gpis-opt', seed=1, timeout=120.0, feedback_callback=feedback.append)
    assert result.success, result.message
    assert result.status == 'succeeded' and result.method == 'gp-gpis-opt'
    assert feedback and feedback[-1].restarts_total == 4
    assert 0.0 <= result.probability_force_closure <= 1.0
    assert result.jaw1.header.frame_id == loop.model.header.frame_id


def test_plan_by_service_gives_the_action_answer(loop):
    by_service = loop.plan(method='gp-gpis-opt', seed=1, timeout=120.0, use_action=False)
    by_action = loop.plan(method='gp-gpis-opt', seed=1, timeout=120.0)
    assert by_service.success and by_service.status == 'answered'
    for jaw in ('jaw1', 'jaw2'):
        a, b = getattr(by_service, jaw).pose.position, getattr(by_action, jaw).pose.position
        assert (a.x, a.y, a.z) == (b.x, b.y, b.z)
    assert by_service.probability_force_closure == by_action.probability_force_closure


def test_refused_request_is_a_result_not_an_exception(loop):
    result = loop.plan(method='gp-xyz', timeout=30.0)
    assert not result.success and "unknown method 'gp-xyz'" in result.message
    assert result.status == 'aborted'
    assert "unknown method" in loop.plan(method='gp-xyz', use_action=False, timeout=30.0).message


def test_cancel_from_the_feedback_callback(loop):
    cancelled = []
    first = threading.Lock()

    def on_feedback(_fb):  # feedback callbacks may run concurrently: cancel once
        if first.acquire(blocking=False):
            cancelled.append(loop.cancel())

    start = time.monotonic()
    result = loop.plan(method='gp-gpis-opt', num_initial_grasps=1000, seed=2, timeout=120.0,
                       feedback_callback=on_feedback)
    done = time.monotonic() + 10.0  # the callback's cancel() may still be waiting for its answer
    while not cancelled and time.monotonic() < done:
        time.sleep(0.05)
    assert cancelled == [True], (result.status, result.message, time.monotonic() - start)
    assert result.status == 'canceled' and not result.success
    assert 'cancelled' in result.message
    assert time.monotonic() - start < 60.0
    assert not loop.cancel()  # nothing to cancel any more


def test_cancel_from_another_thread(loop):
    timer = threading.Timer(1.0, loop.cancel)
    timer.start()
    try:
        result = loop.plan(method='gp-gpis-opt', num_initial_grasps=1000, seed=3, timeout=120.0)
    finally:
        timer.cancel()
    assert result.status == 'canceled', result.message


def test_timeout_cancels_the_goal(loop):
    result = loop.plan(method='gp-gpis-opt', num_initial_grasps=1000, seed=4, timeout=0.5)
    assert result.status == 'timeout' and not result.success and 'cancelled' in result.message
    assert loop.plan(method='gp-gpis-opt', seed=1, timeout=120.0).success  # the planner serves on


def test_execute_on_the_simulated_gripper(loop):
    grasp = loop.plan(method='gp-gpis-opt', seed=1, timeout=120.0)
    outcome = loop.execute(grasp, trials=10, seed=7)
    assert outcome.success, outcome.message
    assert outcome.trials == 10 and 0 <= outcome.successes <= 10
    assert outcome.success_rate == outcome.successes / 10


def test_to_frame_moves_every_point_rigidly(loop):
    grasp = loop.plan(method='gp-gpis-opt', seed=1, timeout=120.0)
    t = TransformStamped()
    t.header.frame_id = 'base_link'
    t.child_frame_id = grasp.jaw1.header.frame_id
    t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = 0.3, -0.1, 0.9
    half = math.radians(120) / 2  # 120 degrees about (1, 1, 1) / sqrt(3): x -> y -> z -> x
    axis = np.ones(3) / math.sqrt(3)
    (t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z) = axis * math.sin(half)
    t.transform.rotation.w = math.cos(half)
    framed = loop.to_frame(grasp, t)
    assert framed.frame_id == 'base_link' == framed.jaw1.header.frame_id == framed.contact2.header.frame_id

    def xyz(p):
        return np.array([p.x, p.y, p.z])

    for before, after in ((grasp.jaw1.pose.position, framed.jaw1.pose.position),
                          (grasp.contact1.point, framed.contact1.point)):
        b = xyz(before)
        assert np.allclose(xyz(after), np.array([b[2], b[0], b[1]]) + [0.3, -0.1, 0.9], atol=1e-12)
    # separations are kept; the closing direction (the jaws' x axis) still points jaw1 -> jaw2
    d = xyz(framed.jaw2.pose.position) - xyz(framed.jaw1.pose.position)
    assert math.isclose(float(np.linalg.norm(d)), grasp.jaw_separation, rel_tol=1e-9)
    x_axis = transform_pose(grasp.jaw1, t).pose.orientation
    q = np.array([x_axis.x, x_axis.y, x_axis.z, x_axis.w])
    u, w = q[:3], q[3]
    ex = np.array([1.0, 0.0, 0.0])
    rotated = ex + w * 2 * np.cross(u, ex) + np.cross(u, 2 * np.cross(u, ex))
    assert np.allclose(rotated, d / np.linalg.norm(d), atol=1e-6)
    wrong = TransformStamped()
    wrong.child_frame_id = 'elsewhere'
    with pytest.raises(ValueError, match='elsewhere'):
        loop.to_frame(grasp, wrong)


def test_no_model_times_out():
    ros = RosHarness(threads=2)
    ros.add(PlannerNode(context=ros.context, parameter_overrides=[Parameter('model_wait', value=1.0)]))
    client = GraspPlannerClient(context=ros.context)
    try:
        start = time.monotonic()
        assert client.wait_until_ready(timeout=1.5) is False
        assert 1.4 <= time.monotonic() - start < 10.0
        start = time.monotonic()
        result = client.plan(timeout=30.0)
        assert not result.success and 'no GPIS received yet' in result.message
        assert 1.0 <= time.monotonic() - start < 20.0  # planner_node's model_wait, then the answer
        outcome = client.execute(result, timeout=1.0)  # no gripper_sim_node here
        assert not outcome.success and 'not available' in outcome.message
    finally:
        client.close()
        ros.close()
