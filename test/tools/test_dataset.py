"""Generated object sets (sim/dataset.py) and the make-dataset command: determinism, outline
properties, serialisation fidelity, bags on request, paper objects and user bags mixed in."""

from __future__ import annotations

import hashlib
import json
import math
from collections import Counter

import numpy as np
import pytest

from gpis_grasp_ros.data.bags import load_bag
from gpis_grasp_ros.sim import dataset as ds
from gpis_grasp_ros.sim import objects
from gpis_grasp_ros.sim.scene import MATERIAL_KINDS, Scene, polygon_area
from gpis_grasp_ros.tools import dataset_cli


def _segments_cross(poly: np.ndarray) -> bool:
    """Independent simplicity check: do any two non-adjacent edges intersect (touching counts)?"""
    n = len(poly)
    a, b = poly, np.roll(poly, -1, axis=0)
    for i in range(n):
        j = np.arange(i + 2, n if i > 0 else n - 1)
        if j.size == 0:
            continue
        p, r = a[i], b[i] - a[i]
        q, s = a[j], b[j] - a[j]
        denom = r[0] * s[:, 1] - r[1] * s[:, 0]
        qp = q - p
        with np.errstate(divide='ignore', invalid='ignore'):
            t = (qp[:, 0] * s[:, 1] - qp[:, 1] * s[:, 0]) / denom
            u = (qp[:, 0] * r[1] - qp[:, 1] * r[0]) / denom
        hit = (np.abs(denom) > 1e-18) & (t >= -1e-12) & (t <= 1 + 1e-12) & (u >= -1e-12) & (u <= 1 + 1e-12)
        if hit.any():
            return True
    return False


def _frame_digest(scene) -> str:
    h = hashlib.sha256()
    for arr in (scene.rgb_frames, scene.depth_frames, scene.true_sdf):
        h.update(np.ascontiguousarray(arr).tobytes())
    return h.hexdigest()


@pytest.mark.parametrize('family', ds.FAMILIES)
def test_outlines_are_simple_polygons_with_the_requested_size(family):
    rng = np.random.default_rng(2026)
    for _ in range(25):
        size = float(rng.uniform(0.02, 0.14))
        poly = ds.generate_outline(family, size, rng)
        assert poly.ndim == 2 and poly.shape[1] == 2 and len(poly) >= 3
        assert np.isfinite(poly).all()
        assert polygon_area(poly) > 0  # counter-clockwise, non-degenerate
        assert not _segments_cross(poly)
        diameter = float(np.max(np.linalg.norm(poly[:, None] - poly[None], axis=-1)))
        assert diameter == pytest.approx(size, rel=2e-3)  # largest extent = requested size
        assert np.linalg.norm(0.5 * (poly.min(axis=0) + poly.max(axis=0))) <= 0.01 * math.sqrt(2) + 1e-12


def test_generated_entries_cover_families_sizes_and_materials():
    manifest = ds.build_manifest(80, seed=4)
    entries = manifest['objects']
    assert Counter(e['family'] for e in entries).keys() == set(ds.FAMILIES)
    sizes = np.array([e['size_m'] for e in entries])
    assert sizes.min() >= 0.02 * (1 - 1e-3) and sizes.max() <= 0.14 * (1 + 1e-3)
    assert {e['size_class'] for e in entries} == {'small', 'medium', 'large'}
    assert any(e['size_m'] > ds.DEFAULT_MAX_OPENING_M for e in entries)  # beyond the gripper's opening
    kinds = {k for e in entries for k in e['materials']}
    assert kinds == set(MATERIAL_KINDS) - {'opaque'}
    assert 'opaque' in {e['material_class'] for e in entries}
    for e in entries:
        assert e['min_width_m'] <= e['size_m']
        assert e['material_class'] == ds.material_class(e['materials'])
        assert e['size_class'] == ds.size_class(e['size_m'])
        spec = e['spec']
        assert 0.5 <= spec['camera_height'] <= 0.8
        if e['camera'] == 'head':
            assert ds.TILTED_CAMERA and ds.HEAD_TILT_DEG[0] <= spec['camera_tilt'] <= ds.HEAD_TILT_DEG[1]
        else:
            assert e['camera'] == 'top-down' and spec.get('camera_tilt', 0.0) == 0.0
    cameras = {e['camera'] for e in entries}
    assert cameras == ({'top-down', 'head'} if ds.TILTED_CAMERA else {'top-down'})


def test_same_seed_same_manifest_and_scene_bytes(tmp_path):
    a = ds.make_dataset(tmp_path / 'a', 5, seed=9)
    b = ds.make_dataset(tmp_path / 'b', 5, seed=9)
    c = ds.make_dataset(tmp_path / 'c', 5, seed=10)
    assert (tmp_path / 'a' / 'manifest.json').read_bytes() == (tmp_path / 'b' / 'manifest.json').read_bytes()
    assert (tmp_path / 'a' / 'manifest.csv').read_bytes() == (tmp_path / 'b' / 'manifest.csv').read_bytes()
    assert (tmp_path / 'a' / 'manifest.json').read_bytes() != (tmp_path / 'c' / 'manifest.json').read_bytes()
    assert ds.manifest_digest(a) == ds.manifest_digest(b) != ds.manifest_digest(c)
    # a prefix: object i depends on (seed, i) only
    assert ds.build_manifest(3, seed=9)['objects'] == a.entries[:3]
    # the loaded manifest round-trips exactly (floats included)
    assert a.entries == json.loads((tmp_path / 'a' / 'manifest.json').read_text())['objects']
    for ea, eb, ec in zip(a.entries[:2], b.entries[:2], c.entries[:2], strict=True):
        ra, rb, rc = (ds.render_entry(e, frames=2) for e in (ea, eb, ec))
        assert _frame_digest(ra) == _frame_digest(rb)
        assert _frame_digest(ra) != _frame_digest(rc)


def test_paper_entry_round_trips_the_catalogue_scene():
    spec = objects.OBJECTS['B'].build()
    entry = ds.paper_entry('b')
    assert entry['id'] == 'paper_B' and entry['source'] == 'paper' and entry['letter'] == 'B'
    back = ds.spec_from_dict(json.loads(json.dumps(entry['spec'])), frames=2)
    np.testing.assert_array_equal(back.outline, spec.outline)
    spec.frames = 2
    f1 = [f.depth for f in Scene(spec).frames()]
    f2 = [f.depth for f in Scene(back).frames()]
    np.testing.assert_array_equal(np.stack(f1), np.stack(f2))
    assert entry['size_class'] == 'large'  # the 10.2 cm nail is longer than the 9 cm opening
    assert entry['min_width_m'] == pytest.approx(0.011, abs=0.002)  # across the head
    with pytest.raises(ValueError, match='unknown paper object'):
        ds.paper_entry('Z')


def test_bag_on_request_matches_the_in_memory_rendering_and_mixes_in(tmp_path):
    dataset = ds.make_dataset(tmp_path / 'set', 2, seed=1, frames=2)
    entry = dataset.entries[0]
    assert dataset_cli.main(['--out', str(tmp_path / 'set'), '--bag-of', entry['id']]) == 0
    bag = tmp_path / 'set' / 'bags' / f"{entry['id']}.mcap"
    rendered = ds.render_entry(entry)
    loaded = load_bag(bag, frames=2, source='images')
    np.testing.assert_array_equal(loaded.depth_frames, rendered.depth_frames)
    np.testing.assert_array_equal(loaded.rgb_frames, rendered.rgb_frames)
    np.testing.assert_allclose(loaded.true_sdf, rendered.true_sdf, atol=1e-7)
    mixed = ds.make_dataset(tmp_path / 'mixed', 1, seed=1, paper=['A'], bags=[bag])
    assert [e['source'] for e in mixed.entries] == ['generated', 'paper', 'bag']
    user = mixed.entries[2]
    assert user['bag'] == str(bag.resolve()) and user['spec'] is None
    assert user['size_m'] == pytest.approx(entry['size_m'], abs=0.003)  # from the bag's 1 mm ground truth
    again = ds.render_entry(user, frames=2)
    np.testing.assert_array_equal(again.rgb_frames.shape, rendered.rgb_frames.shape)


def test_make_dataset_command(tmp_path, capsys):
    assert dataset_cli.main(['--n', '4', '--seed', '2', '--paper', 'C,D', '--out', str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert '6 objects' in text and 'family' in text
    loaded = ds.load_dataset(tmp_path)
    assert [e['id'] for e in loaded.entries][-2:] == ['paper_C', 'paper_D']
    rows = (tmp_path / 'manifest.csv').read_text().splitlines()
    assert len(rows) == 7 and rows[0].startswith('id,source,name,family,size_m')
    assert dataset_cli.main(['--n', '-1', '--out', str(tmp_path / 'x')]) == 2
    assert dataset_cli.main(['--n', '1', '--bag', str(tmp_path / 'missing.mcap'), '--out', str(tmp_path / 'y')]) == 2
    assert 'bag not found' in capsys.readouterr().err
    with pytest.raises(ValueError, match='no dataset manifest'):
        ds.load_dataset(tmp_path / 'nowhere')
