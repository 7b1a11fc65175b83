"""What the planner and the gripper can use: grids too small or too thin, models without a surface, negative
stamps, implausible heights and centres of mass, inexact method names (launch-free, callbacks called directly)."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PointStamped
from rclpy.parameter import Parameter

from gpis_grasp_interfaces.msg import FloatGrid
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.data.bags import load_bag, posterior_from_scene
from gpis_grasp_ros.ros import conversions, validation
from gpis_grasp_ros.ros.nodes.gpis_node import GpisNode
from gpis_grasp_ros.ros.nodes.gripper_sim_node import GripperSimNode
from gpis_grasp_ros.ros.nodes.planner_node import PlannerNode
from gpis_grasp_ros.ros.nodes.segmentation_node import SegmentationNode
from support.rosutil import RosHarness

BAG_H = next((Path(__file__).resolve().parents[2] / 'bags').glob('H_*.mcap'))
F = conversions.RclpyFactory()


@pytest.fixture(scope='module')
def posterior():
    return posterior_from_scene(load_bag(BAG_H))[0]


@pytest.fixture(scope='module')
def model_msg(posterior):
    return messages.posterior_to_gpis_model(posterior, messages.header(F, 1, 'cam'), F)


@pytest.fixture
def ros():
    harness = RosHarness()
    yield harness
    harness.close()


def _small_model(model_msg, side: tuple[int, int]):
    """``model_msg`` claiming a grid of ``side`` = (rows, cols) cells (its mean and variance left out)."""
    bad = copy.deepcopy(model_msg)
    bad.info.height, bad.info.width = side
    bad.mean, bad.variance = [], []
    return bad


@pytest.mark.parametrize('side', [(1, 1), (2, 2), (3, 12), (4, 20)])
def test_a_model_the_planner_cannot_use_is_rejected_and_keeps_the_good_one(ros, model_msg, side):
    planner = ros.add(PlannerNode(context=ros.context))
    planner._on_model(model_msg)
    assert planner.has_model() and planner.rejected == 0
    bad = _small_model(model_msg, side)
    with pytest.raises(ValueError, match='at least 4 x 4|more unequal'):
        validation.check_gpis_model(bad, planner.config.limits)
    planner._on_model(bad)
    assert planner.rejected == 1
    assert planner._model is model_msg  # the good model stays


def test_a_model_without_a_surface_is_rejected(posterior):
    from dataclasses import replace
    with pytest.raises(ValueError, match='no object'):
        validation.check_posterior(replace(posterior, mean=np.abs(posterior.mean) + 1e-3))
    with pytest.raises(ValueError, match='no free space'):
        validation.check_posterior(replace(posterior, mean=-np.abs(posterior.mean) - 1e-3))


def test_a_grid_narrower_than_the_jaws_is_rejected(model_msg):
    limits = validation.Limits(min_extent=1.0)
    with pytest.raises(ValueError, match='narrower than the jaw width'):
        validation.check_gpis_model(model_msg, limits)


def test_a_one_cell_occupancy_grid_is_rejected_by_gpis_node(ros):
    from nav_msgs.msg import OccupancyGrid
    gpis = ros.add(GpisNode(context=ros.context))
    msg = OccupancyGrid()
    msg.info.width = msg.info.height = 1
    msg.info.resolution = 0.005
    msg.info.origin.orientation.w = 1.0
    msg.data = [100]
    gpis._on_occupancy(msg)
    assert gpis.rejected == 1 and gpis._occupancy is None


def test_a_one_cell_ground_truth_is_rejected(ros):
    sim = ros.add(GripperSimNode(context=ros.context))
    msg = FloatGrid()
    msg.info.width = msg.info.height = 1
    msg.info.resolution = 0.005
    msg.info.origin.orientation.w = 1.0
    msg.data = [-0.001]
    sim._on_sdf(msg)
    assert sim.rejected == 1 and sim._sdf is None


def test_negative_stamps_are_rejected_on_input(ros, model_msg):
    seg = ros.add(SegmentationNode(context=ros.context, parameter_overrides=[
        Parameter('input_reliability', value='reliable')]))
    from sensor_msgs.msg import PointCloud2, PointField
    cloud = PointCloud2()
    cloud.header.stamp.sec = -5
    cloud.fields = [PointField(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate('xyz')]
    cloud.height, cloud.width, cloud.point_step = 4, 4, 16
    cloud.row_step = 64
    cloud.data = bytes(256)
    with pytest.raises(ValueError, match='header.stamp'):
        validation.check_pointcloud(cloud, validation.Limits())
    seg._on_cloud(cloud)  # rejected with the reason, never reaches the guard
    assert seg.rejected == 1
    bad = copy.deepcopy(model_msg)
    bad.header.stamp.sec = -1
    with pytest.raises(ValueError, match='header.stamp'):
        validation.check_gpis_model(bad, validation.Limits())


def test_one_object_height_limit_and_a_top_at_the_camera_is_not_an_object(ros, posterior):
    gpis = ros.add(GpisNode(context=ros.context))
    header = messages.header(F, 1, 'cam')
    top = PointStamped()
    top.header = header  # the camera origin: about 0.7 m above the table
    gpis._top = top
    assert gpis.object_height(header, posterior.geometry, 0.0) == 0.0
    assert gpis.rejected == 1
    with pytest.raises(ValueError, match='off the grid|highest object'):
        validation.object_height_of(np.zeros(3), posterior.geometry)
    planner = ros.add(PlannerNode(context=ros.context))
    assert not planner.set_parameters([Parameter('object_height', value=0.7)])[0].successful
    assert validation.MAX_OBJECT_HEIGHT == 0.4


def test_a_centre_of_mass_off_the_ground_truth_grid_is_rejected(ros, posterior):
    sim = ros.add(GripperSimNode(context=ros.context))
    g = posterior.geometry
    sim._on_sdf(messages.numpy_to_float_grid(F, posterior.mean, g, messages.header(F, 1, 'cam'), 'm'))
    assert sim._sdf is not None
    far = PointStamped()
    far.point.x, far.point.z = 10.0, 0.5
    sim._on_com(far)
    assert sim.rejected == 1 and sim._com is None


def test_a_method_is_exactly_one_of_the_names(ros, model_msg):
    planner = ros.add(PlannerNode(context=ros.context))
    planner._on_model(model_msg)
    for name in ('   ', ' gp-m', 'GP-M', 'gp-m\n'):
        reason = planner._make_job(name, 0, -1.0, 1)
        assert isinstance(reason, str) and 'unknown method' in reason and "empty = the node's method" in reason
    assert planner._make_job('', 0, -1.0, 1).method == planner.config.method
    assert planner._make_job('gp-m', 0, -1.0, 1).method == 'gp-m'
