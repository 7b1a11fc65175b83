"""Simulator beyond top-down: tilted camera pose, cast shadows, distractors, the
RealSense D400 sensor model, and the shipped head-camera bags."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from gpis_grasp_ros.core import noise_model
from gpis_grasp_ros.core.sdf_bank import bilinear
from gpis_grasp_ros.data import bagio
from gpis_grasp_ros.data import messages as cv
from gpis_grasp_ros.sim import objects
from gpis_grasp_ros.sim.scene import (
    L_OPAQUE,
    Distractor,
    MaterialRegion,
    Scene,
    SceneSpec,
    polygon_centroid,
    polygon_signed_distance,
    shadow_shift,
    validate_polygon,
    write_scene_bag,
)
from gpis_grasp_ros.tools import scene_cli

ROOT = Path(__file__).resolve().parents[2]
BAGS = ROOT / 'bags'
BOX = np.array([[-0.05, -0.03], [0.05, -0.03], [0.05, 0.03], [-0.05, 0.03]])  # 10 x 6 cm
H = 0.025
TILT, AZIMUTH, DISTANCE = 50.0, 20.0, 0.9
CAN = Distractor.cylinder(0.10, 0.0, 0.02, 0.04, (200, 190, 60))
CUBE = Distractor.box(-0.09, 0.02, 0.02, 0.02, 0.012, yaw_deg=30.0, color=(50, 80, 160))


def tilted_spec(**kw) -> SceneSpec:
    args = dict(outline=BOX, height=H, frames=3, seed=11, camera_height=DISTANCE, camera_tilt=TILT,
                camera_azimuth=AZIMUTH, distractors=[CAN, CUBE])
    args.update(kw)
    return SceneSpec(**args)


@pytest.fixture(scope='module')
def tilted() -> Scene:
    return Scene(tilted_spec())


def _camera_points(scene: Scene) -> np.ndarray:
    depth = scene.static.clean_depth[..., None]
    return np.concatenate([scene.static.rays * depth, depth], axis=-1)


def test_tilted_ground_truth_pose(tilted):
    """The truth grid lies in the table plane seen at 50 degrees: normal (0, -sin t, -cos t) in the camera frame
    (azimuth turns about the normal), plane at distance cos(t) * d, and the centre of mass on it."""
    g = tilted.ground_truth().geometry
    t = np.radians(TILT)
    np.testing.assert_allclose(g.table_normal, [0.0, -np.sin(t), -np.cos(t)], atol=1e-12)
    assert g.z == pytest.approx(DISTANCE * np.cos(t), abs=1e-12)
    # the look-at point T(0, 0) is on the optical axis at the given distance
    np.testing.assert_allclose(tilted.pose.table_to_camera(np.zeros(2)), [0.0, 0.0, DISTANCE], atol=1e-12)
    com = tilted.ground_truth().center_of_mass
    xy, h = g.from_sensor(com)
    assert h == pytest.approx(0.0, abs=1e-12)
    centroid = polygon_centroid(validate_polygon(BOX))
    np.testing.assert_allclose(g.from_sensor(tilted.pose.table_to_camera(centroid))[0], xy)


def test_tilted_depth_lies_on_the_true_shape(tilted):
    """Every rendered (noise-free) point: table points on the plane; target points inside its prism (<= 0.5 mm
    raster), their top-face points exactly at the object height; distractor tops exactly at theirs."""
    gt = tilted.ground_truth()
    g = gt.geometry
    pts = _camera_points(tilted)
    ok = np.isfinite(tilted.static.clean_depth)
    xy, h = g.from_sensor(pts[ok])
    obj = tilted.static.object[ok]
    assert (obj == 0).sum() > 1000 and (obj == 1).sum() > 500 and (obj == 2).sum() > 100 and (obj == 3).sum() > 20
    np.testing.assert_allclose(h[obj == 0], 0.0, atol=1e-9)
    assert (h[obj == 1] > -1e-9).all() and (h[obj == 1] < H + 1e-9).all()
    top = np.abs(h[obj == 1] - H) < 1e-9
    assert top.mean() > 0.5  # the top face is most of what the head camera sees of a flat box
    sdf = bilinear(gt.sdf.astype(np.float64), g, xy[obj == 1])
    assert sdf.max() < 5e-4
    # distractor tops sit exactly at their heights (the tracer snaps hits to lower top faces)
    for index, d in ((2, CAN), (3, CUBE)):
        hd = h[obj == index]
        assert (hd < d.height + 1e-9).all() and np.isclose(hd, d.height, atol=1e-9).mean() > 0.3
        dist = polygon_signed_distance(xy[obj == index] + tilted.pose.c[:2], validate_polygon(d.outline))
        assert dist.max() < 5e-4 and (dist < 0).mean() > 0.8
    # an independent plane fit to the table points gives the same normal
    table = pts[ok][obj == 0]
    centred = table - table.mean(axis=0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][-1]
    assert abs(abs(normal @ g.table_normal) - 1.0) < 1e-9


def test_distractors_do_not_change_the_target_truth(tilted):
    alone = Scene(tilted_spec(distractors=[], frames=1)).ground_truth()
    crowded = tilted.ground_truth()
    assert alone.geometry == crowded.geometry
    np.testing.assert_array_equal(alone.sdf, crowded.sdf)


def test_cast_shadow_is_darker_with_the_same_chromaticity():
    """A light at elevation 45 degrees from -x: the box's shadow is a band of length H beyond its +x side;
    the table there keeps its hue at (1 - strength) of its brightness; depth is unaffected."""
    spec = dict(outline=BOX, height=H, frames=2, seed=3, distractors=[], table_color=(180, 160, 120))
    lit = Scene(SceneSpec(**spec, light=(180.0, 45.0), shadow_strength=0.4))
    dark = Scene(SceneSpec(**spec, light=(180.0, 45.0), shadow_strength=0.0))  # same crop, no darkening
    np.testing.assert_array_equal(lit.static.clean_depth, dark.static.clean_depth)
    assert Scene(SceneSpec(**spec)).shadow_fraction.max() == 0.0
    xy = lit.pose.table_points(lit.window.pixel_rays())
    band = (xy[..., 0] > 0.05 + 0.004) & (xy[..., 0] < 0.05 + H - 0.002) & (np.abs(xy[..., 1]) < 0.025)
    band &= lit.static.object == 0
    free = (xy[..., 0] > 0.05 + H + 0.003) & (np.abs(xy[..., 1]) < 0.025) & (lit.static.object == 0)
    assert band.sum() > 50 and free.sum() > 10
    assert (lit.shadow_fraction[band] == 1.0).all() and (lit.shadow_fraction[free] == 0.0).all()
    ratio = lit.static.colour[band].mean(axis=0) / dark.static.colour[band].mean(axis=0)
    np.testing.assert_allclose(ratio, 0.6, atol=1e-9)  # same factor on R, G, B: same chromaticity
    np.testing.assert_array_equal(lit.static.colour[free], dark.static.colour[free])


def test_transparent_parts_cast_no_shadow():
    clear = [MaterialRegion.box('transparent', -0.06, -0.04, 0.06, 0.04)]
    s = Scene(SceneSpec(outline=BOX, height=H, frames=1, regions=clear, light=(180.0, 45.0)))
    assert s.shadow_fraction.max() == 0.0


def test_realsense_noise_and_quantisation():
    s = Scene(tilted_spec(sensor='realsense_d400', frames=12, distractors=[]))
    assert s.intrinsics[0] == 615.0 and s.camera.projector_baseline == 0.05
    depth = np.stack([f.depth for f in s.frames()]).astype(np.float64)
    finite = depth[np.isfinite(depth)]
    np.testing.assert_allclose(finite, np.round(finite * 1000) / 1000, atol=1e-6)  # 1 mm depth units
    table = (s.static.object == 0) & ~s.static.edge & np.isfinite(s.static.clean_depth)
    z = s.static.clean_depth[table]
    std = np.nanstd(depth[:, table], axis=0, ddof=1)
    model = noise_model.SensorModel.named('realsense_d400').sigma(z)
    ratio = np.sqrt(np.mean(std ** 2) / np.mean(model ** 2 + 1e-6 / 12))
    assert ratio == pytest.approx(1.0, abs=0.08)
    carmine = Scene(tilted_spec(frames=12, distractors=[]))
    c_table = (carmine.static.object == 0) & ~carmine.static.edge & np.isfinite(carmine.static.clean_depth)
    c_std = np.nanstd(np.stack([f.depth for f in carmine.frames()]).astype(np.float64)[:, c_table], axis=0, ddof=1)
    assert np.mean(std) > 1.5 * np.mean(c_std)  # the D400 is noisier at 0.9 m


@pytest.mark.parametrize('kw, message', [
    (dict(camera_tilt=85.0), 'camera tilt'),
    (dict(camera_tilt=float('nan')), 'camera tilt'),
    (dict(light=(0.0, 0.0)), 'light must be'),
    (dict(shadow_strength=1.0), 'shadow strength'),
    (dict(sensor='kinect2'), "unknown sensor 'kinect2'"),
    (dict(distractors=[Distractor.box(0.0, 0.0, 0.02, 0.02, 0.02)]), 'distractor 0 overlaps'),
    (dict(distractors=[Distractor.box(0.2, 0.0, 0.02, 0.02, -0.02)]), 'distractor 0 height'),
    (dict(distractors=[Distractor.box(0.2, 0.0, 0.02, 0.02, 0.02, kind='glass')]), "unknown material kind"),
    (dict(distractors=[Distractor.box(1.5, 0.0, 0.02, 0.02, 0.02)]), 'outside the camera field of view'),
    (dict(camera_tilt=70.0, camera_height=0.3), 'camera height'),
])
def test_bad_pose_specs_raise(kw, message):
    with pytest.raises(ValueError, match=message):
        Scene(tilted_spec(**kw))


def test_make_bag_cli_head_options(tmp_path):
    poly = tmp_path / 'box.csv'
    poly.write_text('\n'.join(f'{x},{y}' for x, y in BOX))
    out = tmp_path / 'head.mcap'
    rc = scene_cli.main(['--polygon', str(poly), '--height', str(H), '--frames', '2', '--camera-height', '0.9',
                         '--tilt', '50', '--azimuth', '20', '--light', '200,55', '--sensor', 'realsense_d400',
                         '--distractor', 'box:0.1,0,0.03,0.03,0.03,10/52,128,74',
                         '--distractor', 'can:-0.1,0,0.02,0.05',
                         '--out', str(out)])
    assert rc == 0
    meta = bagio.bag_topics(out)
    assert meta['/camera/depth/image_raw']['count'] == 2
    _, geom = cv.float_grid_to_numpy(next(m for tp, _, _, m in bagio.read_messages(out, ['/ground_truth/sdf'])))
    np.testing.assert_allclose(geom.table_normal, [0.0, -np.sin(np.radians(50)), -np.cos(np.radians(50))], atol=1e-6)
    assert scene_cli.main(['--polygon', str(poly), '--tilt', '50', '--distractor', 'sphere:0,0,1',
                           '--out', str(tmp_path / 'bad.mcap')]) == 2
    assert not (tmp_path / 'bad.mcap').exists()


# =========================================================================== shipped head-camera bags
def test_head_views_are_pr2_like():
    for letter in objects.HEAD_VIEWS:
        spec = objects.head_spec(letter)
        assert 45.0 <= spec.camera_tilt <= 55.0 and 0.8 <= spec.camera_height <= 1.0
        assert spec.light is not None and len(spec.distractors) >= 1
        area = _area(spec.outline)
        assert all(_area(d.outline) <= 0.5 * area for d in spec.distractors), letter
        shift = shadow_shift(spec.light)  # the light's shadow reaches beyond the object
        assert 0.4 < float(np.linalg.norm(shift)) < 1.0, letter


def _area(poly: np.ndarray) -> float:
    x, y = np.asarray(poly, dtype=np.float64).T
    return 0.5 * abs(float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)))


def test_shipped_head_bags_exist_and_all_bags_fit_40_mb():
    sizes = {}
    for obj in objects.OBJECTS.values():
        path = BAGS / objects.HEAD_DIR / obj.filename
        assert path.is_file(), f'{path} missing: run gpis-grasp make-bags --head'
        sizes[obj.letter] = path.stat().st_size
    total = sum(p.stat().st_size for p in BAGS.rglob('*') if p.is_file())
    assert max(sizes.values()) <= 5e6 and total <= 40e6, (sizes, total)


def test_shipped_head_bag_is_up_to_date(tmp_path):
    """Regenerating head bag B gives the shipped messages (deterministic and current)."""
    assert objects.main(['--out', str(tmp_path), '--only', 'b', '--head']) == 0
    name = objects.OBJECTS['B'].filename
    paths = (tmp_path / objects.HEAD_DIR / name, BAGS / objects.HEAD_DIR / name)
    com_topic = '/ground_truth/center_of_mass'
    fresh, shipped = ([(r.topic, r.t_ns, r.raw if r.topic != com_topic else b'', r.qos) for r in bagio.iter_bag(p)]
                      for p in paths)
    assert len(fresh) == len(shipped) == 55  # 4 ground-truth topics, the distractors as obstacles, 10 x 5 camera
    assert fresh == shipped, 'bags/head is stale: run gpis-grasp make-bags --head'
    # the centre of mass is a sum over the outline: its last bits follow the machine's summation order (SIMD)
    com = [[(m.header.frame_id, (m.point.x, m.point.y, m.point.z)) for *_, m in bagio.read_messages(p, [com_topic])]
           for p in paths]
    assert [f for f, _ in com[0]] == [f for f, _ in com[1]]
    np.testing.assert_allclose([x for _, x in com[0]], [x for _, x in com[1]], rtol=1e-12, atol=0)


def test_head_bag_round_trip(tmp_path):
    spec = dataclasses.replace(objects.head_spec('E'), frames=2)
    path = write_scene_bag(spec, tmp_path / 'e.mcap')
    msgs = {tp: m for tp, _, _, m in bagio.read_messages(path)}
    scene = Scene(spec)
    gt = scene.ground_truth()
    _, geom = cv.float_grid_to_numpy(msgs['/ground_truth/sdf'])
    assert np.allclose(geom.rotation, gt.geometry.rotation, atol=1e-6) and geom.z == pytest.approx(gt.geometry.z)
    outline = cv.polygon_stamped_to_numpy(msgs['/ground_truth/outline'])
    _, h = gt.geometry.from_sensor(outline)
    np.testing.assert_allclose(h, 0.0, atol=1e-6)  # float32 vertices on the table plane
    assert np.count_nonzero(scene.static.label[scene.static.object == 1] == L_OPAQUE) > 100  # the switch body is seen
    assert scene.shadow_fraction.sum() > 20 and np.count_nonzero(scene.static.object >= 2) > 50  # shadow, distractor
