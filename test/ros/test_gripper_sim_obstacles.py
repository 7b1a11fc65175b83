"""gripper_sim_node executes in the truth's world: ``ground_truth/obstacles`` (the other labelled objects) fails
the jaws that meet them, exactly as the offline evaluation does; obstacles on another grid are refused by name."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.sim.execution import execute_grasp_trials
from support.synthetic_shapes import rectangle_sdf


def test_gripper_sim_fails_jaws_on_other_objects_and_refuses_a_foreign_grid():
    from geometry_msgs.msg import PoseStamped

    from gpis_grasp_interfaces.msg import FloatGrid
    from gpis_grasp_interfaces.srv import ExecuteGrasp
    from gpis_grasp_ros.data import messages
    from gpis_grasp_ros.ros import conversions
    from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS
    from gpis_grasp_ros.ros.nodes.gripper_sim_node import GripperSimNode
    from support.rosutil import RosHarness, wait_for

    f = conversions.RclpyFactory()
    g = GridGeometry(-0.05, -0.05, 0.001, 150, 150, 0.7, 'cam')
    c = np.array([0.0, 0.0])
    target = rectangle_sdf(g, tuple(c), (0.015, 0.01))
    neighbour = rectangle_sdf(g, (0.045, 0.0), (0.018, 0.02))  # 12 mm right of the target

    def pose(xy: np.ndarray) -> PoseStamped:
        p = PoseStamped()
        p.header.frame_id = 'cam'
        p.pose.position.x, p.pose.position.y, p.pose.position.z = (float(v) for v in g.to_sensor(xy, 0.0))
        p.pose.orientation.w = 1.0
        return p

    ros = RosHarness()
    try:
        node = ros.add(GripperSimNode(context=ros.context))
        probe = ros.node('probe')
        sdf_pub = probe.create_publisher(FloatGrid, 'ground_truth/sdf', LATCHED_QOS)
        obs_pub = probe.create_publisher(FloatGrid, 'ground_truth/obstacles', LATCHED_QOS)
        sdf_pub.publish(messages.numpy_to_float_grid(f, target.astype(np.float32), g, messages.header(f, 1, 'cam'),
                                                     'm'))
        obs_pub.publish(messages.numpy_to_float_grid(f, neighbour.astype(np.float32), g,
                                                     messages.header(f, 1, 'cam'), 'm'))
        assert wait_for(lambda: node._obstacles is not None and node._sdf is not None, 10.0)
        cli = probe.create_client(ExecuteGrasp, 'execute_grasp')
        across = ExecuteGrasp.Request(jaw1=pose(c - [0.022, 0.0]), jaw2=pose(c + [0.066, 0.0]), trials=50, seed=4)
        res = ros.call(cli, across)
        assert res.success and res.successes == 0, res.message  # the right jaw closes through the neighbour
        collisions = int(res.message.split('(collision ')[1].split(',')[0])
        assert collisions >= 45 and res.message.endswith('on the true shape'), res.message
        along = ExecuteGrasp.Request(jaw1=pose(c - [0.0, 0.03]), jaw2=pose(c + [0.0, 0.03]), trials=50, seed=4)
        res = ros.call(cli, along)
        j = [g.from_sensor(g.to_sensor(p, 0.0))[0] for p in (c - [0.0, 0.03], c + [0.0, 0.03])]
        expected = execute_grasp_trials(target.astype(np.float32).astype(np.float64), g, j[0], j[1], GripperParams(),
                                        50, np.random.default_rng(4), obstacles=neighbour.astype(np.float32))
        assert res.success and res.successes == expected >= 45, res.message
        foreign = replace(g, origin_x=g.origin_x + 0.01)
        obs_pub.publish(messages.numpy_to_float_grid(f, neighbour.astype(np.float32), foreign,
                                                     messages.header(f, 2, 'cam'), 'm'))
        assert wait_for(lambda: abs(node._obstacles[1].origin_x - foreign.origin_x) < 1e-9, 10.0)
        res = ros.call(cli, along)
        assert not res.success and 'not on the grid of ground_truth/sdf' in res.message
        bad = neighbour.astype(np.float32)
        bad[3, 4] = np.nan  # refused (counted, logged with the reason), the previous grid kept
        rejected = node.rejected
        obs_pub.publish(messages.numpy_to_float_grid(f, bad, g, messages.header(f, 3, 'cam'), 'm'))
        assert wait_for(lambda: node.rejected == rejected + 1, 10.0)
        assert abs(node._obstacles[1].origin_x - foreign.origin_x) < 1e-9
    finally:
        ros.close()
