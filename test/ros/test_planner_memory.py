"""planner_node's memory and responsiveness under load (launch-free): waiting service calls hold no threads,
the kept answers are bounded, parameters are answered while plans run and wait."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
from rcl_interfaces.srv import GetParameters
from rclpy.parameter import Parameter

from gpis_grasp_interfaces.msg import GpisModel
from gpis_grasp_interfaces.srv import GraspPlan
from gpis_grasp_ros.core import planners
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.data.bags import load_bag, posterior_from_scene
from gpis_grasp_ros.ros import conversions
from gpis_grasp_ros.ros.nodes import planner_node
from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS, SERVICE_QOS
from gpis_grasp_ros.ros.nodes.planner_node import PlannerNode
from support.rosutil import RosHarness, wait_for

BAG_H = next((Path(__file__).resolve().parents[2] / 'bags').glob('H_*.mcap'))
F = conversions.RclpyFactory()


@pytest.fixture(scope='module')
def model_msg():
    post, _ = posterior_from_scene(load_bag(BAG_H))
    return messages.posterior_to_gpis_model(post, messages.header(F, 1, 'cam'), F)


def test_a_thousand_waiting_calls_hold_no_threads_and_parameters_answer_meanwhile(model_msg, monkeypatch):
    release = threading.Event()
    real = planners.plan

    def gated(*args, **kwargs):
        release.wait(60.0)
        return real(*args, **kwargs)
    monkeypatch.setattr(planners, 'plan', gated)
    monkeypatch.setattr(planner_node, 'ANSWERS_KEPT', 50)
    ros = RosHarness(threads=8)
    try:
        planner = ros.add(PlannerNode(context=ros.context, parameter_overrides=[
            Parameter('max_queue', value=1024), Parameter('num_shape_samples', value=10),
            Parameter('num_grasp_samples', value=5)]))
        probe = ros.node('probe')
        probe.create_publisher(GpisModel, 'gpis/model', LATCHED_QOS).publish(model_msg)
        assert wait_for(planner.has_model, 20.0)
        cli = probe.create_client(GraspPlan, 'plan_grasp', qos_profile=SERVICE_QOS)
        assert cli.wait_for_service(timeout_sec=10.0)
        threads_before = threading.active_count()
        futures = [cli.call_async(GraspPlan.Request(method='gp-m', seed=k + 1)) for k in range(1000)]
        assert wait_for(lambda: planner.queue_length() == 999, 60.0), planner.queue_length()
        assert threading.active_count() - threads_before < 10  # no thread per waiting caller
        params = probe.create_client(GetParameters, '/planner_node/get_parameters')
        latencies = []
        for _ in range(20):  # the worker is busy and 999 calls wait
            start = time.monotonic()
            res = ros.call(params, GetParameters.Request(names=['max_queue']), timeout=5.0)
            latencies.append(time.monotonic() - start)
            assert res.values[0].integer_value == 1024
        assert sorted(latencies)[-2] < 0.1, latencies
        release.set()
        assert wait_for(lambda: all(f.done() for f in futures), 300.0), sum(not f.done() for f in futures)
        answers = [f.result() for f in futures]  # planned, or no grasp among 5 samples (said so)
        assert all(a.success or 'no heuristic candidate' in a.message for a in answers)
        assert sum(a.success for a in answers) > 500
        assert len(planner._answers) == 50 and not planner._keyed  # the kept answers are bounded
    finally:
        release.set()
        ros.close()
