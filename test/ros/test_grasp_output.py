"""3D grasp output: jaw poses in the table plane at grasp_height, grasp orientation,
contact points on the mean shape and the opening width, for top-down and tilted grids."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from gpis_grasp_interfaces.srv import GraspPlan
from gpis_grasp_ros.core.grid import GridGeometry, quaternion_to_rotation
from gpis_grasp_ros.data import messages as cv
from gpis_grasp_ros.ros import conversions as rcv

STAMP = 1_432_598_400_123_456_789


def _rx(deg: float) -> np.ndarray:
    t = np.radians(deg)
    return np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])


def _rz(deg: float) -> np.ndarray:
    t = np.radians(deg)
    return np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])


def _geometry(tilt_deg: float, yaw_deg: float = 0.0, z: float = 0.6) -> GridGeometry:
    """A 30 x 30 grid of 4 mm cells in a table plane seen at ``tilt_deg`` (grid axes = columns of R)."""
    r = _rz(yaw_deg) @ _rx(tilt_deg)
    return GridGeometry(-0.04, -0.05, 0.004, 30, 30, z, 'cam', tuple(r.T.ravel()))


def _result(jaw1, jaw2, success=True) -> SimpleNamespace:
    jaw1, jaw2 = np.asarray(jaw1, float), np.asarray(jaw2, float)
    d = jaw2 - jaw1
    return SimpleNamespace(method='gp-gpis-opt', success=success, message='ok', jaw1=jaw1, jaw2=jaw2,
                           center=(jaw1 + jaw2) / 2, axis=d / np.linalg.norm(d), width=float(np.linalg.norm(d)),
                           q_mean=0.2, p_f=0.8, p_f_std_error=0.01, objective=0.7, planning_time=0.5, iterations=3)


def _xyz(msg) -> np.ndarray:
    p = msg.pose.position if hasattr(msg, 'pose') else msg.point
    return np.array([p.x, p.y, p.z])


def _rotation(pose_stamped) -> np.ndarray:
    q = pose_stamped.pose.orientation
    return quaternion_to_rotation(np.array([q.x, q.y, q.z, q.w]))


def _plane(geometry: GridGeometry) -> tuple[np.ndarray, float]:
    """Unit normal (towards the camera) and offset of the table plane n.p = d, from three grid corners
    mapped to the sensor frame (independent of GridGeometry.table_normal)."""
    a, b, c = (geometry.to_sensor(np.array(p), 0.0) for p in ([0.0, 0.0], [0.1, 0.0], [0.0, 0.1]))
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    if n @ -a < 0:  # the camera (origin) is on the positive side
        n = -n
    return n, float(n @ a)


@pytest.mark.parametrize('tilt', [0.0, 13.0, 30.0, 50.0, 60.0])
def test_jaws_lie_on_the_plane_offset_by_grasp_height(tilt):
    rng = np.random.default_rng(int(tilt))
    hdr = cv.header(rcv.RclpyFactory(), STAMP, 'cam')
    for _ in range(25):
        geom = _geometry(tilt, yaw_deg=float(rng.uniform(-180, 180)), z=float(rng.uniform(0.4, 1.2)))
        jaw1, jaw2 = rng.uniform(-0.04, 0.07, size=(2, 2))
        contacts = np.stack([jaw1 + 0.2 * (jaw2 - jaw1), jaw1 + 0.7 * (jaw2 - jaw1)])
        h = float(rng.uniform(0.0, 0.05))
        result = _result(jaw1, jaw2)
        resp = rcv.fill_grasp_plan_response(GraspPlan.Response(), result, hdr, geometry=geom, grasp_height=h,
                                            contacts_xy=contacts)
        n, d = _plane(geom)
        points = {name: _xyz(getattr(resp, name)) for name in ('jaw1', 'jaw2', 'grasp_pose', 'contact1', 'contact2')}
        for name, p in points.items():
            assert n @ p - d == pytest.approx(h, abs=1e-9), name
        np.testing.assert_allclose(points['grasp_pose'], (points['jaw1'] + points['jaw2']) / 2, atol=1e-12)
        closing = (points['jaw2'] - points['jaw1']) / np.linalg.norm(points['jaw2'] - points['jaw1'])
        for pose in (resp.jaw1, resp.jaw2, resp.grasp_pose):
            r = _rotation(pose)
            np.testing.assert_allclose(r[:, 2], -n, atol=1e-9)  # approach: towards the table
            np.testing.assert_allclose(r[:, 0], closing, atol=1e-9)  # closing direction jaw1 -> jaw2
            assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-9)
        assert resp.width == pytest.approx(0.5 * result.width, abs=1e-9)
        assert resp.width == pytest.approx(np.linalg.norm(points['contact2'] - points['contact1']), abs=1e-12)
        assert resp.jaw_separation == pytest.approx(np.linalg.norm(points['jaw2'] - points['jaw1']), abs=1e-12)
        assert resp.grasp_height == h and resp.contact1.header.frame_id == 'cam'
        # back into the grid: the planned (x, y)
        xy, height = geom.from_sensor(points['jaw1'])
        np.testing.assert_allclose(xy, jaw1, atol=1e-12)
        assert height == pytest.approx(h, abs=1e-12)


def test_tilted_jaw_depths_differ_like_the_table():
    """At 50 degrees tilt two jaws 6 cm apart along the tilt direction sit at different depths."""
    geom = _geometry(50.0)
    hdr = cv.header(rcv.RclpyFactory(), STAMP, 'cam')
    resp = rcv.fill_grasp_plan_response(GraspPlan.Response(), _result([0.0, -0.03], [0.0, 0.03]), hdr,
                                        geometry=geom, grasp_height=0.01, contacts_xy=[[0.0, -0.02], [0.0, 0.02]])
    dz = resp.jaw2.pose.position.z - resp.jaw1.pose.position.z  # grid +y runs towards the camera here
    assert dz == pytest.approx(-0.06 * np.sin(np.radians(50.0)), abs=1e-12)
    assert resp.width == pytest.approx(0.04, abs=1e-12) and resp.jaw_separation == pytest.approx(0.06, abs=1e-12)


def test_top_down_keeps_its_meaning():
    """Identity grid: jaws at depth z - grasp_height, yaw-only orientation (x onto the closing direction)."""
    hdr = cv.header(rcv.RclpyFactory(), STAMP, 'cam')
    result = _result([0.0, 0.0], [0.0, 0.03])
    geom = GridGeometry(0, 0, 0.001, 10, 10, 0.7, 'cam')
    resp = rcv.fill_grasp_plan_response(GraspPlan.Response(), result, hdr, geometry=geom, grasp_height=0.01,
                                        contacts_xy=[[0.0, 0.005], [0.0, 0.025]])
    assert resp.jaw2.pose.position.y == pytest.approx(0.03) and resp.grasp_pose.pose.position.z == pytest.approx(0.69)
    q = resp.grasp_pose.pose.orientation  # x axis rotated onto +y: 90 degrees about the optical axis
    assert (q.x, q.y, q.z, q.w) == pytest.approx((0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)))
    assert resp.width == pytest.approx(0.02) and resp.jaw_separation == pytest.approx(0.03)
    # no geometry: the legacy top-down call at depth z, grasp height 0
    legacy = rcv.fill_grasp_plan_response(GraspPlan.Response(), result, hdr, z=0.7)
    assert legacy.grasp_pose.pose.position.z == 0.7 and legacy.grasp_pose.pose.orientation.z == pytest.approx(q.z)


def test_no_contact_on_the_mean_shape_is_reported():
    hdr = cv.header(rcv.RclpyFactory(), STAMP, 'cam')
    resp = rcv.fill_grasp_plan_response(GraspPlan.Response(), _result([0.0, 0.0], [0.03, 0.0]), hdr,
                                        geometry=_geometry(30.0), grasp_height=0.01, contacts_xy=None)
    assert resp.success and np.isnan(resp.width) and 'no contact on the mean shape' in resp.message
    assert resp.jaw_separation == pytest.approx(0.03)
    failed = rcv.fill_grasp_plan_response(GraspPlan.Response(), _result([np.nan, 0.0], [0.03, 0.0], success=False),
                                          hdr, geometry=_geometry(30.0), grasp_height=0.01)
    assert not failed.success and _xyz(failed.jaw1).tolist() == [0.0, 0.0, 0.0]


def test_markers_are_drawn_at_the_jaw_poses():
    geom = _geometry(50.0, yaw_deg=20.0)
    hdr = cv.header(rcv.RclpyFactory(), STAMP, 'cam')
    result = _result([0.0, 0.01], [0.04, 0.02])
    resp = rcv.fill_grasp_plan_response(GraspPlan.Response(), result, hdr, geometry=geom, grasp_height=0.012,
                                        contacts_xy=[[0.01, 0.0125], [0.03, 0.0175]])
    markers = rcv.grasp_markers(result, hdr, geom, jaw_width=0.02, contacts_xy=[[0.01, 0.0125], [0.03, 0.0175]],
                                grasp_height=0.012).markers
    by_id = {m.id: m for m in markers if m.action == 0}
    for mid, jaw in ((1, resp.jaw1), (2, resp.jaw2)):
        np.testing.assert_allclose(_xyz(by_id[mid]), _xyz(jaw), atol=1e-12)
        assert by_id[mid].pose.orientation == jaw.pose.orientation
    arrow = by_id[3].points
    np.testing.assert_allclose([arrow[0].x, arrow[0].y, arrow[0].z], _xyz(resp.jaw1), atol=1e-12)
    np.testing.assert_allclose(_xyz(by_id[5]), _xyz(resp.contact1), atol=1e-12)
    np.testing.assert_allclose(_xyz(by_id[6]), _xyz(resp.contact2), atol=1e-12)


def test_action_result_carries_the_same_fields():
    from gpis_grasp_interfaces.action import PlanGrasp

    hdr = cv.header(rcv.RclpyFactory(), STAMP, 'cam')
    args = dict(geometry=_geometry(45.0), grasp_height=0.015, contacts_xy=[[0.0, 0.01], [0.02, 0.01]])
    result = _result([-0.01, 0.01], [0.03, 0.01])
    srv = rcv.fill_grasp_plan_response(GraspPlan.Response(), result, hdr, **args)
    act = rcv.fill_grasp_plan_response(PlanGrasp.Result(), result, hdr, **args)
    for name in ('jaw1', 'jaw2', 'grasp_pose', 'contact1', 'contact2'):
        np.testing.assert_array_equal(_xyz(getattr(act, name)), _xyz(getattr(srv, name)))
    assert (act.width, act.jaw_separation, act.grasp_height) == (srv.width, srv.jaw_separation, srv.grasp_height)
    assert act.width == pytest.approx(0.02)


def test_automatic_grasp_height():
    assert rcv.grasp_height_for(0.012, 0.05, 0.02) == 0.012  # given
    assert rcv.grasp_height_for(-1.0, 0.066, 0.02) == pytest.approx(0.033)  # half the object
    assert rcv.grasp_height_for(-1.0, 0.005, 0.02) == pytest.approx(0.01)  # flat object: pads just above the table
    assert rcv.grasp_height_for(-1.0, 0.0, 0.02) == pytest.approx(0.01)  # unknown height


def _tilted_box_cloud(tilt: float, height: float, stamp: int):
    """One noisy frame of a 6 x 4 cm box of ``height`` seen at ``tilt`` (analytic renderer), as a PointCloud2."""
    from support.tilted_scene import Box, TiltedScene

    scene = TiltedScene(tilt, distance_m=0.7, width=320, height=240, focal_px=285.0,
                        boxes=[Box(0.0, 0.0, 0.03, 0.02, height)])
    rgb, depth, _ = scene.frames(1, seed=int(tilt))
    xyz = (scene.intrinsics.rays() * depth[0][..., None]).astype(np.float32)
    return cv.xyz_rgb_to_pointcloud2(rcv.RclpyFactory(), xyz, rgb[0], cv.header(rcv.RclpyFactory(), stamp, 'cam'))


def test_measured_object_height_sets_grasp_height_end_to_end():
    """segmentation_node measures a 5 cm box at 45 degrees (object/top), gpis_node carries it in
    GpisModel.object_height, planner_node closes the jaws at half of it; the object_height parameter overrides."""
    from geometry_msgs.msg import PointStamped
    from rclpy.parameter import Parameter

    from gpis_grasp_interfaces.msg import GpisModel
    from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS
    from gpis_grasp_ros.ros.nodes.gpis_node import GpisNode
    from gpis_grasp_ros.ros.nodes.planner_node import PlannerNode
    from support.rosutil import RosHarness, segmentation_graph, wait_for

    ros = RosHarness(threads=4)
    try:
        _, _, status, pub = segmentation_graph(ros, [])
        ros.add(GpisNode(context=ros.context, parameter_overrides=[Parameter('blur_samples', value=50)]))
        planner = ros.add(PlannerNode(context=ros.context, parameter_overrides=[
            Parameter('num_shape_samples', value=200), Parameter('num_initial_grasps', value=3)]))
        client = ros.node('height_client')
        models, tops = [], []
        client.create_subscription(GpisModel, 'gpis/model', models.append, LATCHED_QOS)
        client.create_subscription(PointStamped, 'object/top', tops.append, LATCHED_QOS)
        plan_cli = client.create_client(GraspPlan, 'plan_grasp')
        pub.publish(_tilted_box_cloud(45.0, 0.05, 11))
        assert wait_for(lambda: bool(models) and planner.has_model(), 60.0), status
        model = models[-1]
        assert model.object_height == pytest.approx(0.05, abs=0.004)
        geometry = cv.gpis_model_to_posterior(model).geometry
        assert geometry.from_sensor(_xyz(tops[-1]))[1] == pytest.approx(model.object_height, abs=1e-9)
        plan = ros.call(plan_cli, GraspPlan.Request(method='gp-gpis-opt', seed=1), timeout=120.0)
        assert plan.success, plan.message
        assert plan.grasp_height == pytest.approx(model.object_height / 2, abs=1e-12)
        for msg in (plan.jaw1, plan.jaw2, plan.contact1):
            assert geometry.from_sensor(_xyz(msg))[1] == pytest.approx(plan.grasp_height, abs=1e-9)
        # a positive object_height parameter overrides the measured height
        planner.set_parameters([Parameter('object_height', value=0.03)])
        plan = ros.call(plan_cli, GraspPlan.Request(method='gp-gpis-opt', seed=1), timeout=120.0)
        assert plan.success and plan.grasp_height == pytest.approx(0.015, abs=1e-12)
    finally:
        ros.close()


def test_object_top_after_the_fit_completes_the_model():
    """Topics are not ordered: the grids arrive, gpis_node fits and publishes the model with height 0 (unknown);
    the matching object/top arrives afterwards and the model is published again with its height, from the same
    fit. A top with another stamp changes nothing."""
    from geometry_msgs.msg import PointStamped
    from nav_msgs.msg import OccupancyGrid
    from rclpy.parameter import Parameter

    from gpis_grasp_interfaces.msg import FloatGrid, GpisModel
    from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS
    from gpis_grasp_ros.ros.nodes.gpis_node import GpisNode
    from support.rosutil import RosHarness, wait_for

    f = rcv.RclpyFactory()
    rot = quaternion_to_rotation(np.array([0.3, 0.0, 0.0, 0.954]) / np.linalg.norm([0.3, 0.0, 0.0, 0.954]))
    g = GridGeometry(-0.05, -0.05, 0.004, 25, 25, 0.7, 'cam', tuple(rot.ravel()))
    yy, xx = np.mgrid[0:25, 0:25]
    occ = np.where((np.abs(xx - 12) <= 5) & (np.abs(yy - 12) <= 3), 100, 0).astype(np.int8)
    noise = np.full(occ.shape, 1e-6, np.float32)
    ros = RosHarness(threads=4)
    try:
        ros.add(GpisNode(context=ros.context, parameter_overrides=[Parameter('blur_samples', value=20)]))
        client = ros.node('late_top_client')
        models = []
        client.create_subscription(GpisModel, 'gpis/model', models.append, LATCHED_QOS)
        occ_pub = client.create_publisher(OccupancyGrid, 'object/occupancy', LATCHED_QOS)
        noise_pub = client.create_publisher(FloatGrid, 'object/noise_map', LATCHED_QOS)
        top_pub = client.create_publisher(PointStamped, 'object/top', LATCHED_QOS)
        stamp = 5_000_000_000
        occ_pub.publish(cv.numpy_to_occupancy_grid(f, occ, g, cv.header(f, stamp, 'cam')))
        noise_pub.publish(cv.numpy_to_float_grid(f, noise, g, cv.header(f, stamp, 'cam'), unit='m^2'))
        assert wait_for(lambda: bool(models), 60.0)
        assert models[-1].object_height == 0.0
        centre = g.to_sensor(np.array([0.0, 0.0]), 0.042)

        def top(t_ns: int) -> PointStamped:
            msg = PointStamped(header=cv.header(f, t_ns, 'cam'))
            msg.point.x, msg.point.y, msg.point.z = (float(v) for v in centre)
            return msg

        top_pub.publish(top(stamp + 10**9))  # another frame's top: ignored
        wait_for(lambda: len(models) > 1, 1.0)
        assert len(models) == 1
        top_pub.publish(top(stamp))
        assert wait_for(lambda: len(models) > 1, 10.0)
        late = models[-1]
        assert late.object_height == pytest.approx(0.042, abs=1e-6)
        assert late.header.stamp == models[0].header.stamp and list(late.mean) == list(models[0].mean)
    finally:
        ros.close()
