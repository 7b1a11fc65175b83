"""Message <-> numpy conversions for rosbags dataclasses and rclpy messages (no rclpy.init needed)."""

from __future__ import annotations

import array
import copy

import numpy as np
import pytest

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.data import bagio
from gpis_grasp_ros.data import messages as cv
from gpis_grasp_ros.ros import conversions as rcv

TS = bagio.get_typestore()
STAMP = 1_432_598_400_123_456_789


def _rosbags_cdr(msg, msgtype):
    """Serialize + deserialize a rosbags message (what reading a bag gives)."""
    return TS.deserialize_cdr(TS.serialize_cdr(msg, msgtype), msgtype)


def _rclpy_cdr(msg, msgtype):
    from rclpy.serialization import deserialize_message, serialize_message

    return deserialize_message(serialize_message(msg), rcv.rclpy_message_class(msgtype))


FACTORIES = {
    'rosbags': (lambda: cv.RosbagsFactory(TS), _rosbags_cdr),
    'rclpy': (rcv.RclpyFactory, _rclpy_cdr),
}


@pytest.fixture(params=sorted(FACTORIES))
def flavour(request):
    make, wire = FACTORIES[request.param]
    return make(), wire


def _cloud(h: int = 4, w: int = 5, seed: int = 0):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(h, w, 3)).astype(np.float32)
    xyz[1, 2] = np.nan
    rgb = rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
    return xyz, rgb


def test_header_and_stamp(flavour):
    f, wire = flavour
    hdr = wire(cv.header(f, STAMP, 'cam'), 'std_msgs/msg/Header')
    assert hdr.frame_id == 'cam'
    assert cv.stamp_to_ns(hdr) == STAMP
    assert cv.stamp_to_ns(hdr.stamp) == STAMP
    with pytest.raises(ValueError, match='non-negative'):
        cv.header(f, -1, 'cam')


def test_pointcloud_round_trip(flavour):
    f, wire = flavour
    xyz, rgb = _cloud()
    msg = cv.xyz_rgb_to_pointcloud2(f, xyz, rgb, cv.header(f, STAMP, 'cam'))
    assert not msg.is_dense and msg.height == 4 and msg.width == 5 and msg.point_step == 16
    for m in (msg, wire(msg, 'sensor_msgs/msg/PointCloud2')):
        xyz2, rgb2 = cv.pointcloud2_to_xyz_rgb(m)
        np.testing.assert_array_equal(xyz2, xyz)  # NaN-aware
        np.testing.assert_array_equal(rgb2, rgb)
        assert xyz2.dtype == np.float32 and rgb2.dtype == np.uint8


def test_pointcloud_padding_big_endian_and_uint32_rgb():
    """Readers honour offsets, padded points and rows, big-endian data and a uint32 rgb field."""
    f = cv.RosbagsFactory(TS)
    xyz, rgb = _cloud(3, 4, seed=1)
    h, w = xyz.shape[:2]
    point_step, row_step = 24, 24 * w + 8
    dt = np.dtype({'names': ['rgb', 'x', 'y', 'z'], 'formats': ['>u4', '>f4', '>f4', '>f4'],
                   'offsets': [0, 8, 12, 16], 'itemsize': point_step})
    pts = np.zeros((h, w), dtype=dt)
    pts['x'], pts['y'], pts['z'] = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    pts['rgb'] = (rgb[..., 0].astype(np.uint32) << 16) | (rgb[..., 1].astype(np.uint32) << 8) | rgb[..., 2]
    rows = np.zeros((h, row_step), dtype=np.uint8)
    rows[:, :w * point_step] = pts.view(np.uint8).reshape(h, -1)
    fields = [f.new('sensor_msgs/msg/PointField', name=n, offset=o, datatype=d, count=1)
              for n, o, d in (('rgb', 0, 6), ('x', 8, 7), ('y', 12, 7), ('z', 16, 7))]
    msg = f.new('sensor_msgs/msg/PointCloud2', header=cv.header(f, 0, 'c'), height=h, width=w, fields=fields,
                is_bigendian=True, point_step=point_step, row_step=row_step, data=rows.ravel(), is_dense=False)
    xyz2, rgb2 = cv.pointcloud2_to_xyz_rgb(msg)
    np.testing.assert_array_equal(xyz2, xyz)
    np.testing.assert_array_equal(rgb2, rgb)


def test_pointcloud_bad_messages_raise_clear_errors():
    f = cv.RosbagsFactory(TS)
    xyz, rgb = _cloud()
    good = cv.xyz_rgb_to_pointcloud2(f, xyz, rgb, cv.header(f, 0, 'c'))

    no_rgb = copy.copy(good)
    no_rgb.fields = good.fields[:3]
    with pytest.raises(ValueError, match=r"lacks field\(s\) \['rgb'\]"):
        cv.pointcloud2_to_xyz_rgb(no_rgb)
    wrong_type = copy.copy(good)
    wrong_type.fields = [f.new('sensor_msgs/msg/PointField', name=fl.name, offset=fl.offset,
                               datatype=8 if fl.name == 'x' else fl.datatype, count=1) for fl in good.fields]
    with pytest.raises(ValueError, match="field 'x' has datatype 8"):
        cv.pointcloud2_to_xyz_rgb(wrong_type)
    short = copy.copy(good)
    short.data = good.data[:-1]
    with pytest.raises(ValueError, match='data has .* bytes, expected'):
        cv.pointcloud2_to_xyz_rgb(short)
    bad_step = copy.copy(good)
    bad_step.row_step = good.row_step - 1
    with pytest.raises(ValueError, match='row_step'):
        cv.pointcloud2_to_xyz_rgb(bad_step)
    with pytest.raises(ValueError, match='rgb shape'):
        cv.xyz_rgb_to_pointcloud2(f, xyz, rgb[:, :2], cv.header(f, 0, 'c'))


@pytest.mark.parametrize('encoding', ['rgb8', 'bgr8', 'mono8', '32FC1', '16UC1'])
def test_image_round_trip(flavour, encoding):
    f, wire = flavour
    rng = np.random.default_rng(3)
    if encoding in ('rgb8', 'bgr8'):
        arr = rng.integers(0, 256, size=(6, 7, 3), dtype=np.uint8)
    elif encoding == 'mono8':
        arr = rng.integers(0, 256, size=(6, 7), dtype=np.uint8)
    else:
        arr = rng.uniform(0.5, 1.5, size=(6, 7)).astype(np.float32)
        arr[2, 3] = np.nan
        if encoding == '16UC1':
            arr = np.where(np.isfinite(arr), np.round(arr * 1000) / 1000, np.nan).astype(np.float32)
    msg = cv.numpy_to_image(f, arr, encoding, cv.header(f, STAMP, 'cam'))
    assert msg.encoding == encoding
    for m in (msg, wire(msg, 'sensor_msgs/msg/Image')):
        out = cv.image_to_numpy(m)
        assert out.shape == arr.shape
        if encoding == '16UC1':
            np.testing.assert_allclose(out, arr, atol=1e-6)
            assert np.isnan(out[2, 3])
        else:
            np.testing.assert_array_equal(out, arr)
    if encoding == 'bgr8':  # wire order is BGR, numpy side is RGB
        raw = np.frombuffer(bytes(msg.data), dtype=np.uint8).reshape(6, 7, 3)
        np.testing.assert_array_equal(raw, arr[..., ::-1])


def test_image_padded_rows_and_big_endian():
    f = cv.RosbagsFactory(TS)
    depth = np.arange(12, dtype=np.float32).reshape(3, 4) * 0.1
    step = 4 * 4 + 4
    rows = np.zeros((3, step), dtype=np.uint8)
    rows[:, :16] = depth.astype('>f4').view(np.uint8).reshape(3, 16)
    msg = f.new('sensor_msgs/msg/Image', header=cv.header(f, 0, 'c'), height=3, width=4, encoding='32FC1',
                is_bigendian=1, step=step, data=rows.ravel())
    np.testing.assert_array_equal(cv.image_to_numpy(msg), depth)


def test_image_bad_messages_raise_clear_errors():
    f = rcv.RclpyFactory()
    msg = cv.numpy_to_image(f, np.zeros((4, 5), np.float32), '32FC1', cv.header(f, 0, 'c'))
    bad = copy.copy(msg)
    bad.encoding = 'yuv422'
    with pytest.raises(ValueError, match="unsupported image encoding 'yuv422'"):
        cv.image_to_numpy(bad)
    bad = copy.copy(msg)
    bad.step = 19
    with pytest.raises(ValueError, match='step 19 < width 5'):
        cv.image_to_numpy(bad)
    bad = copy.copy(msg)
    bad.data = array.array('B', bytes(10))
    with pytest.raises(ValueError, match='data has 10 bytes, expected'):
        cv.image_to_numpy(bad)
    with pytest.raises(ValueError, match=r'shape \(H, W, 3\)'):
        cv.numpy_to_image(f, np.zeros((4, 5), np.uint8), 'rgb8', cv.header(f, 0, 'c'))
    with pytest.raises(ValueError, match='uint8'):
        cv.numpy_to_image(f, np.full((4, 5), 300), 'mono8', cv.header(f, 0, 'c'))


def test_camera_info_round_trip(flavour):
    f, wire = flavour
    msg = cv.intrinsics_to_camera_info(f, 570.3, 571.0, 58.5, 41.5, 127, 84, cv.header(f, STAMP, 'cam'))
    for m in (msg, wire(msg, 'sensor_msgs/msg/CameraInfo')):
        assert cv.camera_info_to_intrinsics(m) == (570.3, 571.0, 58.5, 41.5, 127, 84)
        assert len(m.d) == 5 and m.distortion_model == 'plumb_bob'
    bad = wire(msg, 'sensor_msgs/msg/CameraInfo')
    bad.k = np.zeros(9)
    with pytest.raises(ValueError, match='no valid focal length'):
        cv.camera_info_to_intrinsics(bad)


def test_grids_round_trip(flavour):
    f, wire = flavour
    geom = GridGeometry(-0.05, -0.04, 0.001, 7, 5, 0.7, 'cam')
    rng = np.random.default_rng(5)
    occ = rng.choice(np.array([-1, 0, 100], dtype=np.int8), size=geom.shape)
    sdf = rng.normal(size=geom.shape).astype(np.float32)
    occ_msg = cv.numpy_to_occupancy_grid(f, occ, geom, cv.header(f, STAMP, 'cam'))
    sdf_msg = cv.numpy_to_float_grid(f, sdf, geom, cv.header(f, STAMP, 'cam'), unit='m')
    for m in (occ_msg, wire(occ_msg, 'nav_msgs/msg/OccupancyGrid')):
        occ2, g2 = cv.occupancy_grid_to_numpy(m)
        np.testing.assert_array_equal(occ2, occ)
        assert g2 == geom
    for m in (sdf_msg, wire(sdf_msg, 'gpis_grasp_interfaces/msg/FloatGrid')):
        sdf2, g2 = cv.float_grid_to_numpy(m, expect_unit='m')
        np.testing.assert_array_equal(sdf2, sdf)
        assert g2 == geom and m.unit == 'm'
    with pytest.raises(ValueError, match="unit is 'm', expected 'm\\^2'"):
        cv.float_grid_to_numpy(sdf_msg, expect_unit='m^2')
    with pytest.raises(ValueError, match='differs from grid shape'):
        cv.numpy_to_float_grid(f, sdf[:, :3], geom)
    with pytest.raises(ValueError, match=r'\[-1, 100\]'):
        cv.numpy_to_occupancy_grid(f, np.full(geom.shape, 101), geom)


def test_grid_bad_messages_raise_clear_errors():
    f = cv.RosbagsFactory(TS)
    geom = GridGeometry(0.0, 0.0, 0.01, 4, 3, 0.7, 'cam')
    msg = cv.numpy_to_occupancy_grid(f, np.zeros(geom.shape, np.int8), geom)
    msg.data = msg.data[:-1]
    with pytest.raises(ValueError, match='has 11 values, expected width 4 \\* height 3 = 12'):
        cv.occupancy_grid_to_numpy(msg)
    msg = cv.numpy_to_occupancy_grid(f, np.zeros(geom.shape, np.int8), geom)
    msg.info.origin.orientation.w = 0.0
    with pytest.raises(ValueError, match='unit quaternion'):
        cv.occupancy_grid_to_numpy(msg)
    msg.info.origin.orientation.w = float('nan')
    with pytest.raises(ValueError, match='unit quaternion'):
        cv.occupancy_grid_to_numpy(msg)


def test_tilted_grid_pose_round_trips_through_messages(flavour):
    """A grid in a table plane tilted by 50° keeps its full pose through OccupancyGrid and FloatGrid."""
    f, wire = flavour
    a = np.deg2rad(50.0)
    rot = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])
    geom = GridGeometry(-0.05, -0.04, 0.004, 25, 25, 0.9, 'cam', tuple(rot.ravel()))
    occ = np.zeros(geom.shape, np.int8)
    msg = wire(cv.numpy_to_occupancy_grid(f, occ, geom), 'nav_msgs/msg/OccupancyGrid')
    _, g2 = cv.occupancy_grid_to_numpy(msg)
    np.testing.assert_allclose(g2.rotation, geom.rotation, atol=1e-12)
    np.testing.assert_allclose([g2.origin_x, g2.origin_y, g2.z], [geom.origin_x, geom.origin_y, geom.z], atol=1e-12)
    corner = [msg.info.origin.position.x, msg.info.origin.position.y, msg.info.origin.position.z]
    np.testing.assert_allclose(corner, geom.to_sensor(np.array([-0.05, -0.04])), atol=1e-12)


def test_geometry_messages_round_trip(flavour):
    f, wire = flavour
    hdr = cv.header(f, STAMP, 'cam')
    pt = wire(cv.point_stamped(f, [0.01, -0.02, 0.7], hdr), 'geometry_msgs/msg/PointStamped')
    np.testing.assert_allclose(cv.point_stamped_to_numpy(pt), [0.01, -0.02, 0.7])
    xy = np.array([[0.0, 0.0], [0.05, 0.0], [0.05, 0.03]])
    poly = wire(cv.polygon_stamped(f, xy, 0.7, hdr), 'geometry_msgs/msg/PolygonStamped')
    out = cv.polygon_stamped_to_numpy(poly)
    np.testing.assert_allclose(out[:, :2], xy, atol=1e-7)
    np.testing.assert_allclose(out[:, 2], 0.7, atol=1e-6)


def test_rosbags_bytes_are_valid_rclpy_messages():
    """The CDR written to bags deserializes into rclpy messages that convert identically."""
    from rclpy.serialization import deserialize_message

    f = cv.RosbagsFactory(TS)
    xyz, rgb = _cloud(8, 9)
    msg = cv.xyz_rgb_to_pointcloud2(f, xyz, rgb, cv.header(f, STAMP, 'cam'))
    raw = bytes(TS.serialize_cdr(msg, 'sensor_msgs/msg/PointCloud2'))
    rmsg = deserialize_message(raw, rcv.rclpy_message_class('sensor_msgs/msg/PointCloud2'))
    xyz2, rgb2 = cv.pointcloud2_to_xyz_rgb(rmsg)
    np.testing.assert_array_equal(xyz2, xyz)
    np.testing.assert_array_equal(rgb2, rgb)
    geom = GridGeometry(0.0, 0.0, 0.01, 4, 3, 0.7, 'cam')
    grid = cv.numpy_to_float_grid(f, np.arange(12, dtype=np.float32).reshape(3, 4), geom)
    raw = bytes(TS.serialize_cdr(grid, 'gpis_grasp_interfaces/msg/FloatGrid'))
    rgrid = deserialize_message(raw, rcv.rclpy_message_class('gpis_grasp_interfaces/msg/FloatGrid'))
    np.testing.assert_array_equal(cv.float_grid_to_numpy(rgrid)[0], np.arange(12).reshape(3, 4))


def test_rclpy_builders_are_fast():
    """A VGA cloud is built without per-element Python loops (well under a second)."""
    import time

    f = rcv.RclpyFactory()
    xyz = np.zeros((480, 640, 3), np.float32)
    rgb = np.zeros((480, 640, 3), np.uint8)
    t0 = time.perf_counter()
    msg = cv.xyz_rgb_to_pointcloud2(f, xyz, rgb, cv.header(f, 0, 'c'))
    cv.pointcloud2_to_xyz_rgb(msg)
    assert time.perf_counter() - t0 < 0.5
    assert isinstance(msg.data, array.array) and msg.data.typecode == 'B'


def test_unknown_types_raise_value_error():
    with pytest.raises(ValueError, match="'pkg/msg/Type'"):
        rcv.rclpy_message_class('nonsense')
    with pytest.raises(ValueError, match='cannot import'):
        rcv.rclpy_message_class('no_such_pkg/msg/Foo')
    with pytest.raises(ValueError, match='not in the rosbags typestore'):
        cv.RosbagsFactory(TS).new('no_such_pkg/msg/Foo')


# --------------------------------------------------------------------------- GPIS model and grasps
def _posterior():
    from gpis_grasp_ros.core import gpis

    geom = GridGeometry(-0.01, -0.01, 0.0021, 10, 10, 0.7, 'cam')  # not a float32-exact resolution
    centers = geom.cell_centers().reshape(-1, 2)
    sdf = np.linalg.norm(centers, axis=1) - 0.006  # disc of radius 6 mm
    keep = np.arange(len(sdf)) % 3 != 0
    kp = gpis.KernelParams(signal_variance=1e-4, length_scale=0.004, prior_mean=-0.005)
    grad = centers[keep] / np.linalg.norm(centers[keep], axis=1, keepdims=True)  # gradient of the disc SDF
    axis = np.arange(keep.sum()) % 2
    return gpis.posterior_from_data(geom, kp, centers[keep], sdf[keep], np.full(keep.sum(), 1e-6), 1e-10,
                                    train_grad_xy=centers[keep], train_grad_axis=axis,
                                    train_grad=grad[np.arange(keep.sum()), axis],
                                    train_grad_noise=np.full(keep.sum(), 0.01))


@pytest.mark.parametrize('name', sorted(FACTORIES))
def test_gpis_model_round_trip(name):
    make, wire = FACTORIES[name]
    f = make()
    post = _posterior()
    msg = wire(cv.posterior_to_gpis_model(post, cv.header(f, STAMP, 'cam'), f=f, com_samples=50),
               'gpis_grasp_interfaces/msg/GpisModel')
    assert msg.length_scale == 0.004 and len(msg.train_y) == len(post.train_y)
    np.testing.assert_allclose(np.asarray(msg.mean).reshape(10, 10), post.mean)
    np.testing.assert_allclose([msg.center_of_mass.x, msg.center_of_mass.y], post.center_of_mass())
    assert msg.center_of_mass.z == 0.7 and msg.center_of_mass_std >= 0
    assert len(msg.train_grad) == len(post.train_grad) > 0 and len(msg.train_grad_x) == 2 * len(post.train_grad)
    back = cv.gpis_model_to_posterior(msg)
    assert back.geometry == post.geometry and back.geometry.resolution == 0.0021
    for field in ('train_grad_xy', 'train_grad_axis', 'train_grad', 'train_grad_noise'):
        np.testing.assert_array_equal(getattr(back, field), getattr(post, field))
    np.testing.assert_allclose(back.mean, post.mean, atol=1e-12)
    np.testing.assert_allclose(back.variance, post.variance, atol=1e-14)
    np.testing.assert_allclose(back.gradient, post.gradient, atol=1e-10)
    bad = copy.copy(msg)
    bad.train_noise_variance = np.zeros(3) if name == 'rosbags' else array.array('d', [0.0] * 3)
    with pytest.raises(ValueError, match='training arrays disagree'):
        cv.gpis_model_to_posterior(bad)
    bad = copy.copy(msg)
    bad.train_grad_noise_variance = np.zeros(3) if name == 'rosbags' else array.array('d', [0.0] * 3)
    with pytest.raises(ValueError, match='gradient arrays disagree'):
        cv.gpis_model_to_posterior(bad)


def test_grasp_plan_response_and_markers():
    from types import SimpleNamespace

    from gpis_grasp_interfaces.srv import GraspPlan

    f = rcv.RclpyFactory()
    hdr = cv.header(f, STAMP, 'cam')
    result = SimpleNamespace(method='gp-gpis-opt', success=True, message='ok', jaw1=np.array([0.0, 0.0]),
                             jaw2=np.array([0.0, 0.03]), center=np.array([0.0, 0.015]), axis=np.array([0.0, 1.0]),
                             width=0.03, q_mean=0.2, p_f=0.8, p_f_std_error=0.01, objective=0.7,
                             planning_time=0.5, iterations=12)
    resp = rcv.fill_grasp_plan_response(GraspPlan.Response(), result, hdr, z=0.7)
    assert resp.success and resp.method == 'gp-gpis-opt' and resp.iterations == 12
    assert resp.jaw2.pose.position.y == pytest.approx(0.03) and resp.grasp_pose.pose.position.z == 0.7
    q = resp.grasp_pose.pose.orientation  # x axis rotated onto +y: 90 degrees about z
    assert (q.z, q.w) == pytest.approx((np.sqrt(0.5), np.sqrt(0.5)))
    assert resp.probability_force_closure == 0.8 and resp.grasp_pose.header.frame_id == 'cam'
    markers = rcv.grasp_markers(result, hdr, GridGeometry(0, 0, 0.001, 10, 10, 0.7, 'cam'), jaw_width=0.02)
    assert [m.action for m in markers.markers] == [3, 0, 0, 0, 0]
    assert markers.markers[1].scale.y == 0.02 and 'P_F = 0.80' in markers.markers[4].text
