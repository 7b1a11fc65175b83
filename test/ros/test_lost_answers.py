"""Answers the middleware loses: the service sends again when rmw refused, a repeated seeded call is the same
request (planned once), and the client asks again (launch-free)."""

from __future__ import annotations

import threading
import time
import warnings
from pathlib import Path

import pytest
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from gpis_grasp_interfaces.msg import GpisModel
from gpis_grasp_interfaces.srv import GraspPlan
from gpis_grasp_ros.core import planners
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.data.bags import load_bag, posterior_from_scene
from gpis_grasp_ros.ros import client as client_api
from gpis_grasp_ros.ros import conversions
from gpis_grasp_ros.ros.nodes import replies
from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS, SERVICE_QOS
from gpis_grasp_ros.ros.nodes.planner_node import PlannerNode
from support.rosutil import RosHarness, wait_for

BAG_H = next((Path(__file__).resolve().parents[2] / 'bags').glob('H_*.mcap'))
F = conversions.RclpyFactory()


@pytest.fixture(scope='module')
def model_msg():
    post, _ = posterior_from_scene(load_bag(BAG_H))
    return messages.posterior_to_gpis_model(post, messages.header(F, 1, 'cam'), F)


def test_send_checked_sees_the_rmw_timeout_warning():
    def refused(_response, _header):
        warnings.warn('failed to send response (timeout): client will not receive response', RuntimeWarning,
                      stacklevel=1)

    assert not replies.send_checked(refused, None, None)
    assert not replies.send_checked(refused, None, None)  # every time, not once per location
    assert replies.send_checked(lambda _r, _h: None, None, None)


def test_an_answer_the_middleware_refused_is_sent_again():
    ros = RosHarness()
    try:
        server = ros.node('server')
        attempts = []

        def handler(_request, reply):
            reply.response.success, reply.response.message = True, 'ok'
            threading.Timer(0.05, reply.send).start()  # answered later, from another thread

        svc = replies.DeferredService(server, Trigger, 'trigger', handler, SERVICE_QOS)
        real = svc._send

        def flaky(response, header):  # rmw_fastrtps: the caller's reader not matched yet, twice
            attempts.append(time.monotonic())
            if len(attempts) <= 2:
                warnings.warn('failed to send response (timeout): client will not receive response',
                              RuntimeWarning, stacklevel=1)
                return
            real(response, header)
        svc._send = flaky
        cli = ros.node('caller').create_client(Trigger, 'trigger', qos_profile=SERVICE_QOS)
        res = ros.call(cli, Trigger.Request(), timeout=10.0)
        assert res.success and res.message == 'ok'
        assert len(attempts) == 3 and svc.send_timeouts == 2 and svc.answers_sent == 1
        svc.close()
    finally:
        ros.close()


def _planner_with_model(ros: RosHarness, model_msg):
    """A small planner_node in ``ros`` holding ``model_msg`` (latched by a probe node); (probe, planner)."""
    planner = ros.add(PlannerNode(context=ros.context, parameter_overrides=[
        Parameter('num_shape_samples', value=50), Parameter('num_grasp_samples', value=20)]))
    probe = ros.node('probe')
    probe.create_publisher(GpisModel, 'gpis/model', LATCHED_QOS).publish(model_msg)
    assert wait_for(planner.has_model, 20.0)
    return probe, planner


def test_a_repeated_seeded_call_is_planned_once(model_msg, monkeypatch):
    real = planners.plan
    calls = []

    def counting(*args, **kwargs):
        calls.append(args[0])
        time.sleep(0.3)  # still planning when the call is repeated
        return real(*args, **kwargs)
    monkeypatch.setattr(planners, 'plan', counting)
    ros = RosHarness()
    try:
        probe, planner = _planner_with_model(ros, model_msg)
        cli = probe.create_client(GraspPlan, 'plan_grasp', qos_profile=SERVICE_QOS)
        assert cli.wait_for_service(timeout_sec=10.0)
        request = GraspPlan.Request(method='gp-m', seed=7)
        first, again = cli.call_async(request), cli.call_async(request)  # asked again while planning
        assert wait_for(lambda: first.done() and again.done(), 60.0)
        late = ros.call(cli, request)  # asked again after the answer
        assert first.result().success and first.result() == again.result() == late
        assert calls == ['gp-m']
        other = ros.call(ros.node('other').create_client(GraspPlan, 'plan_grasp'), GraspPlan.Request(
            method='gp-m', seed=8))
        assert other.success and len(calls) == 2  # another seed is another request
    finally:
        ros.close()


def test_the_client_asks_again_until_an_answer_comes(monkeypatch):
    from rclpy.task import Future
    monkeypatch.setattr(client_api, 'ASK_AGAIN', (0.05,))
    sent, forgotten = [], []

    def send():
        future = Future()
        sent.append(future)
        if len(sent) == 3:  # the first two answers are lost
            threading.Timer(0.01, future.set_result, args=('answer',)).start()
        return future

    assert client_api._ask(send, forgotten.append, 5.0) == 'answer'
    assert len(sent) == 3 and forgotten == sent[:2]
    assert client_api._ask(lambda: Future(), lambda _f: None, 0.2) is None


def _drop_first(waitable, kinds: tuple[str, ...], dropped: dict[str, int]) -> None:
    """Lose the first message of each kind ('goal', 'result') the action client or server takes."""
    real = waitable.execute

    async def lossy(taken):
        for kind in kinds:
            if kind in taken and not dropped.get(kind):
                dropped[kind] = 1
                del taken[kind]
        await real(taken)
    waitable.execute = lossy


@pytest.mark.parametrize('side', ['client', 'server'])
def test_the_action_path_asks_again_and_the_goal_is_planned_once(model_msg, monkeypatch, side):
    """client: the goal's acceptance and the first result reply are lost on the way back (the server has the
    goal; the repeat with the same goal id is answered 'not accepted' = held already); server: the first goal
    request and the first result request are lost on the way in."""
    monkeypatch.setattr(client_api, 'ASK_AGAIN', (0.5,))
    real = planners.plan
    calls = []

    def counting(*args, **kwargs):
        calls.append(args[0])
        return real(*args, **kwargs)
    monkeypatch.setattr(planners, 'plan', counting)
    ros = RosHarness()
    try:
        _probe, planner = _planner_with_model(ros, model_msg)
        client = client_api.GraspPlannerClient(context=ros.context)
        try:
            assert client.wait_until_ready(timeout=20.0)
            dropped: dict[str, int] = {}
            _drop_first(client._plan_action if side == 'client' else planner._action, ('goal', 'result'), dropped)
            grasp = client.plan(method='gp-m', seed=3, timeout=60.0)
            assert dropped == {'goal': 1, 'result': 1}
            assert grasp.success and grasp.status == 'succeeded', grasp.message
            assert calls == ['gp-m']  # planned once although the goal was sent twice
            again = client.plan(method='gp-m', seed=3, timeout=60.0)  # nothing lost: the same grasp
            assert again.success and again.jaw1.pose == grasp.jaw1.pose and len(calls) == 2
        finally:
            client.close()
    finally:
        ros.close()
