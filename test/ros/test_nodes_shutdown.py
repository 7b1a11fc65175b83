"""SIGINT/SIGTERM on the nodes run as processes: in-flight requests are answered 'shutting down',
exit code 0, no error in the log. Not timed: it asserts answered / exited / clean."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from rclpy.action import ActionClient

from gpis_grasp_interfaces.action import PlanGrasp
from gpis_grasp_interfaces.msg import GpisModel
from gpis_grasp_interfaces.srv import GraspPlan
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.data.bags import load_bag, posterior_from_scene
from gpis_grasp_ros.ros import conversions
from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS
from support.rosutil import RosHarness, wait_for

ROOT = Path(__file__).resolve().parents[2]
F = conversions.RclpyFactory()


def _start(module: str, domain: int, *ros_args: str) -> subprocess.Popen:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               PYTHONUNBUFFERED='1', RCUTILS_COLORIZED_OUTPUT='0')
    return subprocess.Popen([sys.executable, '-m', f'gpis_grasp_ros.ros.nodes.{module}', '--ros-args', *ros_args],
                            env=env, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _probe_with_model(ros: RosHarness):
    """A probe node that has published bag H's GPIS model (latched; the node keeps its publisher)."""
    probe = ros.node('probe')
    pub = probe.create_publisher(GpisModel, 'gpis/model', LATCHED_QOS)
    post, _ = posterior_from_scene(load_bag(next((ROOT / 'bags').glob('H_*.mcap')), frames=3))
    pub.publish(messages.posterior_to_gpis_model(post, messages.header(F, 1, 'cam'), F))
    return probe


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_signal_during_a_plan_answers_the_caller_and_exits_cleanly(sig):
    ros = RosHarness()
    proc = _start('planner_node', ros.domain_id, '-p', 'num_shape_samples:=100000')
    try:
        probe = _probe_with_model(ros)
        cli = probe.create_client(GraspPlan, 'plan_grasp')
        assert cli.wait_for_service(timeout_sec=30.0)
        lines: list[str] = []
        reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, '')), daemon=True)
        reader.start()
        # wait until the planner has the model, then start a plan that runs for a long time
        assert wait_for(lambda: any('GPIS received' in ln for ln in lines), 30.0)
        answer = {}
        caller = threading.Thread(target=lambda: answer.setdefault('res', ros.call(
            cli, GraspPlan.Request(method='gp-gpis-opt', num_initial_grasps=1000, seed=1), timeout=60.0)))
        caller.start()
        wait_for(lambda: False, 1.0)  # the plan is running
        proc.send_signal(sig)
        code = proc.wait(timeout=30)
        caller.join(timeout=30)
        reader.join(timeout=5)
        log = ''.join(lines)
        assert code == 0, log
        assert '[ERROR]' not in log and 'Traceback' not in log, log
        res = answer['res']
        assert not res.success and 'shutting down' in res.message
    finally:
        if proc.poll() is None:
            proc.kill()
        ros.close()


def test_sigint_during_an_action_goal_aborts_it_with_the_reason():
    ros = RosHarness()
    proc = _start('planner_node', ros.domain_id, '-p', 'num_shape_samples:=100000')
    try:
        probe = _probe_with_model(ros)
        client = ActionClient(probe, PlanGrasp, 'plan_grasp')
        assert client.wait_for_server(timeout_sec=30.0)
        lines: list[str] = []
        reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, '')), daemon=True)
        reader.start()
        assert wait_for(lambda: any('GPIS received' in ln for ln in lines), 30.0)
        sent = client.send_goal_async(PlanGrasp.Goal(method='gp-gpis-opt', num_initial_grasps=1000, seed=1))
        assert wait_for(sent.done, 30.0) and sent.result().accepted
        result = sent.result().get_result_async()
        wait_for(lambda: False, 1.0)  # the plan is running
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=30)
        reader.join(timeout=5)
        log = ''.join(lines)
        assert code == 0, log
        assert '[ERROR]' not in log and 'Traceback' not in log, log
        assert wait_for(result.done, 10.0), log
        assert not result.result().result.success and 'shutting down' in result.result().result.message
    finally:
        if proc.poll() is None:
            proc.kill()
        ros.close()


@pytest.mark.parametrize('module', ['segmentation_node', 'gpis_node', 'gripper_sim_node'])
def test_idle_nodes_exit_cleanly_on_sigint(module):
    proc = _start(module, 90)
    try:
        # wait for the start-up line, then interrupt
        line = ''
        while 'started;' not in line:
            line = proc.stdout.readline()
            assert line, 'node exited before its start-up line'
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=30)
        rest = proc.stdout.read()
        assert code == 0 and '[ERROR]' not in rest and 'Traceback' not in rest, rest
    finally:
        if proc.poll() is None:
            proc.kill()
