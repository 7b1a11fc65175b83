"""The other objects travel with the model: segmentation's ``object/obstacles`` grid → gpis_node →
``GpisModel.obstacle_distance`` → the planner's posterior, whether the grid arrives before or after the fit."""

from __future__ import annotations

import numpy as np
import pytest

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.pipeline import obstacle_distance, posterior_from_grids
from gpis_grasp_ros.data import messages as cv
from gpis_grasp_ros.ros import conversions as rcv


def _grids():
    g = GridGeometry(-0.05, -0.05, 0.004, 25, 25, 0.7, 'cam')
    yy, xx = np.mgrid[0:25, 0:25]
    occ = np.where((np.abs(xx - 10) <= 4) & (np.abs(yy - 12) <= 3), 100, 0).astype(np.int8)
    obstacles = np.where((xx >= 16) & (xx <= 20) & (np.abs(yy - 12) <= 6), 100, 0).astype(np.int8)
    return g, occ, np.full(occ.shape, 1e-6, np.float32), obstacles


def test_the_model_message_carries_the_obstacles_and_rejects_a_wrong_length():
    g, occ, noise, obstacles = _grids()
    post = posterior_from_grids(occ, noise, g, obstacles=obstacles)
    f = rcv.RclpyFactory()
    msg = cv.posterior_to_gpis_model(post, cv.header(f, 1, 'cam'), f, com_samples=0)
    back = cv.gpis_model_to_posterior(msg)
    assert np.array_equal(back.obstacles, post.obstacles) and (back.obstacles < 0).sum() == (obstacles > 0).sum()
    plain = cv.gpis_model_to_posterior(cv.posterior_to_gpis_model(posterior_from_grids(occ, noise, g),
                                                                  cv.header(f, 1, 'cam'), f, com_samples=0))
    assert plain.obstacles is None
    msg.obstacle_distance = [0.01] * 7
    with pytest.raises(ValueError, match='obstacle_distance has 7 values'):
        cv.gpis_model_to_posterior(msg)


@pytest.mark.parametrize('late', [False, True])
def test_gpis_node_puts_the_matching_obstacles_in_the_model(late):
    """Published before the grids, the obstacles are in the first model; published after the fit (topics are
    not ordered), the model is published again with them, from the same fit. Another frame's obstacles count
    for nothing."""
    from nav_msgs.msg import OccupancyGrid
    from rclpy.parameter import Parameter

    from gpis_grasp_interfaces.msg import FloatGrid, GpisModel
    from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS
    from gpis_grasp_ros.ros.nodes.gpis_node import GpisNode
    from support.rosutil import RosHarness, wait_for

    f = rcv.RclpyFactory()
    g, occ, noise, obstacles = _grids()
    expected = obstacle_distance(obstacles, g)
    ros = RosHarness(threads=4)
    try:
        ros.add(GpisNode(context=ros.context, parameter_overrides=[Parameter('blur_samples', value=20)]))
        client = ros.node('obstacles_client')
        models = []
        client.create_subscription(GpisModel, 'gpis/model', models.append, LATCHED_QOS)
        occ_pub = client.create_publisher(OccupancyGrid, 'object/occupancy', LATCHED_QOS)
        noise_pub = client.create_publisher(FloatGrid, 'object/noise_map', LATCHED_QOS)
        obstacles_pub = client.create_publisher(OccupancyGrid, 'object/obstacles', LATCHED_QOS)
        stamp = 7_000_000_000

        def publish_obstacles(t_ns: int) -> None:
            obstacles_pub.publish(cv.numpy_to_occupancy_grid(f, obstacles, g, cv.header(f, t_ns, 'cam')))

        if not late:
            publish_obstacles(stamp)
            wait_for(lambda: False, 0.5)
        occ_pub.publish(cv.numpy_to_occupancy_grid(f, occ, g, cv.header(f, stamp, 'cam')))
        noise_pub.publish(cv.numpy_to_float_grid(f, noise, g, cv.header(f, stamp, 'cam'), unit='m^2'))
        assert wait_for(lambda: bool(models), 60.0)
        if late:
            assert len(models[-1].obstacle_distance) == 0
            publish_obstacles(stamp + 10**9)  # another frame's: ignored
            wait_for(lambda: len(models) > 1, 1.0)
            assert len(models) == 1
            publish_obstacles(stamp)
            assert wait_for(lambda: len(models) > 1, 10.0)
            assert list(models[-1].mean) == list(models[0].mean)
        got = cv.gpis_model_to_posterior(models[-1]).obstacles
        assert got is not None and np.allclose(got, expected, atol=1e-12)
    finally:
        ros.close()


def test_a_neighbour_seen_by_segmentation_node_keeps_the_planned_jaws_out():
    """Two boxes 1 cm apart seen at 40 degrees through the node graph: segmentation_node publishes the smaller
    one as obstacles on the larger target's grid (same stamp and grid), gpis_node carries them in the model,
    and planner_node's grasp keeps both jaws outside them."""
    from nav_msgs.msg import OccupancyGrid
    from rclpy.parameter import Parameter

    from gpis_grasp_interfaces.msg import GpisModel
    from gpis_grasp_interfaces.srv import GraspPlan
    from gpis_grasp_ros.core.sdf_bank import bilinear
    from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS
    from gpis_grasp_ros.ros.nodes.gpis_node import GpisNode
    from gpis_grasp_ros.ros.nodes.planner_node import PlannerNode
    from support.rosutil import RosHarness, segmentation_graph, wait_for
    from support.tilted_scene import Box, TiltedScene

    scene = TiltedScene(40.0, distance_m=0.7, width=320, height=240, focal_px=285.0,
                        boxes=[Box(-0.035, 0.0, 0.03, 0.02, 0.03), Box(0.02, 0.0, 0.015, 0.02, 0.04,
                                                                        rgb=(200.0, 60.0, 40.0))])
    rgb, depth, _ = scene.frames(1, seed=4)
    f = rcv.RclpyFactory()
    xyz = (scene.intrinsics.rays() * depth[0][..., None]).astype(np.float32)
    cloud = cv.xyz_rgb_to_pointcloud2(f, xyz, rgb[0], cv.header(f, 3_000_000_000, 'cam'))
    ros = RosHarness(threads=4)
    try:
        _, grids, status, pub = segmentation_graph(ros, [])
        ros.add(GpisNode(context=ros.context, parameter_overrides=[Parameter('blur_samples', value=20)]))
        planner = ros.add(PlannerNode(context=ros.context, parameter_overrides=[
            Parameter('num_shape_samples', value=200), Parameter('num_initial_grasps', value=3)]))
        client = ros.node('neighbour_client')
        models, obstacle_grids = [], []
        client.create_subscription(GpisModel, 'gpis/model', models.append, LATCHED_QOS)
        client.create_subscription(OccupancyGrid, 'object/obstacles', obstacle_grids.append, LATCHED_QOS)
        plan_cli = client.create_client(GraspPlan, 'plan_grasp')
        pub.publish(cloud)
        # the model with the obstacles (first, or re-published when the grid came after the fit), in the planner
        assert wait_for(lambda: bool(obstacle_grids) and any(len(m.obstacle_distance) for m in models)
                        and planner.has_model() and planner._latest_model(0.0)[1].obstacles is not None, 60.0), status
        occ_msg, obs_msg = grids[-1], obstacle_grids[-1]
        assert obs_msg.header.stamp == occ_msg.header.stamp and obs_msg.info == occ_msg.info
        n_cells = sum(v == 100 for v in obs_msg.data)  # the neighbour's part inside the target's grid
        assert n_cells >= 4
        posterior = cv.gpis_model_to_posterior(models[-1])
        assert posterior.obstacles is not None and (posterior.obstacles < 0).sum() == n_cells
        plan = ros.call(plan_cli, GraspPlan.Request(method='gp-gpis-opt', seed=0), timeout=120.0)
        assert plan.success, plan.message
        jaws = np.stack([posterior.geometry.from_sensor(np.array([p.x, p.y, p.z]))[0]
                         for p in (plan.jaw1.pose.position, plan.jaw2.pose.position)])
        assert np.all(bilinear(posterior.obstacles, posterior.geometry, jaws) > 0.0)
    finally:
        ros.close()
