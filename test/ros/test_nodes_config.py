"""config/default.yaml documents exactly the parameters the nodes declare, with their defaults."""

from __future__ import annotations

import sys
from pathlib import Path

import rclpy
import yaml
from rclpy.context import Context

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / 'scripts'))

from gen_default_config import node_parameters  # noqa: E402


def test_default_yaml_matches_declared_parameters():
    context = Context()
    rclpy.init(context=context)
    try:
        declared = node_parameters(context)
    finally:
        rclpy.try_shutdown(context=context)
    documented = yaml.safe_load((ROOT / 'config' / 'default.yaml').read_text())
    # '/**/node:' keys: the file applies to the nodes under any namespace
    assert set(documented) == {f'/**/{node}' for node in declared}
    for node, rows in declared.items():
        values = documented[f'/**/{node}']['ros__parameters']
        assert set(values) == {name for name, _, _ in rows}, node
        for name, default, description in rows:
            assert values[name] == default, f'{node}.{name}'
            assert description, f'{node}.{name} has no description'


def test_gpis_settings_are_node_parameters():
    """The GPIS settings a user tunes for their objects are gpis_node parameters, set at run time
    (`ros2 param set`), mapped onto GpisParams (0 = off where documented) and range-checked."""
    from rclpy.parameter import Parameter

    from gpis_grasp_ros.core import gpis
    from gpis_grasp_ros.ros.nodes.gpis_node import GpisNode

    context = Context()
    rclpy.init(context=context)
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
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def test_perception_model_switches_are_segmentation_parameters():
    """The clear-body extension and the unknown-cell model are segmentation_node parameters mapped onto
    SensingParams at run time; out-of-range values are refused and leave the settings unchanged."""
    from rclpy.parameter import Parameter

    from gpis_grasp_ros.core import sensing
    from gpis_grasp_ros.ros.nodes.segmentation_node import SegmentationNode

    context = Context()
    rclpy.init(context=context)
    node = SegmentationNode(context=context)
    try:
        d = sensing.SensingParams()
        assert node.params.chroma_z_min == d.chroma_z_min
        ok = node.set_parameters([Parameter('chroma_z_min', value=0.0)])[0]
        assert ok.successful, ok.reason
        assert node.params.chroma_z_min == 0.0
        assert not node.set_parameters([Parameter('chroma_z_min', value=-1.0)])[0].successful
        assert node.params.chroma_z_min == 0.0
        assert (node.params.clear_body_prism, node.params.train_clear_body) == (True, True) == (
            d.clear_body_prism, d.train_clear_body)
        ok = node.set_parameters([Parameter('clear_body_prism', value=False),
                                  Parameter('train_clear_body', value=False)])
        assert all(r.successful for r in ok)
        assert (node.params.clear_body_prism, node.params.train_clear_body) == (False, False)
        assert not node.set_parameters([Parameter('clear_body_prism', value=1.5)])[0].successful  # wrong type
        assert node.params.clear_body_prism is False
        assert node.params.see_through_test is True is d.see_through_test
        assert node.set_parameters([Parameter('see_through_test', value=False)])[0].successful
        assert node.params.see_through_test is False
        assert node.params.shadow_test is True is d.shadow_test
        assert node.set_parameters([Parameter('shadow_test', value=False)])[0].successful
        assert node.params.shadow_test is False
        assert node.params.sensor.occluder_x_m == 0.075  # carmine's projector (sensor_model is read-only)
        assert node.params.clear_body_height_m == 0.0 == d.clear_body_height_m  # the priors
        assert node.set_parameters([Parameter('clear_body_height', value=0.061)])[0].successful
        assert node.params.clear_body_height_m == 0.061
        for bad in (-0.01, 0.5):  # below 0, above max_object_height_m
            assert not node.set_parameters([Parameter('clear_body_height', value=bad)])[0].successful
        assert node.params.clear_body_height_m == 0.061
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
