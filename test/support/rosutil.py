"""Launch-free ROS test helpers: an isolated rclpy context with a spinning executor."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable

import rclpy
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node


class RosHarness:
    """Own rclpy Context + MultiThreadedExecutor spun in a background thread."""

    _instances = 0

    def __init__(self, threads: int = 4) -> None:
        # Every harness gets its own DDS domain so that latched topics of one test's graph never
        # reach another's (contexts in one process otherwise share the domain).
        base = int(os.environ.get('ROS_DOMAIN_ID', '40'))
        RosHarness._instances += 1
        self.domain_id = 1 + (base + RosHarness._instances) % 100
        self.context = Context()
        rclpy.init(context=self.context, domain_id=self.domain_id)
        self.executor = MultiThreadedExecutor(num_threads=threads, context=self.context)
        self.nodes: list[Node] = []
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # a callback raised: make it visible in the test output
            import traceback
            traceback.print_exc()

    def add(self, node: Node) -> Node:
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def node(self, name: str) -> Node:
        return self.add(rclpy.create_node(name, context=self.context))

    def call(self, client, request, timeout: float = 60.0):
        """Call a service through the spinning executor and wait for the answer."""
        if not client.wait_for_service(timeout_sec=10.0):
            raise TimeoutError(f'service {client.srv_name} not available')
        future = client.call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _f: done.set())
        if not done.wait(timeout):
            raise TimeoutError(f'no answer from {client.srv_name} within {timeout} s')
        return future.result()

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2.0)
        for n in self.nodes:
            n.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self._thread.join(timeout=5.0)


def wait_for(predicate: Callable[[], bool], timeout: float, period: float = 0.02) -> bool:
    """Poll ``predicate`` until it is true or ``timeout`` seconds passed."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(period)
    return predicate()


def segmentation_graph(ros: RosHarness, overrides: list) -> tuple:
    """segmentation_node (reliable input, one frame per estimate, plus ``overrides``) and a probe that
    records its latched grids and ``segmentation/status``; returns (node, grids, status, cloud publisher)."""
    from nav_msgs.msg import OccupancyGrid
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import String

    from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS, RELIABLE_SENSOR_QOS
    from gpis_grasp_ros.ros.nodes.segmentation_node import SegmentationNode

    node = ros.add(SegmentationNode(context=ros.context, parameter_overrides=[
        Parameter('input_reliability', value='reliable'), Parameter('frames_to_average', value=1), *overrides]))
    probe = ros.node('probe')
    grids, status = [], []
    probe.create_subscription(OccupancyGrid, 'object/occupancy', grids.append, LATCHED_QOS)
    probe.create_subscription(String, 'segmentation/status', status.append, LATCHED_QOS)
    pub = probe.create_publisher(PointCloud2, 'camera/depth/points', RELIABLE_SENSOR_QOS)
    assert wait_for(lambda: pub.get_subscription_count() > 0, 5.0)
    return node, grids, status, pub
