"""plan_grasp through a real rclpy executor: well-formed answers before a model arrives and
for invalid requests, and the node keeps serving afterwards."""

from __future__ import annotations

import math

import pytest

from gpis_grasp_interfaces.srv import GraspPlan
from gpis_grasp_ros.ros.nodes.planner_node import PlannerNode
from rosutil import RosHarness


@pytest.fixture(scope='module')
def ros():
    harness = RosHarness()
    harness.add(PlannerNode(context=harness.context))
    client_node = harness.node('plan_client')
    harness.client = client_node.create_client(GraspPlan, 'plan_grasp')
    yield harness
    harness.close()


def test_plan_before_model_says_what_it_waits_for(ros):
    res = ros.call(ros.client, GraspPlan.Request())
    assert res.success is False
    assert 'no GPIS received yet' in res.message and '/gpis/model' in res.message


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
