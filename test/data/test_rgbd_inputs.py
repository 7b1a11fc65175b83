"""import-rgbd input readers: 32-bit float OpenEXR depth (ClearGrasp's format) and JSON intrinsics, ROS-free."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from gpis_grasp_ros.data import rgbd_import as ri

OpenEXR = pytest.importorskip('OpenEXR')

HEADER = {'compression': OpenEXR.ZIP_COMPRESSION, 'type': OpenEXR.scanlineimage}


def _depth(h: int = 24, w: int = 32) -> np.ndarray:
    """float32 depth (m) with every float32 bit pattern the reader must keep: fractions, holes (0, NaN, inf)."""
    rng = np.random.default_rng(3)
    d = (0.4 + 0.6 * rng.random((h, w))).astype(np.float32)
    d[0, 0], d[1, 1], d[2, 2] = 0.0, np.nan, np.inf
    return d


def test_exr_single_channel_reads_back_exactly(tmp_path):
    d = _depth()
    path = tmp_path / 'depth.exr'
    OpenEXR.File(HEADER, {'Z': d}).write(str(path))
    raw = ri.read_exr(path)
    assert raw.dtype == np.float32 and raw.shape == d.shape
    assert np.array_equal(raw, d, equal_nan=True)
    metres = ri.load_depth(path)
    valid = np.isfinite(d) & (d > 0)
    assert np.array_equal(metres[valid], d[valid].astype(np.float64))
    assert np.isnan(metres[~valid]).all()  # 0, NaN and inf are "no return"


def test_exr_rgb_depth_as_cleargrasp_writes_it(tmp_path):
    """ClearGrasp stores depth in R, G and B: the reader takes R (the first of Z, depth, Y, R present)."""
    d = _depth()
    path = tmp_path / 'cleargrasp-depth.exr'
    OpenEXR.File(HEADER, {'RGB': np.stack([d, d * 2, d * 3], axis=-1)}).write(str(path))
    assert np.array_equal(ri.read_exr(path), d, equal_nan=True)


def test_exr_half_precision_and_no_depth_channel(tmp_path):
    d = _depth().astype(np.float16)
    path = tmp_path / 'half.exr'
    OpenEXR.File(HEADER, {'depth': d, 'A': np.ones_like(d)}).write(str(path))
    assert np.array_equal(ri.read_exr(path), d, equal_nan=True)
    other = tmp_path / 'other.exr'
    OpenEXR.File(HEADER, {'U': d, 'V': d}).write(str(other))
    with pytest.raises(ValueError, match='no depth channel'):
        ri.read_exr(other)


def test_exr_not_an_exr(tmp_path):
    path = tmp_path / 'fake.exr'
    path.write_bytes(b'not an image')
    with pytest.raises(ValueError, match='OpenEXR'):
        ri.load_depth(path)


def test_capture_with_exr_depth(tmp_path):
    """A whole capture with EXR depth loads as one with the same depth in a .npy."""
    d = _depth()
    OpenEXR.File(HEADER, {'Z': d}).write(str(tmp_path / 'd.exr'))
    np.save(tmp_path / 'd.npy', d)
    cv2.imwrite(str(tmp_path / 'c.png'), np.zeros((*d.shape, 3), np.uint8))
    intr = {'fx': 50.0, 'fy': 51.0, 'cx': 15.5, 'cy': 11.5}
    a = ri.load_capture(tmp_path / 'c.png', tmp_path / 'd.exr', intr)
    b = ri.load_capture(tmp_path / 'c.png', tmp_path / 'd.npy', intr)
    assert np.array_equal(a.depth, b.depth, equal_nan=True) and a.intrinsics == b.intrinsics


@pytest.mark.parametrize('form', ['underscore', 'plain'])
def test_json_intrinsics(tmp_path, form):
    values = {'fx': 615.25, 'fy': 616.5, 'cx': 319.75, 'cy': 241.125, 'width': 640, 'height': 480}
    data = {('_' + k if form == 'underscore' and k[0] in 'fc' else k): v for k, v in values.items()}
    path = tmp_path / 'camera.json'
    path.write_text(json.dumps(data))
    i = ri.load_intrinsics(path)
    assert (i.fx, i.fy, i.cx, i.cy, i.width, i.height) == (615.25, 616.5, 319.75, 241.125, 640, 480)


def test_json_intrinsics_without_size_take_the_image_size(tmp_path):
    path = tmp_path / 'camera.json'
    path.write_text(json.dumps({'_fx': 500.0, '_fy': 501.0, '_cx': 320.0, '_cy': 240.0}))
    with pytest.raises(ValueError, match='image size'):
        ri.load_intrinsics(path)
    i = ri.load_intrinsics(path, width=640, height=480)
    assert (i.fx, i.cy, i.width, i.height) == (500.0, 240.0, 640, 480)


def test_json_intrinsics_errors(tmp_path):
    bad = tmp_path / 'bad.json'
    bad.write_text('{"_fx": 1,')
    with pytest.raises(ValueError, match='not valid JSON'):
        ri.load_intrinsics(bad)
    listed = tmp_path / 'list.json'
    listed.write_text('[1, 2, 3]')
    with pytest.raises(ValueError, match='JSON object'):
        ri.load_intrinsics(listed)
    missing = tmp_path / 'missing.json'
    missing.write_text(json.dumps({'_fx': 1.0, '_fy': 1.0, '_cx': 1.0}))
    with pytest.raises(ValueError, match='_fx, _fy, _cx, _cy'):
        ri.load_intrinsics(missing, 4, 4)


def test_import_rgbd_help_names_defaults_and_units(capsys, monkeypatch):
    from gpis_grasp_ros.tools import import_rgbd

    monkeypatch.setenv('COLUMNS', '1000')  # no hyphenated line breaks

    with pytest.raises(SystemExit):
        import_rgbd.parse_args(['--help'])
    text = ' '.join(capsys.readouterr().out.split())
    assert 'OpenEXR' in text and '_fx' in text
    assert 'table-plane fit of the ground truth' in text and 'segmentation of --evaluate' in text
    for default in ('default 0.001', 'default 1)', 'default 20', 'default 0, as segmentation_node',
                    'default realsense_d400'):
        assert default in text, default
