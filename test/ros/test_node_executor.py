"""The nodes' executor answers parameter requests while every thread of its pool is busy (launch-free)."""

from __future__ import annotations

import threading

import pytest
import rclpy
from rcl_interfaces.srv import GetParameters
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor
from std_srvs.srv import Trigger

from gpis_grasp_ros.ros.nodes.common import NodeExecutor
from support.rosutil import RosHarness, wait_for


@pytest.mark.parametrize('kind', ['nodes', 'rclpy'])
def test_parameters_are_answered_while_the_pool_is_busy(kind):
    ros = RosHarness()
    context = Context()
    rclpy.init(context=context, domain_id=ros.domain_id)
    release = threading.Event()
    running = []

    def block(_request, response):
        running.append(1)
        release.wait(30.0)
        return response
    node = rclpy.create_node('busy', context=context)
    node.declare_parameter('answer', 42)
    node.create_service(Trigger, 'block', block, callback_group=ReentrantCallbackGroup())
    executor = NodeExecutor(2, context) if kind == 'nodes' else MultiThreadedExecutor(num_threads=2, context=context)
    executor.add_node(node)
    if kind == 'nodes':
        executor.start_defaults()
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        probe = ros.node('probe')
        blocker = probe.create_client(Trigger, '/block')
        assert blocker.wait_for_service(timeout_sec=10.0)
        calls = [blocker.call_async(Trigger.Request()) for _ in range(2)]
        assert wait_for(lambda: len(running) == 2, 10.0)  # both pool threads wait in 'block'
        params = probe.create_client(GetParameters, '/busy/get_parameters')
        assert params.wait_for_service(timeout_sec=10.0)
        future = params.call_async(GetParameters.Request(names=['answer']))
        answered = wait_for(future.done, 5.0)
        if kind == 'nodes':
            assert answered and future.result().values[0].integer_value == 42
        else:  # rclpy's executor runs the parameter service in its pool too: nothing answers it
            assert not answered
        release.set()
        assert wait_for(lambda: all(c.done() for c in calls), 10.0)
    finally:
        release.set()
        executor.shutdown(timeout_sec=2.0)
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        ros.close()
