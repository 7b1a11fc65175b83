"""Carmine scene simulator, the eight object bags and the make-bag / make-bags commands."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from gpis_grasp_ros.core import noise_model
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.data import bagio
from gpis_grasp_ros.data import messages as cv
from gpis_grasp_ros.data.topics import CAMERA_TOPICS, GROUND_TRUTH_TOPICS, TOPIC_TYPES
from gpis_grasp_ros.sim import objects
from gpis_grasp_ros.sim.scene import (
    FRAME_ID,
    TRANSPARENT_TINT,
    MaterialRegion,
    Scene,
    SceneSpec,
    disparity_quantise,
    load_mask_png,
    load_polygon_csv,
    mask_to_polygon,
    points_in_polygon,
    polygon_centroid,
    polygon_signed_distance,
    rasterise_polygon,
    validate_polygon,
    write_scene_bag,
)
from gpis_grasp_ros.tools import scene_cli

ROOT = Path(__file__).resolve().parents[2]
BAGS = ROOT / 'bags'
SQUARE = np.array([[-0.05, -0.03], [0.06, -0.03], [0.06, 0.03], [-0.05, 0.03]])
TRANSPARENT_BOX = (0.03, -0.04, 0.07, 0.04)  # right end of the object
SPECULAR_BOX = (-0.06, -0.01, -0.03, 0.01)  # left end
H = 0.025


def small_spec(**kw) -> SceneSpec:
    """10 x 6 cm box, 2.5 cm high: transparent right end, specular patch on the left."""
    args = dict(outline=SQUARE, regions=[MaterialRegion.box('transparent', *TRANSPARENT_BOX),
                                         MaterialRegion.box('specular', *SPECULAR_BOX)],
                height=H, frames=3, seed=7)
    args.update(kw)
    return SceneSpec(**args)


def _pixels_of(scene: Scene, x0, y0, x1, y1, depth: float) -> np.ndarray:
    """Mask of pixels whose ray meets the plane z=depth inside the box (shrunk by 3 mm)."""
    xy = scene.window.pixel_rays() * depth
    return (xy[..., 0] > x0 + 0.003) & (xy[..., 0] < x1 - 0.003) & (xy[..., 1] > y0 + 0.003) & \
        (xy[..., 1] < y1 - 0.003)


# =========================================================================== geometry helpers
def test_polygon_helpers():
    poly = validate_polygon(SQUARE[::-1])  # clockwise input → counter-clockwise
    assert poly[0].tolist() in SQUARE.tolist()
    np.testing.assert_allclose(polygon_centroid(poly), [0.005, 0.0], atol=1e-12)
    pts = np.array([[0.0, 0.0], [0.059, 0.029], [0.061, 0.0], [-0.2, 0.0]])
    assert points_in_polygon(pts, poly).tolist() == [True, True, False, False]
    np.testing.assert_allclose(polygon_signed_distance(pts, poly), [-0.03, -0.001, 0.001, 0.15], atol=1e-12)
    geom = GridGeometry(-0.07, -0.05, 0.002, 70, 50)
    raster = rasterise_polygon(poly, geom)
    np.testing.assert_array_equal(raster, points_in_polygon(geom.cell_centers(), poly))
    assert raster.sum() * 0.002 ** 2 == pytest.approx(0.11 * 0.06, rel=0.02)


@pytest.mark.parametrize('points, message', [
    (np.zeros((0, 2)), 'empty'),
    ([[0, 0], [1, 1]], 'degenerate'),
    ([[0, 0], [0.1, 0.1], [0.2, 0.2]], 'on one line'),
    ([[0, 0], [0.1, 0.1], [0.1, 0], [0, 0.1]], 'self-intersecting'),
    ([[0, 0], [0.1, 0], [0.1, 0.1], [0.05, -0.05], [0, 0.1]], 'self-intersecting'),
    ([[0, 0], [0.1, np.nan], [0.1, 0.1]], 'non-finite'),
    ([[0, 0, 0], [1, 0, 0], [1, 1, 0]], r'\(N, 2\)'),
])
def test_bad_polygons_raise(points, message):
    with pytest.raises(ValueError, match=message):
        validate_polygon(points)


def test_polygon_and_mask_files(tmp_path):
    csv = tmp_path / 'p.csv'
    csv.write_text('# outline\nx,y\n0,0\n0.1, 0\n0.1;0.05\n\n0 0.05\n')
    np.testing.assert_allclose(np.abs(load_polygon_csv(csv)).max(), 0.1)
    (tmp_path / 'bad.csv').write_text('0,0\n0.1,zero\n0,1\n')
    with pytest.raises(ValueError, match=r'bad.csv:2: expected'):
        load_polygon_csv(tmp_path / 'bad.csv')
    with pytest.raises(ValueError, match='file not found'):
        load_polygon_csv(tmp_path / 'missing.csv')

    mask = np.zeros((100, 120), np.uint8)
    cv2.rectangle(mask, (20, 30), (99, 69), 255, -1)  # 80 x 40 px
    cv2.imwrite(str(tmp_path / 'm.png'), mask)
    poly = load_mask_png(tmp_path / 'm.png', 0.001)
    area = abs(0.5 * np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1]))
    assert area == pytest.approx(0.079 * 0.039, rel=1e-6)  # outline through boundary pixel centres
    np.testing.assert_allclose(polygon_centroid(poly), [(20 + 99 + 1) / 2 * 0.001 - 0.06, 0.0], atol=1e-9)
    cv2.imwrite(str(tmp_path / 'empty.png'), np.zeros((10, 10), np.uint8))
    with pytest.raises(ValueError, match='no object pixels'):
        load_mask_png(tmp_path / 'empty.png', 0.001)
    with pytest.raises(ValueError, match='file not found'):
        load_mask_png(tmp_path / 'missing.png', 0.001)
    two = np.zeros((50, 50), np.uint8)
    two[5:10, 5:10] = two[30:40, 30:40] = 1
    with pytest.raises(ValueError, match='2 separate objects'):
        mask_to_polygon(two, 0.001)


def test_disparity_quantisation_levels():
    z = np.linspace(0.6, 0.8, 20001)
    q = disparity_quantise(z)
    levels = np.unique(q)
    k = noise_model.QUANTISATION_PER_M  # levels are uniformly spaced in 1 / z
    assert abs(len(levels) - (1 / (k * 0.6) - 1 / (k * 0.8))) <= 2
    steps = np.diff(levels)
    np.testing.assert_allclose(steps, noise_model.quantisation_step(levels[:-1]), rtol=0.01)
    assert np.abs(q - z).max() <= 0.51 * noise_model.quantisation_step(0.8) + 1e-9
    assert np.isnan(disparity_quantise(np.array([np.nan]))).all()


# =========================================================================== the simulator
@pytest.fixture(scope='module')
def scene() -> Scene:
    return Scene(small_spec())


@pytest.fixture(scope='module')
def frames(scene):
    return list(scene.frames())


def test_intrinsics_and_crop(scene):
    fx, fy, cx, cy, w, h = scene.intrinsics
    assert fx == fy == 570.3
    assert cx == pytest.approx(319.5 - scene.window.u0) and cy == pytest.approx(239.5 - scene.window.v0)
    # the object's top face, projected with the cropped intrinsics, lies inside the image
    top = SQUARE / (0.7 - H)
    u, v = cx + fx * top[:, 0], cy + fy * top[:, 1]
    assert (u > 0).all() and (u < w - 1).all() and (v > 0).all() and (v < h - 1).all()
    assert w >= 80


def test_depth_materials(scene, frames):
    """Transparent: table depth; specular: no return; opaque: object top; noise ~ axial model."""
    depth = np.stack([f.depth for f in frames])
    zt, zo = 0.7, 0.7 - H
    transparent = _pixels_of(scene, *TRANSPARENT_BOX[:2], 0.06, 0.03, zo)
    specular = _pixels_of(scene, -0.05, -0.01, -0.03, 0.01, zo)
    opaque = _pixels_of(scene, -0.02, -0.02, 0.02, 0.02, zo)
    table = _pixels_of(scene, -0.08, 0.035, 0.08, 0.05, zt)
    assert transparent.sum() > 100 and specular.sum() > 50 and opaque.sum() > 500 and table.sum() > 100
    t_vals = depth[:, transparent]
    assert np.isfinite(t_vals).mean() > 0.9
    assert np.nanmean(t_vals) == pytest.approx(zt, abs=5e-4)
    assert np.isnan(depth[:, specular]).all()
    o_vals = depth[:, opaque]
    assert np.nanmean(o_vals) == pytest.approx(zo, abs=5e-4)
    assert np.nanstd(o_vals) == pytest.approx(noise_model.axial_sigma(zo), rel=0.25)
    assert np.nanmean(depth[:, table]) == pytest.approx(zt, abs=5e-4)
    finite = depth[np.isfinite(depth)]
    assert np.isin(finite, disparity_quantise(finite).astype(np.float32)).all()


def test_point_cloud_geometry(scene, frames):
    f = frames[0]
    ok = np.isfinite(f.depth)
    np.testing.assert_array_equal(np.isfinite(f.xyz).all(axis=-1), ok)
    np.testing.assert_allclose(f.xyz[..., 2][ok], f.depth[ok])
    # points on the object top (depth well above the table) project inside the outline
    top = ok & (f.depth < 0.7 - H / 2)
    assert points_in_polygon(f.xyz[top][:, :2].astype(np.float64), validate_polygon(SQUARE)).mean() > 0.97


def test_colour_sees_table_through_transparent(scene, frames):
    rgb = np.mean([f.rgb.astype(float) for f in frames], axis=0)
    zo = 0.7 - H
    transparent = _pixels_of(scene, *TRANSPARENT_BOX[:2], 0.06, 0.03, zo)
    opaque = _pixels_of(scene, -0.02, -0.02, 0.02, 0.02, zo)
    table, obj = np.array(scene.table_color), np.array(scene.object_color)
    assert np.abs(rgb[opaque].mean(axis=0) - obj).max() < 8
    tint = rgb[transparent].mean(axis=0)
    # the table seen through the part, blended with TRANSPARENT_TINT of the part's colour
    expected = (1 - TRANSPARENT_TINT) * table + TRANSPARENT_TINT * obj
    assert np.abs(tint - expected).max() < 6
    assert np.abs(tint - table).max() < 0.5 * np.abs(obj - table).max()  # still mostly the table


def test_projector_shadow_on_the_far_side(scene, frames):
    """The projector sits at +x, so the table just left of the object (-x) gets no depth.

    Table points x in (-0.0546, -0.0519) m are both visible past the top edge (-0.05 * 0.7 / 0.675)
    and hidden from the projector (0.075 m baseline) by the 2.5 cm high object."""
    zt = 0.7
    xy = scene.window.pixel_rays() * zt
    left = (xy[..., 0] > -0.0543) & (xy[..., 0] < -0.0522) & (np.abs(xy[..., 1]) < 0.02)
    right = (xy[..., 0] > 0.06 + 0.003) & (xy[..., 0] < 0.06 + 0.006) & (np.abs(xy[..., 1]) < 0.02)
    assert np.isnan(scene.static.clean_depth[left]).mean() > 0.9
    assert np.isfinite(scene.static.clean_depth[right]).all()


def test_ground_truth(scene):
    gt = scene.ground_truth()
    g = gt.geometry
    assert g.resolution == 0.001 and g.z == 0.7 and g.frame_id == FRAME_ID
    assert (gt.occupancy == 100).sum() * 1e-6 == pytest.approx(0.11 * 0.06, rel=0.01)
    assert set(np.unique(gt.occupancy)) == {0, 100}
    np.testing.assert_array_equal(gt.sdf < 0, gt.occupancy == 100)
    assert gt.sdf.min() == pytest.approx(-0.03, abs=1e-3)
    np.testing.assert_allclose(gt.center_of_mass, [0.005, 0.0, 0.7], atol=1e-12)


def test_frames_are_deterministic(scene, frames):
    again = list(Scene(small_spec()).frames())
    repeat = list(scene.frames())
    other = next(Scene(small_spec(seed=8)).frames())
    for a, b, c in zip(frames, again, repeat, strict=True):
        assert a.stamp_ns == b.stamp_ns
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.depth, c.depth)
        np.testing.assert_array_equal(a.rgb, b.rgb)
    assert not np.array_equal(frames[0].rgb, other.rgb)
    assert set(np.diff([f.stamp_ns for f in frames]).tolist()) <= {33_333_333, 33_333_334}  # 1/30 s


@pytest.mark.parametrize('kw, message', [
    (dict(height=0.0), 'height must be positive'),
    (dict(camera_height=0.3), 'camera height'),
    (dict(height=0.4), 'minimum range'),
    (dict(frames=0), 'frames'),
    (dict(object_color=(0, 0, 300)), 'object colour'),
    (dict(outline=SQUARE + 0.5, regions=[]), 'outside the camera field of view'),
    (dict(regions=[MaterialRegion.box('glass', 0, 0, 0.01, 0.01)]), "unknown material kind 'glass'"),
    (dict(regions=[MaterialRegion.box('specular', 0.2, 0.2, 0.3, 0.3)]), 'does not overlap'),
    (dict(outline=np.zeros((0, 2))), 'object outline is empty'),
])
def test_bad_specs_raise(kw, message):
    with pytest.raises(ValueError, match=message):
        Scene(small_spec(**kw))


# =========================================================================== bags
@pytest.fixture(scope='module')
def bag(tmp_path_factory) -> Path:
    return write_scene_bag(small_spec(), tmp_path_factory.mktemp('bag') / 'small.mcap')


def test_bag_round_trip(bag, scene):
    info = bagio.bag_topics(bag)
    assert set(info) == set(GROUND_TRUTH_TOPICS + CAMERA_TOPICS)  # no distractor: no /ground_truth/obstacles
    for topic in info:
        assert info[topic]['type'] == TOPIC_TYPES[topic]
        assert info[topic]['count'] == (1 if topic in GROUND_TRUTH_TOPICS else 3)
    msgs = list(bagio.read_messages(bag))
    t0 = small_spec().start_ns
    assert all(t == t0 for topic, _, t, _ in msgs if topic in GROUND_TRUTH_TOPICS)
    for topic in CAMERA_TOPICS:
        stamps = [(t, cv.stamp_to_ns(m.header)) for tp, _, t, m in msgs if tp == topic]
        assert [a for a, _ in stamps] == [b for _, b in stamps]
        assert [a - t0 for a, _ in stamps] == [33_333_333, 66_666_667, 100_000_000]
        assert all(m.header.frame_id == FRAME_ID for tp, _, _, m in msgs if tp == topic)

    depth = np.stack([cv.image_to_numpy(m) for tp, _, _, m in msgs if tp == '/camera/depth/image_raw'])
    zo = 0.7 - H
    transparent = _pixels_of(scene, *TRANSPARENT_BOX[:2], 0.06, 0.03, zo)
    specular = _pixels_of(scene, -0.05, -0.01, -0.03, 0.01, zo)
    assert np.nanmean(depth[:, transparent]) == pytest.approx(0.7, abs=5e-4)
    assert np.isnan(depth[:, specular]).all()
    cloud = next(m for tp, _, _, m in msgs if tp == '/camera/depth/points')
    xyz, rgb = cv.pointcloud2_to_xyz_rgb(cloud)
    np.testing.assert_array_equal(xyz[..., 2], depth[0])
    image = next(m for tp, _, _, m in msgs if tp == '/camera/rgb/image_raw')
    np.testing.assert_array_equal(cv.image_to_numpy(image), rgb)
    info_msg = next(m for tp, _, _, m in msgs if tp == '/camera/depth/camera_info')
    assert cv.camera_info_to_intrinsics(info_msg) == scene.intrinsics

    occ, geom = cv.occupancy_grid_to_numpy(next(m for tp, _, _, m in msgs if tp == '/ground_truth/occupancy'))
    sdf, geom2 = cv.float_grid_to_numpy(next(m for tp, _, _, m in msgs if tp == '/ground_truth/sdf'), 'm')
    gt = scene.ground_truth()
    assert geom == geom2 == gt.geometry
    np.testing.assert_array_equal(occ, gt.occupancy)
    np.testing.assert_array_equal(sdf, gt.sdf)
    com = cv.point_stamped_to_numpy(next(m for tp, _, _, m in msgs if tp == '/ground_truth/center_of_mass'))
    np.testing.assert_allclose(com, gt.center_of_mass)
    outline = cv.polygon_stamped_to_numpy(next(m for tp, _, _, m in msgs if tp == '/ground_truth/outline'))
    np.testing.assert_allclose(outline[:, :2], gt.outline, atol=1e-7)


def test_bag_bytes_are_deterministic(bag, tmp_path):
    again = write_scene_bag(small_spec(), tmp_path / bag.name)
    assert again.read_bytes() == bag.read_bytes()


def test_bad_input_leaves_no_bag(tmp_path):
    out = tmp_path / 'x.mcap'
    with pytest.raises(ValueError, match='self-intersecting'):
        write_scene_bag(small_spec(outline=[[0, 0], [0.05, 0.05], [0.05, 0], [0, 0.05]]), out)
    assert list(tmp_path.iterdir()) == []


def test_failure_while_writing_leaves_no_bag(tmp_path, monkeypatch):
    def broken_frames(self):
        yield from []
        raise RuntimeError('sensor unplugged')

    monkeypatch.setattr(Scene, 'frames', broken_frames)
    with pytest.raises(RuntimeError, match='sensor unplugged'):
        write_scene_bag(small_spec(), tmp_path / 'x.mcap')
    assert list(tmp_path.iterdir()) == []


# =========================================================================== make-bag CLI
def test_ground_truth_obstacles_are_the_distractors(tmp_path):
    """A distractor 2 cm beside the target is the truth's obstacle: its exact signed distance on the truth grid
    (the analytic box distance at every cell centre), none without distractors; a bag carries it as
    /ground_truth/obstacles and load_bag gives it back."""
    from gpis_grasp_ros.data.bags import load_bag
    from gpis_grasp_ros.sim.scene import Distractor

    spec = small_spec(distractors=[Distractor.box(0.09, 0.0, 0.02, 0.04, 0.03)])  # x in [0.08, 0.10], y +-0.02
    assert spec.top_down
    gt = Scene(spec).ground_truth()
    assert Scene(small_spec()).ground_truth().obstacles is None
    q = np.abs(gt.geometry.cell_centers() - [0.09, 0.0]) - [0.01, 0.02]
    box = np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)
    np.testing.assert_allclose(gt.obstacles, box, atol=1e-6)
    assert gt.obstacles.min() < -0.009 and (gt.obstacles[gt.sdf < 0] > 0.019).all()
    bag = write_scene_bag(spec, tmp_path / 'distractor.mcap')
    loaded = load_bag(bag, frames=1)
    np.testing.assert_array_equal(loaded.true_obstacles, gt.obstacles.astype(np.float64))


def test_make_bag_cli(tmp_path, capsys):
    poly = tmp_path / 'square.csv'
    poly.write_text('\n'.join(f'{x},{y}' for x, y in SQUARE))
    out = tmp_path / 'cli.mcap'
    rc = scene_cli.main(['--polygon', str(poly), '--height', str(H), '--frames', '3', '--seed', '7',
                         '--region', 'transparent:' + ','.join(map(str, TRANSPARENT_BOX)),
                         '--region', 'specular:' + ','.join(map(str, SPECULAR_BOX)),
                         '--table-color', '186,176,160', '--object-color', '70,90,150', '--out', str(out)])
    assert rc == 0 and out.is_file()
    assert bagio.bag_topics(out)['/camera/depth/image_raw']['count'] == 3
    # same scene through the CLI and the API: same depth data
    cli_depth = [cv.image_to_numpy(m) for _, _, _, m in bagio.read_messages(out, ['/camera/depth/image_raw'])]
    api_depth = [f.depth for f in Scene(small_spec(outline=load_polygon_csv(poly))).frames()]
    for a, b in zip(cli_depth, api_depth, strict=True):
        np.testing.assert_array_equal(a, b)
    assert 'wrote' in capsys.readouterr().out


def _bad_inputs(tmp: Path) -> list[tuple[list[str], str]]:
    (tmp / 'bow.csv').write_text('0,0\n0.05,0.05\n0.05,0\n0,0.05\n')
    (tmp / 'empty.csv').write_text('# nothing\n')
    (tmp / 'ok.csv').write_text('0,0\n0.05,0\n0.05,0.03\n')
    cv2.imwrite(str(tmp / 'black.png'), np.zeros((20, 20), np.uint8))
    return [
        (['--polygon', str(tmp / 'bow.csv')], 'self-intersecting'),
        (['--polygon', str(tmp / 'empty.csv')], 'empty'),
        (['--polygon', str(tmp / 'missing.csv')], 'file not found'),
        (['--mask', str(tmp / 'black.png'), '--mpp', '0.001'], 'no object pixels'),
        (['--mask', str(tmp / 'missing.png'), '--mpp', '0.001'], 'file not found'),
        (['--mask', str(tmp / 'black.png')], 'needs --mpp'),
        (['--polygon', str(tmp / 'ok.csv'), '--region', 'glass:0,0,1,1'], "unknown material 'glass'"),
        (['--polygon', str(tmp / 'ok.csv'), '--region', 'specular:0,0,1'], 'expected 4'),
        (['--polygon', str(tmp / 'ok.csv'), '--table-color', '1,2'], 'expected 3'),
        (['--polygon', str(tmp / 'ok.csv'), '--object-color', '1,2,256'], 'R,G,B integers'),
        (['--polygon', str(tmp / 'ok.csv'), '--height', '-1'], 'height'),
        (['--polygon', str(tmp / 'ok.csv'), '--frames', 'many'], 'invalid int'),
        (['--polygon', str(tmp / 'ok.csv'), '--mask', str(tmp / 'black.png')], 'not allowed with'),
    ]


def test_make_bag_cli_bad_inputs_exit_2_without_output(tmp_path, capsys):
    out = tmp_path / 'out' / 'x.mcap'
    for argv, message in _bad_inputs(tmp_path):
        rc = scene_cli.main(argv + ['--out', str(out)])
        err = capsys.readouterr().err
        assert rc == 2, argv
        assert message in err, (argv, err)
        assert not out.exists()
        assert not out.parent.exists() or list(out.parent.iterdir()) == []


def test_gpis_grasp_dispatches_make_bag(tmp_path, capsys):
    from gpis_grasp_ros.tools import cli

    assert cli.main(['make-bag', '--polygon', str(tmp_path / 'missing.csv'), '--out', str(tmp_path / 'x.mcap')]) == 2
    assert 'file not found' in capsys.readouterr().err


# =========================================================================== the eight objects
@pytest.mark.parametrize('letter', sorted(objects.OBJECTS))
def test_object_definitions(letter):
    obj = objects.OBJECTS[letter]
    spec = obj.build()
    s = Scene(spec)
    span_px = np.ptp(s.outline, axis=0).max() / spec.camera_height * spec.camera.fx
    assert span_px >= 79.5, f'{letter} spans only {span_px:.0f} px'
    assert 0.004 <= spec.height <= 0.08 and spec.frames == 10
    assert 0.04 <= np.ptp(s.outline, axis=0).max() <= 0.25  # plausible sizes (m)
    kinds = {r.kind for r in spec.regions}
    assert kinds & {'transparent', 'specular'}, 'every paper object has unsensed parts'


def test_shipped_bags_exist_and_are_small():
    sizes = {}
    for obj in objects.OBJECTS.values():
        path = BAGS / obj.filename
        assert path.is_file(), f'{path} missing: run gpis-grasp make-bags'
        sizes[obj.letter] = path.stat().st_size
        assert (BAGS / 'objects' / f'{obj.letter}_{obj.name}.csv').is_file()
    assert max(sizes.values()) <= 5e6 and sum(sizes.values()) <= 40e6, sizes
    assert (BAGS / 'README.md').is_file()


def test_shipped_bag_is_up_to_date(tmp_path):
    """Regenerating an object gives the shipped messages (bags are deterministic and current).

    Messages are compared rather than file bytes so that another zstd build cannot fail the test;
    byte identity of two runs is checked in test_bag_bytes_are_deterministic."""
    assert objects.main(['--out', str(tmp_path), '--only', 'b']) == 0
    obj = objects.OBJECTS['B']
    fresh = [(r.topic, r.t_ns, r.raw, r.qos) for r in bagio.iter_bag(tmp_path / obj.filename)]
    shipped = [(r.topic, r.t_ns, r.raw, r.qos) for r in bagio.iter_bag(BAGS / obj.filename)]
    assert len(fresh) == len(shipped) == 54
    assert fresh == shipped, 'bags/ is stale: run gpis-grasp make-bags'
    shipped_csv = BAGS / 'objects' / f'{obj.letter}_{obj.name}.csv'
    assert (tmp_path / 'objects' / shipped_csv.name).read_text() == shipped_csv.read_text()
    np.testing.assert_array_equal(load_polygon_csv(shipped_csv), validate_polygon(obj.build().outline))


def test_make_bags_rejects_unknown_objects(tmp_path, capsys):
    assert objects.main(['--out', str(tmp_path), '--only', 'A,Z']) == 2
    assert 'unknown object(s) Z' in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_scene_from_mask():
    mask = np.zeros((120, 200), np.uint8)
    cv2.circle(mask, (100, 60), 50, 1, -1)  # 5 cm disc at 0.5 mm per pixel
    s = Scene(SceneSpec.from_mask(mask, 0.0005, height=0.02, frames=1))
    gt = s.ground_truth()
    assert (gt.occupancy == 100).sum() * 1e-6 == pytest.approx(np.pi * 0.025 ** 2, rel=0.03)
    np.testing.assert_allclose(gt.center_of_mass[:2], [0.0, 0.0], atol=3e-4)
    assert np.isfinite(next(s.frames()).depth).mean() > 0.8
