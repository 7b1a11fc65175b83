"""The nodes' parameter tables: what the nodes declare, config/default.yaml, the README tables, and
how the values reach the library dataclasses."""

from __future__ import annotations

from pathlib import Path

import pytest
import rclpy
import yaml
from rclpy.context import Context
from rclpy.parameter import Parameter

from gpis_grasp_ros.ros import params as ros_params

ROOT = Path(__file__).resolve().parents[2]
BUILT_IN = {'use_sim_time', 'start_type_description_service'}  # rclpy's own parameters
NODE_CLASSES = {
    'segmentation_node': 'gpis_grasp_ros.ros.nodes.segmentation_node:SegmentationNode',
    'gpis_node': 'gpis_grasp_ros.ros.nodes.gpis_node:GpisNode',
    'planner_node': 'gpis_grasp_ros.ros.nodes.planner_node:PlannerNode',
    'gripper_sim_node': 'gpis_grasp_ros.ros.nodes.gripper_sim_node:GripperSimNode',
}


def _node_class(node: str):
    import importlib
    module, cls = NODE_CLASSES[node].split(':')
    return getattr(importlib.import_module(module), cls)


@pytest.fixture
def context():
    ctx = Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


def test_default_yaml_is_generated_from_the_tables():
    """config/default.yaml is exactly what `python -m gpis_grasp_ros.ros.params --yaml` writes."""
    assert (ROOT / 'config' / 'default.yaml').read_text() == ros_params.render_yaml(), \
        'config/default.yaml is out of date: python -m gpis_grasp_ros.ros.params --yaml > config/default.yaml'
    documented = yaml.safe_load((ROOT / 'config' / 'default.yaml').read_text())
    tables = ros_params.node_tables()
    assert set(documented) == {f'/**/{node}' for node in tables}
    for node, table in tables.items():
        assert documented[f'/**/{node}']['ros__parameters'] == table.defaults(), node


def test_readme_tables_are_current():
    """The tables between the README's <!-- params:NODE --> markers are the generated ones."""
    text = (ROOT / 'README.md').read_text()
    present = ros_params.readme_nodes(text)
    if not present:
        pytest.skip('README.md has no <!-- params:NODE --> markers yet')
    for node in present:
        start, end = f'<!-- params:{node} -->', f'<!-- /params:{node} -->'
        block = text[text.index(start) + len(start):text.index(end)]
        assert block == '\n' + ros_params.render_markdown(node), \
            f'README table of {node} is out of date: python -m gpis_grasp_ros.ros.params --update-readme README.md'


def test_update_readme_rewrites_between_markers_and_names_missing_ones():
    tables = ros_params.node_tables()
    text = 'intro\n' + ''.join(f'<!-- params:{n} -->\nSTALE TABLE\n<!-- /params:{n} -->\n' for n in tables) + 'end\n'
    out = ros_params.update_readme(text, tables)
    assert out.startswith('intro\n') and out.endswith('end\n') and 'STALE TABLE' not in out
    assert ros_params.update_readme(out, tables) == out  # idempotent
    assert '| `num_initial_grasps` | integer | `20` |' in out
    with pytest.raises(ValueError, match='params:gpis_node'):
        ros_params.update_readme(text.replace('<!-- /params:gpis_node -->', ''), tables)


@pytest.mark.parametrize('node', list(NODE_CLASSES))
def test_nodes_declare_exactly_their_table(node, context):
    """Every declared parameter comes from the table, with its default, description, range and read-only."""
    table = ros_params.node_tables()[node]
    instance = _node_class(node)(context=context)
    try:
        names = set(instance.list_parameters([], 0).names) - BUILT_IN
        assert names == set(table.params)
        for p in table:
            assert instance.get_parameter(p.name).value == p.default_value(), p.name
            d = instance.describe_parameter(p.name)
            assert d.description.startswith(p.description) and d.read_only == p.read_only, p.name
            if p.kind is float and p.low is not None:
                assert (d.floating_point_range[0].from_value, d.floating_point_range[0].to_value) == (p.low, p.high)
            if p.kind is int and p.low is not None:
                assert (d.integer_range[0].from_value, d.integer_range[0].to_value) == (p.low, p.high)
    finally:
        instance.destroy_node()


def test_defaults_come_from_the_library_dataclasses():
    from gpis_grasp_ros.core import gpis, gripper, planners, sensing

    tables = ros_params.node_tables()
    assert tables['segmentation_node']['grid_margin'].default_value() == sensing.SensingParams().margin
    assert tables['gpis_node']['length_scale_max_extent'].default_value() == gpis.GpisParams().length_scale_max_extent
    assert tables['planner_node']['num_initial_grasps'].default_value() == planners.PlannerParams().n_initial_grasps
    assert tables['planner_node']['friction_coefficient'].default_value() == gripper.GripperParams().friction_coef
    assert tables['planner_node']['friction_coefficient'].maps_to == 'GripperParams.friction_coef'


def test_gripper_is_one_group_in_metres(context):
    """planner_node and gripper_sim_node share the gripper, in metres on every grid: the same defaults, so P_F
    predicts what the simulated gripper executes."""
    from gpis_grasp_ros.core import gripper
    from gpis_grasp_ros.core.grid import GridGeometry
    from gpis_grasp_ros.ros.nodes.gripper_sim_node import GripperSimNode
    from gpis_grasp_ros.ros.nodes.planner_node import PlannerNode

    tables = ros_params.node_tables()
    for name in ('jaw_width', 'max_opening', 'friction_coefficient'):
        assert tables['planner_node'][name] == tables['gripper_sim_node'][name]
    opening = tables['planner_node']['max_opening'].default_value()
    assert tables['segmentation_node']['max_opening'].default_value() == opening
    planner = PlannerNode(context=context)
    sim = GripperSimNode(context=context)
    try:
        g = planner.config.gripper
        assert g == gripper.GripperParams(jaw_width=0.01, max_opening=0.09, friction_coef=0.5,
                                           position_noise=0.003, contact_patch=0.002)
        assert sim.gripper == g
        geometry = GridGeometry(0.0, 0.0, 0.004, 25, 25, 0.7, 'cam')
        assert g.sigma_g == 0.003 and g.patch_cells(geometry) == 0.5
        assert planner.set_parameters([Parameter('position_noise', value=0.002)])[0].successful
        assert planner.config.gripper.sigma_g == 0.002
        zero_patch = sim.set_parameters([Parameter('contact_patch', value=0.0)])[0]
        assert not zero_patch.successful and 'contact patch' in zero_patch.reason
        assert not sim.set_parameters([Parameter('position_noise', value=0.5)])[0].successful
        assert sim.gripper.position_noise == 0.003
    finally:
        planner.destroy_node()
        sim.destroy_node()


def test_gpis_settings_are_node_parameters(context):
    """The GPIS settings a user tunes for their objects are gpis_node parameters, set at run time
    (`ros2 param set`), mapped onto GpisParams (0 = off where documented) and range-checked."""
    from gpis_grasp_ros.core import gpis
    from gpis_grasp_ros.ros.nodes.gpis_node import GpisNode

    node = GpisNode(context=context)
    try:
        d = gpis.GpisParams()
        p = node.params
        assert (p.gradient_observations, p.gradient_noise_variance, p.search_band_cells, p.length_scale_min_cells,
                p.length_scale_max_extent, p.length_scale_max_thickness) == \
            (d.gradient_observations, d.gradient_noise_variance, d.search_band_cells, d.length_scale_min_cells,
             d.length_scale_max_extent, d.length_scale_max_thickness)
        ok = node.set_parameters([Parameter('gradient_observations', value=False),
                                  Parameter('length_scale_max_thickness', value=0.0),
                                  Parameter('search_band_cells', value=0.0),
                                  Parameter('length_scale_max_extent', value=0.25)])[0]
        assert ok.successful, ok.reason
        p = node.params
        assert p.gradient_observations is False and p.length_scale_max_thickness is None
        assert p.search_band_cells is None and p.length_scale_max_extent == 0.25
        bad = node.set_parameters([Parameter('length_scale_min_cells', value=0.0)])[0]
        assert not bad.successful
        assert node.params.length_scale_min_cells == d.length_scale_min_cells
        assert not node.set_parameters([Parameter('optimize_hyperparameters', value=1.5)])[0].successful  # type
        assert node.set_parameters([Parameter('max_resolution', value=0.01)])[0].successful
        inconsistent = node.set_parameters([Parameter('min_resolution', value=0.05)])[0]
        assert not inconsistent.successful and 'min_resolution' in inconsistent.reason
        assert node.config.limits.min_resolution == 1e-4
    finally:
        node.destroy_node()


def test_perception_settings_are_segmentation_parameters(context):
    """The clear-body settings a user tunes are segmentation_node parameters mapped onto SensingParams at run
    time; out-of-range values are refused and leave the settings unchanged. The perception ablation switches
    stay in the library (SensingParams) and are not node parameters."""
    from gpis_grasp_ros.core import sensing
    from gpis_grasp_ros.ros.nodes.segmentation_node import SegmentationNode

    node = SegmentationNode(context=context)
    try:
        d = sensing.SensingParams()
        for name in ('see_through_test', 'shadow_test', 'clear_body_prism', 'train_clear_body', 'exclude_uncertain',
                     'color_smooth_px', 'color_hole_margin_px', 'transparent_core_occupied'):
            assert not node.has_parameter(name), name
        assert (node.params.see_through_test, node.params.shadow_test, node.params.clear_body_prism,
                node.params.train_clear_body) == (d.see_through_test, d.shadow_test, d.clear_body_prism,
                                                  d.train_clear_body)
        assert node.params.chroma_z_min == d.chroma_z_min
        assert node.set_parameters([Parameter('chroma_z_min', value=0.0)])[0].successful
        assert node.params.chroma_z_min == 0.0
        assert not node.set_parameters([Parameter('chroma_z_min', value=-1.0)])[0].successful
        assert node.params.chroma_z_min == 0.0
        assert node.params.sensor.occluder_x_m == 0.075  # carmine's projector (sensor_model is read-only)
        assert node.params.clear_body_height_m == 0.0 == d.clear_body_height_m  # the priors
        assert node.set_parameters([Parameter('clear_body_height', value=0.061)])[0].successful
        assert node.params.clear_body_height_m == 0.061
        for bad in (-0.01, 0.5):  # below 0, above max_object_height_m
            assert not node.set_parameters([Parameter('clear_body_height', value=bad)])[0].successful
        assert node.params.clear_body_height_m == 0.061
        assert node.params.table_plane is None and node.params.target_point is None
        short = node.set_parameters([Parameter('roi_px', value=[1.0, 2.0])])[0]
        assert not short.successful and 'roi_px' in short.reason
        assert node.set_parameters([Parameter('target', value='pixel'), Parameter('target_point', value=[3.0, 4.0])])
        assert node.params.target_point == (3.0, 4.0)
    finally:
        node.destroy_node()


def test_perturbation_count_is_a_planner_parameter(context):
    """K_p of GP-GPIS-OPT's smoothed P_F is set on planner_node at run time and range-checked."""
    from gpis_grasp_ros.core import planners
    from gpis_grasp_ros.ros.nodes.planner_node import PlannerNode

    node = PlannerNode(context=context)
    try:
        assert node.config.planner.n_perturbations == planners.PlannerParams().n_perturbations == 32
        assert node.set_parameters([Parameter('num_perturbations', value=16)])[0].successful
        assert node.config.planner.n_perturbations == 16
        assert not node.set_parameters([Parameter('num_perturbations', value=0)])[0].successful
        assert node.config.planner.n_perturbations == 16
    finally:
        node.destroy_node()


def test_a_custom_sensor_rolled_a_quarter_turn(context):
    """A custom sensor model takes its second viewpoint anywhere in the image plane (a rolled camera)."""
    from gpis_grasp_ros.ros.nodes.segmentation_node import SegmentationNode

    node = SegmentationNode(context=context, parameter_overrides=[
        Parameter('sensor_model', value='custom'), Parameter('sensor_sigma_constant', value=0.001),
        Parameter('sensor_occluder_x', value=0.0), Parameter('sensor_occluder_y', value=0.075)])
    try:
        sensor = node.params.sensor
        assert sensor.name == 'custom' and (sensor.occluder_x_m, sensor.occluder_y_m) == (0.0, 0.075)
        assert sensor.sigma_constant_m == 0.001
    finally:
        node.destroy_node()
