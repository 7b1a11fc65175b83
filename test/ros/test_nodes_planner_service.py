"""plan_grasp through a real rclpy executor: well-formed answers before a model arrives and
for invalid requests, and the node keeps serving afterwards; a request sent the moment a model
is published is planned on it."""

from __future__ import annotations

import math
import time
from pathlib import Path

import pytest
from rclpy.parameter import Parameter

from gpis_grasp_interfaces.msg import GpisModel
from gpis_grasp_interfaces.srv import GraspPlan
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.data.bags import load_bag, posterior_from_scene
from gpis_grasp_ros.ros import conversions
from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS
from gpis_grasp_ros.ros.nodes.planner_node import PlannerNode
from support.rosutil import RosHarness

BAG_H = next((Path(__file__).resolve().parents[2] / 'bags').glob('H_*.mcap'))
#: model_wait of the no-model fixture: each "no GPIS" answer takes this long
NO_MODEL_WAIT = 0.5


@pytest.fixture(scope='module')
def ros():
    harness = RosHarness()
    harness.add(PlannerNode(context=harness.context,
                            parameter_overrides=[Parameter('model_wait', value=NO_MODEL_WAIT)]))
    client_node = harness.node('plan_client')
    harness.client = client_node.create_client(GraspPlan, 'plan_grasp')
    yield harness
    harness.close()


def test_plan_before_model_says_what_it_waits_for(ros):
    start = time.monotonic()
    res = ros.call(ros.client, GraspPlan.Request())
    assert time.monotonic() - start >= NO_MODEL_WAIT  # the bounded wait for a model, then the answer
    assert res.success is False
    assert 'no GPIS received yet' in res.message and '/gpis/model' in res.message
    assert f'model_wait={NO_MODEL_WAIT:g} s' in res.message


@pytest.mark.parametrize('request_fields, expected', [
    ({'method': 'gp-xyz'}, "unknown method 'gp-xyz'"),
    ({'method': 'gp-gpis-opt', 'num_initial_grasps': 100000}, 'too large'),
    ({'uncertainty_penalty': math.nan}, 'finite'),
])
def test_bad_requests_rejected_with_reason(ros, request_fields, expected):
    res = ros.call(ros.client, GraspPlan.Request(**request_fields))
    assert res.success is False
    assert expected in res.message
    # ... and the node still answers afterwards
    assert 'no GPIS' in ros.call(ros.client, GraspPlan.Request()).message


def test_request_sent_as_the_model_is_published_is_planned():
    """The planner takes a model (validation, GPIS-Blur) before it can plan on it: a request sent the
    moment the model is published waits for it (model_wait) instead of being answered 'no GPIS'."""
    post, _ = posterior_from_scene(load_bag(BAG_H))
    f = conversions.RclpyFactory()
    model = messages.posterior_to_gpis_model(post, messages.header(f, 1, 'camera_rgb_optical_frame'), f)
    ros = RosHarness()
    try:
        planner = ros.add(PlannerNode(context=ros.context, parameter_overrides=[
            Parameter('num_shape_samples', value=100), Parameter('num_initial_grasps', value=3)]))
        probe = ros.node('probe')
        client = probe.create_client(GraspPlan, 'plan_grasp')
        publisher = probe.create_publisher(GpisModel, 'gpis/model', LATCHED_QOS)
        assert client.wait_for_service(timeout_sec=10.0)
        assert not planner.has_model()
        publisher.publish(model)
        future = client.call_async(GraspPlan.Request(method='gp-gpis-opt', seed=1))  # at once
        deadline = time.monotonic() + 120.0
        while not future.done() and time.monotonic() < deadline:
            time.sleep(0.01)
        res = future.result()
        assert res is not None and res.success, res.message if res else 'no answer'
        assert res.jaw1.header.frame_id == 'camera_rgb_optical_frame'
    finally:
        ros.close()
