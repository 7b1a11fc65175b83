"""Parameters are answered while a node works, and a reliable replay into best-effort subscribers is not
paced by acknowledgements that never come (launch-free)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import rclpy
from rcl_interfaces.srv import GetParameters
from rclpy.qos import qos_profile_sensor_data

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.ros import conversions, player
from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS
from gpis_grasp_ros.ros.nodes.gpis_node import GpisNode
from gpis_grasp_ros.sim.scene import MaterialRegion, SceneSpec, write_scene_bag
from support.rosutil import RosHarness, wait_for

F = conversions.RclpyFactory()


def test_gpis_node_answers_parameters_while_it_fits(monkeypatch):
    fitting, release = threading.Event(), threading.Event()

    def slow_fit(self, occ, noise, geometry, params=None, *, warm_start=None):
        fitting.set()
        release.wait(10.0)
        raise ValueError('stopped by the test')
    monkeypatch.setattr(GpisNode, 'fit', slow_fit)
    ros = RosHarness()
    try:
        node = ros.add(GpisNode(context=ros.context))
        probe = ros.node('probe')
        from nav_msgs.msg import OccupancyGrid

        from gpis_grasp_interfaces.msg import FloatGrid
        g = GridGeometry(0.0, 0.0, 0.005, 8, 8, 0.7, 'cam')
        header = messages.header(F, 1, 'cam')
        occ = np.zeros((8, 8), np.int8)
        occ[3:5, 3:5] = 100
        probe.create_publisher(OccupancyGrid, 'object/occupancy', LATCHED_QOS).publish(
            messages.numpy_to_occupancy_grid(F, occ, g, header))
        probe.create_publisher(FloatGrid, 'object/noise_map', LATCHED_QOS).publish(
            messages.numpy_to_float_grid(F, np.full((8, 8), 1e-6, np.float32), g, header, 'm^2'))
        assert fitting.wait(20.0)
        cli = probe.create_client(GetParameters, '/gpis_node/get_parameters')
        latencies = []
        for _ in range(5):
            start = time.monotonic()
            res = ros.call(cli, GetParameters.Request(names=['blur_samples']), timeout=5.0)
            latencies.append(time.monotonic() - start)
            assert res.values[0].integer_value == node.config.blur_samples
        assert min(latencies) < 0.1 and not release.is_set(), latencies  # answered during the fit
    finally:
        release.set()
        ros.close()


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    square = np.array([[-0.03, -0.02], [0.04, -0.02], [0.04, 0.02], [-0.03, 0.02]])
    spec = SceneSpec(outline=square, regions=[MaterialRegion.box('transparent', 0.02, -0.03, 0.05, 0.03)],
                     height=0.02, frames=4, seed=3)
    return write_scene_bag(spec, tmp_path_factory.mktemp('pacing') / 'p.mcap')


def test_reliable_replay_into_best_effort_subscribers_is_not_held_by_acknowledgements(bag):
    ros = RosHarness()
    try:
        sub = ros.node('best_effort_camera')
        from sensor_msgs.msg import PointCloud2
        got = []
        sub.create_subscription(PointCloud2, 'camera/depth/points', got.append, qos_profile_sensor_data)
        bp = player.BagPlayer(ros.context, bag, rate=0.0, reliable=True, wait_for_subscribers=5.0,
                              ack_timeout=5.0)
        ros.add(bp.node)
        start = time.monotonic()
        bp.play_once(blocking=True)
        elapsed = time.monotonic() - start
        assert '/camera/depth/points' in bp.time_paced
        assert elapsed < 5.0 + 5.0, elapsed  # not 4 frames x ack_timeout
        assert wait_for(lambda: len(got) >= 3, 5.0), len(got)
    finally:
        ros.close()


def test_the_player_names_best_effort_subscribers(bag):
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    try:
        node = rclpy.create_node('be', context=ctx)
        from sensor_msgs.msg import PointCloud2
        node.create_subscription(PointCloud2, 'camera/depth/points', lambda _m: None, qos_profile_sensor_data)
        bp = player.BagPlayer(ctx, bag, rate=0.0, reliable=True)
        assert wait_for(lambda: bool(bp.best_effort_subscribers()), 5.0)
        assert bp.best_effort_subscribers()['/camera/depth/points'] == ['/be']
        bp.destroy()
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
