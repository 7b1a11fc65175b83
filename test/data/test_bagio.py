"""rosbag2 / MCAP writing and reading with rosbags."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.interfaces import QosDurability, QosReliability
from rosbags.rosbag2 import Reader

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.data import bagio
from gpis_grasp_ros.data import messages as cv

TS = bagio.get_typestore()
F = cv.RosbagsFactory(TS)
T0 = 1_432_598_400_000_000_000


def _write_sample(path, n=3, **kwargs):
    geom = GridGeometry(0.0, 0.0, 0.01, 4, 3, 0.7, 'cam')
    with bagio.BagWriter(path, **kwargs) as bag:
        bag.add_topic('/gt/sdf', 'gpis_grasp_interfaces/msg/FloatGrid', bagio.LATCHED_QOS)
        bag.add_topic('/cam/info', 'sensor_msgs/msg/CameraInfo', bagio.SENSOR_QOS)
        bag.write('/gt/sdf', T0, cv.numpy_to_float_grid(F, np.full((3, 4), 0.5), geom, cv.header(F, T0, 'cam')))
        for i in range(n):
            t = T0 + (i + 1) * 33_333_333
            bag.write('/cam/info', t, cv.intrinsics_to_camera_info(F, 570.0, 570.0, 10.0 + i, 8.0, 20, 16,
                                                                   cv.header(F, t, 'cam')))


def test_typestore_has_interface_types():
    assert bagio.interface_msg_dir().name == 'msg'
    for name in ('gpis_grasp_interfaces/msg/FloatGrid', 'gpis_grasp_interfaces/msg/GpisModel',
                 'sensor_msgs/msg/PointCloud2', 'nav_msgs/msg/OccupancyGrid'):
        assert name in TS.types
    assert bagio.get_typestore() is TS  # cached


def test_single_file_round_trip_with_qos(tmp_path):
    path = tmp_path / 'x.mcap'
    _write_sample(path, custom_data={'k': 'v'})
    assert path.is_file()
    assert [p.name for p in tmp_path.iterdir()] == ['x.mcap']  # no temp directory left
    info = bagio.bag_topics(path)
    assert info['/gt/sdf']['count'] == 1 and info['/cam/info']['count'] == 3
    (gt_qos,), (cam_qos,) = info['/gt/sdf']['qos'], info['/cam/info']['qos']
    assert (gt_qos.reliability, gt_qos.durability, gt_qos.depth) == \
        (QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, 1)
    assert (cam_qos.reliability, cam_qos.durability, cam_qos.depth) == \
        (QosReliability.BEST_EFFORT, QosDurability.VOLATILE, 5)

    records = list(bagio.iter_bag(path))
    assert [r.topic for r in records] == ['/gt/sdf'] + ['/cam/info'] * 3
    assert [r.t_ns for r in records] == sorted(r.t_ns for r in records)
    topic, msgtype, t_ns, raw, qos = records[1]  # plain tuple unpacking works
    assert msgtype == 'sensor_msgs/msg/CameraInfo' and isinstance(raw, bytes) and qos[0] == cam_qos

    msgs = list(bagio.read_messages(path, topics=['cam/info']))
    assert [cv.camera_info_to_intrinsics(m)[2] for _, _, _, m in msgs] == [10.0, 11.0, 12.0]
    sdf, geom = cv.float_grid_to_numpy(next(bagio.read_messages(path, ['/gt/sdf']))[3], expect_unit='m')
    assert np.allclose(sdf, 0.5) and geom.shape == (3, 4)

    with Reader(path) as reader:  # rosbags' low-level reader sees the embedded metadata
        assert reader.message_count == 4
    assert b'zstd' in path.read_bytes()  # chunks are zstd-compressed


def test_directory_bag(tmp_path):
    path = tmp_path / 'dir_bag'
    _write_sample(path)
    assert (path / 'metadata.yaml').is_file() and (path / 'dir_bag.mcap').is_file()
    assert len(list(bagio.iter_bag(path))) == 4


def test_existing_output_and_overwrite(tmp_path):
    path = tmp_path / 'x.mcap'
    _write_sample(path, n=1)
    with pytest.raises(FileExistsError, match='exists already'):
        _write_sample(path, n=2)
    assert bagio.bag_topics(path)['/cam/info']['count'] == 1
    _write_sample(path, n=2, overwrite=True)
    assert bagio.bag_topics(path)['/cam/info']['count'] == 2


def test_error_leaves_no_partial_bag(tmp_path):
    path = tmp_path / 'x.mcap'
    with pytest.raises(RuntimeError, match='boom'):
        with bagio.BagWriter(path) as bag:
            bag.add_topic('/a', 'std_msgs/msg/Header', bagio.SENSOR_QOS)
            bag.write('/a', T0, cv.header(F, T0, 'x'))
            raise RuntimeError('boom')
    assert list(tmp_path.iterdir()) == []
    # an existing bag survives a failed overwrite untouched
    _write_sample(path, n=1)
    before = path.read_bytes()
    with pytest.raises(ValueError, match="topic '/nope' was not added"):
        with bagio.BagWriter(path, overwrite=True) as bag:
            bag.write('/nope', T0, cv.header(F, T0, 'x'))
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ['x.mcap']


def test_writes_are_deterministic(tmp_path):
    """Same content and file name → identical bytes (the embedded metadata holds the file name)."""
    _write_sample(tmp_path / 'a' / 'x.mcap')
    _write_sample(tmp_path / 'b' / 'x.mcap')
    assert (tmp_path / 'a' / 'x.mcap').read_bytes() == (tmp_path / 'b' / 'x.mcap').read_bytes()


def test_missing_bag_raises(tmp_path):
    with pytest.raises(FileNotFoundError, match='does not exist'):
        list(bagio.iter_bag(tmp_path / 'missing.mcap'))
    with pytest.raises(FileNotFoundError, match='does not exist'):
        bagio.bag_topics(tmp_path / 'missing.mcap')
