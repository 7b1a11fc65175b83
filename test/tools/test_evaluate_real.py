"""``gpis-grasp evaluate-real``: the manifest, the in-memory import, and the command end to end on bags/real."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from gpis_grasp_ros.data import rgbd_import as ri  # noqa: E402
from gpis_grasp_ros.data.bags import load_bag  # noqa: E402
from gpis_grasp_ros.tools import import_rgbd  # noqa: E402
from gpis_grasp_ros.tools.evaluate_real import main  # noqa: E402
from gpis_grasp_ros.tools.evaluate_real.manifest import load_manifest  # noqa: E402
from support.tilted_scene import Box, TiltedScene  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
BAGS_MANIFEST = REPO / 'manifests' / 'bags_real.yaml'


def _millimetres(depth_m: np.ndarray) -> np.ndarray:
    return np.where(np.isfinite(depth_m), np.round(depth_m * 1000), 0).astype(np.uint16)


@pytest.fixture(scope='module')
def raw_capture(tmp_path_factory):
    """A synthetic tilted capture of one box as a user has it (PNG colour, 16-bit mm depth, true depth, mask,
    intrinsics YAML) in ``data/``; returns the directory and the box's mean pixel."""
    root = tmp_path_factory.mktemp('raw')
    out = root / 'data'
    out.mkdir()
    scene = TiltedScene(45.0, boxes=[Box(0.0, 0.01, 0.03, 0.02, 0.04)], width=320, height=240, focal_px=300.0)
    depth, rgb, label = scene.render()
    cv2.imwrite(str(out / 'rgb.png'), np.asarray(rgb, dtype=np.uint8)[..., ::-1])
    cv2.imwrite(str(out / 'depth.png'), _millimetres(depth))
    cv2.imwrite(str(out / 'true-depth.png'), _millimetres(depth))
    cv2.imwrite(str(out / 'mask.png'), np.where(label == 1, 255, 0).astype(np.uint8))
    i = scene.intrinsics
    (out / 'cam.yaml').write_text(yaml.safe_dump({'fx': i.fx, 'fy': i.fy, 'cx': i.cx, 'cy': i.cy}))
    v, u = np.nonzero(label == 1)
    return root, (round(float(u.mean()), 1), round(float(v.mean()), 1))


def _raw_item(target: tuple[float, float], **kw) -> dict:
    item = {'name': 'box', 'rgb': 'rgb.png', 'depth': 'depth.png', 'intrinsics': 'cam.yaml', 'gt_mask': 'mask.png',
            'gt_depth': 'true-depth.png', 'target_pixel': target and list(target)}
    item.update(kw)
    return item


def _write(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data))
    return path


def test_manifest_of_raw_files_with_root_and_override(raw_capture, tmp_path):
    root, target = raw_capture
    crop = [40, 30, 300, 220]
    m = _write(root / 'm.yaml', {'root': 'data', 'captures': [_raw_item(target, crop=crop, scale=0.5)]})
    units = load_manifest(m)
    assert [u.id for u in units] == ['box|whole', 'box|crop']
    whole, cropped = units
    assert whole.crop is None and cropped.crop == tuple(crop) and whole.scale == cropped.scale == 0.5
    assert Path(whole.rgb) == (root / 'data' / 'rgb.png').resolve() and whole.target_pixel == target
    assert whole.sensor == 'realsense_d400'
    # --root overrides the manifest's root: a copy elsewhere, the manifest's root pointing nowhere
    other = tmp_path / 'elsewhere'
    other.mkdir()
    for f in (root / 'data').iterdir():
        (other / f.name).write_bytes(f.read_bytes())
    moved = _write(tmp_path / 'm.yaml', {'root': 'missing', 'captures': [_raw_item(target)]})
    with pytest.raises(FileNotFoundError):
        load_manifest(moved)
    assert Path(load_manifest(moved, other)[0].depth) == (other / 'depth.png').resolve()
    # a bag entry, and what a malformed manifest says
    assert load_manifest(BAGS_MANIFEST)[1].variant == 'bag'
    bad = [({'captures': []}, 'non-empty'), ({'captures': [_raw_item(target, colour='x')]}, 'unknown key'),
           ({'captures': [{k: v for k, v in _raw_item(target).items() if k != 'gt_depth'}]}, 'gt_depth'),
           ({'captures': [_raw_item(target, crop=[10, 10, 5, 20])]}, 'u0 < u1'),
           ({'captures': [_raw_item(target, scale=2)]}, 'scale'),
           ({'captures': [_raw_item(target, sensor='kinect')]}, 'sensor'),
           ({'captures': [_raw_item(None)]}, 'target_pixel'),
           ({'captures': [_raw_item(target), _raw_item(target)]}, 'unique')]
    for data, match in bad:
        with pytest.raises(ValueError, match=match):
            load_manifest(_write(root / 'data' / 'bad.yaml', data))


def test_in_memory_import_is_the_scene_of_the_bag(raw_capture, tmp_path):
    """``evaluate-real`` imports a raw capture in memory: the scene is exactly the one its bag gives."""
    root, target = raw_capture
    d = root / 'data'
    crop, scale = (40, 30, 300, 220), 0.5
    bag = tmp_path / 'box.mcap'
    assert import_rgbd.main(['--rgb', str(d / 'rgb.png'), '--depth', str(d / 'depth.png'), '--intrinsics',
                             str(d / 'cam.yaml'), str(bag), '--gt-mask', str(d / 'mask.png'), '--gt-depth',
                             str(d / 'true-depth.png'), '--target-pixel', *map(str, target), '--crop',
                             *map(str, crop), '--scale', str(scale)]) == 0
    imported = ri.import_capture(d / 'rgb.png', d / 'depth.png', d / 'cam.yaml', crop=crop, scale=scale,
                                 gt_mask=d / 'mask.png', gt_depth=d / 'true-depth.png', target_px=target)
    a, b = ri.capture_scene(imported), load_bag(bag, frames=1)
    for name in ('rgb_frames', 'depth_frames', 'true_sdf', 'true_center_of_mass'):
        assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True), name
    assert a.intrinsics == b.intrinsics and a.true_geometry == b.true_geometry
    assert imported.target_px == ri.map_pixel(*target, crop, scale)


def test_raw_manifest_end_to_end_with_kept_bags_and_a_refusal(raw_capture, tmp_path, capsys):
    root, target = raw_capture
    m = _write(root / 'run.yaml', {'root': 'data', 'captures': [
        _raw_item(target, crop=[40, 30, 300, 220]), _raw_item((3.0, 3.0), name='table')]})
    assert main([str(m), '--methods', 'gp-m', '--seeds', '1', '--trials', '3', '--keep-bags',
                 str(tmp_path / 'bags')]) == 0
    captured = capsys.readouterr()
    assert sorted(p.name for p in (tmp_path / 'bags').glob('*.mcap')) == ['box_crop.mcap', 'box_whole.mcap']
    rows = [line for line in captured.out.splitlines() if line.startswith('| box') or line.startswith('| table')]
    assert len(rows) == 3  # box whole and crop, table (no crop given) whole
    assert all('not on the mask' in r for r in rows if r.startswith('| table'))
    assert 'evaluate-real: box [crop] gp-m seed 0:' in captured.err
    assert main([str(m), '--methods', 'no-such-planner']) == 2
    # --only: the units whose id holds the text; none is an error naming the units there are
    assert main([str(m), '--methods', 'gp-m', '--seeds', '1', '--trials', '3', '--only', 'box|crop']) == 0
    captured = capsys.readouterr()
    assert [r.split('|')[1:3] for r in captured.out.splitlines() if r.startswith('| ')][1:] == [[' box ', ' crop ']]
    assert main([str(m), '--only', 'no-such-unit']) == 2
    err = capsys.readouterr().err
    assert 'matches no unit' in err and 'box|whole, box|crop, table|whole' in err


def test_evaluate_real_on_the_shipped_bags(tmp_path, capsys):
    out = tmp_path / 'out'
    assert main([str(BAGS_MANIFEST), '--methods', 'gp-gpis-opt', '--seeds', '1', '--trials', '4', '--oracle',
                 '--out', str(out)]) == 0
    text = capsys.readouterr().out
    assert text.splitlines()[0].startswith('| capture | variant | occ. IoU | mean-shape IoU | gp-gpis-opt closures /4')
    assert 'oracle closures /4' in text and 'mean over 2 units (0 refused)' in text
    result = json.loads((out / 'results.json').read_text())
    assert (out / 'table.md').read_text().startswith('| capture') and (out / 'reliability.png').stat().st_size > 1000
    units = {u['capture']: u for u in result['units']}
    assert set(units) == {'cleargrasp_000000080_bottle', 'cleargrasp_000000123_flower_box'}
    for u in units.values():
        assert u['variant'] == 'bag' and not u['refusal']
        assert 0.0 <= u['occupancy_iou'] <= 1.0 and 0.0 <= u['mean_shape_iou'] <= 1.0
        for f in (u['methods']['gp-gpis-opt'], u['oracle']):
            assert 0.0 <= f['closures'] <= 4 and 0.0 <= f['p_f'] <= 1.0 and 0.0 <= f['gap'] <= 1.0
        assert u['objects_seen'] >= 3 and (math.isinf(u['jaw_clearance_mm']) or u['jaw_clearance_mm'] > 5.0)
    assert units['cleargrasp_000000080_bottle']['occupancy_iou'] > 0.5  # bags/real/README.md: 0.60
    # the bottle's truth has its upright neighbour (47 mm from the target), the flower box's none
    assert 5.0 < units['cleargrasp_000000080_bottle']['true_clearance_mm'] < 200.0
    assert math.isinf(units['cleargrasp_000000123_flower_box']['true_clearance_mm'])
    assert 'true clearance (mm)' in text.splitlines()[0]
    rows = result['rows']
    assert len(rows) == 4 and all(0 <= r['successes'] <= r['trials'] == 4 for r in rows)
    # every execution of a grasp is counted once: closed, or failed by collision, miss or slip
    assert all(r['successes'] + r['collision'] + r['missed'] + r['slipped'] + r['too_wide'] == 4 for r in rows
               if r['status'] == 'ok')
    assert 'gp-gpis-opt collision / missed / slipped' in text.splitlines()[0]
    assert all(u['methods']['gp-gpis-opt']['closures'] + u['methods']['gp-gpis-opt']['collision']
               + u['methods']['gp-gpis-opt']['missed'] + u['methods']['gp-gpis-opt']['slipped'] == 4
               for u in units.values())
    assert sum(b['count'] for s in result['reliability'].values() for b in s) == 4
    # a target pixel off every object is a row with its reason, not a crash
    off = _write(tmp_path / 'off.yaml', {'root': str(REPO), 'captures': [
        {'name': 'nothing', 'bag': 'bags/real/cleargrasp_000000123_flower_box.mcap', 'target_pixel': [2, 2]}]})
    assert main([str(off), '--methods', 'gp-gpis-opt', '--seeds', '1', '--trials', '4', '--out',
                 str(tmp_path / 'off')]) == 0
    unit = json.loads((tmp_path / 'off' / 'results.json').read_text())['units'][0]
    assert unit['refusal'].startswith('segmentation: ') and unit['methods'] == {}
    assert 'mean over 1 units (1 refused)' in capsys.readouterr().out


def test_the_oracle_plans_in_the_truths_world(tmp_path):
    """A labelled neighbour 8 mm beside the target: the truth carries it as an obstacle, sampled at the planning
    grid it is the oracle posterior's obstacle (negative on the neighbour's cells, positive on the target's), and
    the perceived scene has it too; a grasp whose jaw starts in it fails every execution as a collision."""
    from gpis_grasp_ros.tools.evaluation.real import evaluate_grasp, prepare_real, sensing_params

    target, second = Box(0.0, 0.01, 0.03, 0.02, 0.04), Box(0.05, 0.01, 0.012, 0.02, 0.03, rgb=(200.0, 60.0, 40.0))
    scene = TiltedScene(45.0, distance_m=0.6, boxes=[target, second], width=480, height=360, focal_px=450.0)
    depth, rgb, label = scene.render()
    d = tmp_path
    cv2.imwrite(str(d / 'rgb.png'), np.asarray(rgb, dtype=np.uint8)[..., ::-1])
    cv2.imwrite(str(d / 'depth.png'), _millimetres(depth))
    cv2.imwrite(str(d / 'mask.png'), np.where(label > 0, 255, 0).astype(np.uint8))
    i = scene.intrinsics
    (d / 'cam.yaml').write_text(yaml.safe_dump({'fx': i.fx, 'fy': i.fy, 'cx': i.cx, 'cy': i.cy}))
    v, u = np.nonzero(label == 1)
    px = (float(u.mean()), float(v.mean()))
    imported = ri.import_capture(d / 'rgb.png', d / 'depth.png', d / 'cam.yaml', gt_mask=d / 'mask.png',
                                 gt_depth=d / 'depth.png', target_px=px)
    rf = prepare_real(ri.capture_scene(imported), sensing_params(imported.target_px), 'two boxes')
    g = rf.fit.sensing.geometry
    assert rf.true_obstacles is not None and rf.true_obstacles.sum() > 20
    oracle = rf.posterior(oracle=True)
    assert oracle.obstacles is not None
    assert (oracle.obstacles[rf.true_obstacles] < 0).all() and (oracle.obstacles[rf.truth] > 0).all()
    assert rf.fit.posterior.obstacles is not None  # the perception saw the neighbour as an obstacle too
    cells = g.cell_centers()
    ts = rf.true_shape  # the neighbour's deepest point on the truth's own grid, in planning-grid metres
    deepest = np.unravel_index(np.argmin(ts.obstacles), ts.obstacles.shape)
    centre_ob = ts.to_plan(ts.geometry.cell_centers()[deepest])
    assert ts.obstacles[deepest] < -0.01  # the neighbour's middle, 12 mm from its long faces
    centre_t = cells[rf.truth].mean(axis=0)
    away = centre_t - 0.035 * (centre_ob - centre_t) / np.linalg.norm(centre_ob - centre_t)
    out = rf.true_shape.execute_outcome(away, centre_ob, rf.gripper, 20, np.random.default_rng(0))
    assert out.collision == 20 and out.closed == 0, out
    # the grasps planned on the oracle and on the perception keep their jaw centres out of the true neighbour
    for oracle in (True, False):
        ev = evaluate_grasp(rf, 'gp-gpis-opt', 0, 10, oracle)
        assert np.isfinite(ev.true_clearance_m) and ev.true_clearance_m > 0.0, ev


def test_per_capture_checks_count_what_the_targets_ask():
    """Three captures, 20 trials: variants 2.9 apart pass and 3.1 apart fail the spread; a refused variant closes 0;
    the first method against GP-M on the mean of the variants; the oracle's floor on every variant. With 10 trials
    the thresholds scale (1.5 and 8.5 closures)."""
    from gpis_grasp_ros.tools.evaluate_real import report

    def unit(capture, variant, opt, gp_m, oracle, trials=20, refusal=''):
        figures = {'closures': opt}, {'closures': gp_m}
        return {'capture': capture, 'variant': variant, 'trials': trials, 'refusal': refusal,
                'methods': {} if refusal else {'gp-gpis-opt': figures[0], 'gp-m': figures[1]},
                'oracle': None if refusal else {'closures': oracle}}

    units = [unit('a', 'whole', 15.0, 14.0, 17.0), unit('a', 'crop', 17.9, 19.0, 18.0),   # 2.9 apart, mean 16.45 < 16.5
             unit('b', 'whole', 10.0, 9.0, 16.9), unit('b', 'crop', 13.1, 9.0, 20.0),     # 3.1 apart, oracle 16.9
             unit('c', 'whole', 2.0, 1.0, 18.0), unit('c', 'crop', 0, 0, 0, refusal='x')]  # refused crop: 0
    c = report.capture_checks(units, ['gp-gpis-opt', 'gp-m'], oracle=True)
    assert c == {'captures': 3, 'method': 'gp-gpis-opt', 'with_variants': 3, 'variants_within': 2,
                 'at_least_gp_m': 2, 'oracle_floor': 1}
    assert report.capture_line(c) == ('per capture (3): gp-gpis-opt within 3/20 across variants on 2 of 3; '
                                      'gp-gpis-opt >= gp-m on 2 of 3; oracle >= 17/20 on every variant of 1 of 3')
    tens = [unit('d', 'whole', 5.0, 5.0, 8.5, trials=10), unit('d', 'crop', 6.5, 5.0, 9.0, trials=10)]
    assert report.capture_checks(tens, ['gp-gpis-opt', 'gp-m'], oracle=True)['variants_within'] == 1
    assert report.capture_checks(tens, ['gp-gpis-opt', 'gp-m'], oracle=True)['oracle_floor'] == 1
    tens[1]['methods']['gp-gpis-opt']['closures'] = 6.6
    tens[0]['oracle']['closures'] = 8.4
    assert report.capture_checks(tens, ['gp-gpis-opt', 'gp-m'], oracle=True)['variants_within'] == 0
    assert report.capture_checks(tens, ['gp-gpis-opt', 'gp-m'], oracle=True)['oracle_floor'] == 0
    only_m = report.capture_checks(units, ['gp-m'], oracle=False)
    assert 'at_least_gp_m' not in only_m and 'oracle_floor' not in only_m
