"""The custom messages round-trip through rosbags' CDR with the types registered from the
interface package's .msg text, and the bytes agree with rclpy's own serialisation, so bag files
and live topics carry the same data."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gpis_grasp_ros.data import bagio

ROOT = Path(__file__).resolve().parents[2]
MSG_DIR = ROOT / 'gpis_grasp_interfaces' / 'msg'


@pytest.fixture(scope='module')
def typestore():
    # Jazzy typestore + the custom types registered from the interface package's .msg text
    assert sorted(p.stem for p in MSG_DIR.glob('*.msg')) == ['FloatGrid', 'GpisModel']
    return bagio.get_typestore()


def _header(ts, sec, nsec, frame):
    Header = ts.types['std_msgs/msg/Header']
    Time = ts.types['builtin_interfaces/msg/Time']
    return Header(stamp=Time(sec=sec, nanosec=nsec), frame_id=frame)


def _info(ts, res, w, h, ox, oy, oz):
    t = ts.types
    pose = t['geometry_msgs/msg/Pose'](
        position=t['geometry_msgs/msg/Point'](x=ox, y=oy, z=oz),
        orientation=t['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0))
    return t['nav_msgs/msg/MapMetaData'](
        map_load_time=t['builtin_interfaces/msg/Time'](sec=0, nanosec=0),
        resolution=res, width=w, height=h, origin=pose)


def test_float_grid_round_trip(typestore):
    ts = typestore
    data = np.linspace(-0.05, 0.05, 12, dtype=np.float32)
    msg = ts.types['gpis_grasp_interfaces/msg/FloatGrid'](
        header=_header(ts, 12, 345, 'camera_rgb_optical_frame'),
        info=_info(ts, 0.004, 4, 3, -0.05, -0.06, 0.7), unit='m', data=data)
    raw = ts.serialize_cdr(msg, 'gpis_grasp_interfaces/msg/FloatGrid')
    back = ts.deserialize_cdr(raw, 'gpis_grasp_interfaces/msg/FloatGrid')
    assert back.header.frame_id == 'camera_rgb_optical_frame'
    assert back.header.stamp.nanosec == 345
    assert back.info.width == 4 and back.info.height == 3
    assert back.info.resolution == pytest.approx(0.004)
    assert back.unit == 'm'
    np.testing.assert_array_equal(back.data, data)


def test_gpis_model_round_trip_and_matches_rclpy(typestore):
    ts = typestore
    rng = np.random.default_rng(3)
    n, cells = 7, 12
    t = ts.types
    msg = t['gpis_grasp_interfaces/msg/GpisModel'](
        header=_header(ts, 1, 2, 'cam'), info=_info(ts, 0.005, 4, 3, 0.1, 0.2, 0.69),
        resolution=0.005, signal_variance=1.5e-4, length_scale=0.012, prior_mean=-0.01, jitter=1e-10,
        hyperparameters_optimized=True,
        train_x=rng.normal(size=2 * n), train_y=rng.normal(size=n), train_noise_variance=rng.random(n),
        train_grad_x=rng.normal(size=4), train_grad_axis=np.array([0, 1], np.uint8), train_grad=rng.normal(size=2),
        train_grad_noise_variance=rng.random(2),
        mean=rng.normal(size=cells), variance=rng.random(cells),
        center_of_mass=t['geometry_msgs/msg/Point'](x=0.11, y=0.21, z=0.69), center_of_mass_std=0.001,
        object_height=0.033, obstacle_distance=rng.normal(size=cells))
    raw = ts.serialize_cdr(msg, 'gpis_grasp_interfaces/msg/GpisModel')
    back = ts.deserialize_cdr(raw, 'gpis_grasp_interfaces/msg/GpisModel')
    np.testing.assert_array_equal(back.train_x, msg.train_x)
    np.testing.assert_array_equal(back.variance, msg.variance)
    assert back.length_scale == msg.length_scale and back.hyperparameters_optimized

    # The same bytes decode with rclpy's generated type (live topics == bag files).
    from rclpy.serialization import deserialize_message, serialize_message

    from gpis_grasp_interfaces.msg import GpisModel
    live = deserialize_message(bytes(raw), GpisModel)
    assert live.header.frame_id == 'cam'
    np.testing.assert_array_equal(np.asarray(live.mean), msg.mean)
    np.testing.assert_array_equal(np.asarray(live.train_noise_variance), msg.train_noise_variance)
    np.testing.assert_array_equal(np.asarray(live.obstacle_distance), msg.obstacle_distance)
    assert live.center_of_mass.x == pytest.approx(0.11) and live.object_height == 0.033
    again = ts.deserialize_cdr(np.frombuffer(serialize_message(live), dtype=np.uint8),
                               'gpis_grasp_interfaces/msg/GpisModel')
    np.testing.assert_array_equal(again.train_y, msg.train_y)
    assert again.info.resolution == np.float32(msg.info.resolution)  # MapMetaData.resolution is float32
    assert again.resolution == msg.resolution and again.prior_mean == msg.prior_mean


def test_services_have_contract_fields():
    from gpis_grasp_interfaces.srv import ExecuteGrasp, GraspPlan
    req = GraspPlan.Request()
    for name in ('method', 'num_initial_grasps', 'uncertainty_penalty', 'seed'):
        assert hasattr(req, name)
    res = GraspPlan.Response()
    for name in ('success', 'message', 'jaw1', 'jaw2', 'grasp_pose', 'width', 'probability_force_closure',
                 'ferrari_canny_on_mean', 'objective', 'planning_time'):
        assert hasattr(res, name)
    ereq, eres = ExecuteGrasp.Request(), ExecuteGrasp.Response()
    for name in ('jaw1', 'jaw2', 'trials', 'seed'):
        assert hasattr(ereq, name)
    for name in ('success', 'message', 'trials', 'successes', 'success_rate'):
        assert hasattr(eres, name)
