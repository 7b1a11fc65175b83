"""planner_node replans from its last plan's optima on a newer model of the same frame (``warm_start``), plans
cold on the model it already planned on, for the sampling planners and with the parameter off (launch-free,
real executor)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from rclpy.parameter import Parameter

from gpis_grasp_interfaces.msg import GpisModel
from gpis_grasp_interfaces.srv import GraspPlan
from gpis_grasp_ros.core import planners
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.data.bags import load_bag, posterior_from_scene
from gpis_grasp_ros.ros import conversions
from gpis_grasp_ros.ros.nodes import planner_node
from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS
from support.rosutil import RosHarness, wait_for

BAG_A = next((Path(__file__).resolve().parents[2] / 'bags').glob('A_*.mcap'))
F = conversions.RclpyFactory()


@pytest.fixture(scope='module')
def models():
    """GPIS models of object A from two bursts (frames 0-4 and 5-9) and the first again with a later stamp."""
    scene = load_bag(BAG_A)
    out = []
    for k, stamp in ((0, 1), (5, 2), (0, 3)):
        burst = dataclasses.replace(scene, rgb_frames=scene.rgb_frames[k:k + 5],
                                    depth_frames=scene.depth_frames[k:k + 5])
        post, _ = posterior_from_scene(burst)
        out.append(messages.posterior_to_gpis_model(post, messages.header(F, stamp, 'cam'), F))
    return out


def test_newer_model_warm_starts_same_model_and_sampling_planners_do_not(models, monkeypatch):
    calls = []
    real_plan = planners.plan

    def recording_plan(method, posterior, params=None, seed=None, control=None, warm_start=None):
        result = real_plan(method, posterior, params, seed, control, warm_start)
        calls.append((method, warm_start, result))
        return result

    monkeypatch.setattr(planner_node.planners, 'plan', recording_plan)
    ros = RosHarness()
    try:
        node = ros.add(planner_node.PlannerNode(context=ros.context, parameter_overrides=[
            Parameter('num_shape_samples', value=100)]))
        probe = ros.node('probe')
        client = probe.create_client(GraspPlan, 'plan_grasp')
        publisher = probe.create_publisher(GpisModel, 'gpis/model', LATCHED_QOS)
        assert client.wait_for_service(timeout_sec=10.0)

        def publish(model) -> None:
            publisher.publish(model)
            assert wait_for(lambda: node._model is not None and node._model.header.stamp == model.header.stamp, 30.0)

        def ask(method: str, seed: int):
            res = ros.call(client, GraspPlan.Request(method=method, seed=seed))
            assert res.success, res.message
            return calls[-1]

        publish(models[0])
        _, warm, first = ask('gp-gpis-opt', 3)
        assert warm is None and not any(r.warm for r in first.restarts)  # nothing planned before
        _, warm, _ = ask('gp-gpis-opt', 4)
        assert warm is None  # the same model again: cold, reproducible from the model and the seed
        _, warm, _ = ask('gp-m', 3)
        assert warm is None  # a sampling planner has no starts

        publish(models[1])
        _, warm, second = ask('gp-gpis-opt', 3)
        assert warm is not None and warm.size == len(first.restarts)
        n_warm = sum(r.warm for r in second.restarts)
        assert 0 < n_warm <= 15  # the optima of the last plan valid on the new mean shape, at most 3/4 of N_g
        # the seed-4 plan finished last on the first model: its optima are the starts
        ref = planners.WarmStart.from_result(calls[1][2], messages.gpis_model_to_posterior(models[0]).geometry)
        assert abs(warm.jaw1 - ref.jaw1).max() < 1e-12

        node.set_parameters([Parameter('warm_start', value=False)])
        publish(models[2])
        _, warm, third = ask('gp-gpis-opt', 3)
        assert warm is None and not any(r.warm for r in third.restarts)
    finally:
        ros.close()
