"""Objects stage (core.sensing.objects): touching objects split, specks dropped, the target picked."""

from __future__ import annotations

import numpy as np
import pytest

from gpis_grasp_ros.core.sensing import (
    CameraIntrinsics,
    SensingParams,
    minimum_width,
    nearest_pixel,
    object_height,
    split_touching,
)
from gpis_grasp_ros.core.sensing.objects import _Raster, _select_target, object_labels


def test_two_touching_boxes_are_split_at_their_contact():
    """Two 12 x 12-cell squares joined by a 2-cell neck: one component, split into two of the squares' size."""
    labels = np.zeros((20, 40), np.int32)
    labels[4:16, 4:16] = 1
    labels[4:16, 24:36] = 1
    labels[9:11, 16:24] = 1  # the contact
    out, origin = split_touching(labels, neck_cells=1.0)
    parts = [lab for lab in np.unique(out) if lab > 0]
    assert len(parts) == 2 and list(origin[parts]) == [1, 1]
    assert len(np.unique(out[4:16, 4:16])) == 1 and len(np.unique(out[4:16, 24:36])) == 1
    assert out[10, 10] != out[10, 30]
    assert all(abs(int((out == p).sum()) - 12 * 12 - 8) <= 8 for p in parts)


def test_an_object_with_a_narrow_part_stays_whole():
    labels = np.zeros((20, 40), np.int32)
    labels[4:16, 4:16] = 1
    labels[9:11, 16:34] = 1  # a marker's tip: no second blob
    out, _ = split_touching(labels, neck_cells=1.0)
    assert np.array_equal(out > 0, labels > 0) and len(np.unique(out[out > 0])) == 1


def _scene_labels() -> tuple[np.ndarray, _Raster, np.ndarray, CameraIntrinsics]:
    """Three components in the table raster (5 mm cells): 10 x 10 cells, 5 x 5 cells and one cell (a speck of
    0.25 cm^2), with 200, 100 and 50 pixels, each pixel's foot in a cell of its component."""
    labels = np.zeros((30, 30), np.int32)
    labels[2:12, 2:12] = 1
    labels[20:25, 20:25] = 2
    labels[27, 5] = 3
    raster = _Raster(np.zeros(2), 0.005, labels)
    px = np.zeros((40, 60), np.int64)
    px[:10, :20] = 1
    px[30:35, 40:60] = 2
    px[20:25, 0:10] = 3
    foot = np.full((40, 60, 2), np.nan)
    for lab in (1, 2, 3):
        iy, ix = np.nonzero(labels == lab)
        centres = (np.stack([ix, iy], axis=1) + 0.5) * raster.res
        foot[px == lab] = centres[np.arange((px == lab).sum()) % centres.shape[0]]
    return px, raster, foot, CameraIntrinsics(50.0, 50.0, 29.5, 19.5, 60, 40)


def _select(px, raster, foot, params, intr, solid=None):
    solid = px > 0 if solid is None else solid
    return _select_target(px, raster, foot, params, intr, object_labels(px, raster, foot, solid, params))


def test_specks_are_not_objects():
    px, raster, foot, intr = _scene_labels()
    target, seen = _select(px, raster, foot, SensingParams(), intr)
    assert (target, seen) == (1, 2)
    target, seen = _select(px, raster, foot, SensingParams(min_object_area_m2=1e-5), intr)
    assert seen == 3
    with pytest.raises(ValueError, match='no object found'):
        _select(px, raster, foot, SensingParams(min_object_area_px=1000), intr)


def test_an_object_needs_a_minimum_area_of_solid_evidence():
    """Component 2 (5 x 5 cells, 6.25 cm^2) with solid evidence in 3 cells (0.75 cm^2) is no object; in 4 cells
    (1 cm^2, the minimum) it is. Component 1 without any solid pixel is none either."""
    px, raster, foot, intr = _scene_labels()
    ix, iy, _ = raster.cell(foot)
    cell = iy * 30 + ix
    for n_cells, objects in ((3, []), (4, [2])):
        solid = (px == 2) & np.isin(cell, np.unique(cell[px == 2])[:n_cells])
        assert list(object_labels(px, raster, foot, solid, SensingParams())) == objects
    with pytest.raises(ValueError, match='no object found'):
        _select(px, raster, foot, SensingParams(), intr, np.zeros(px.shape, bool))


def test_target_nearest_the_image_centre():
    px, raster, foot, intr = _scene_labels()
    px[:] = 0
    px[0:5, 0:40] = 1  # centroid (19.5, 2)
    px[15:25, 25:35] = 2  # centroid (29.5, 19.5): the image centre
    foot[:] = np.nan
    for lab in (1, 2):
        iy, ix = np.nonzero(raster.labels == lab)
        centres = (np.stack([ix, iy], axis=1) + 0.5) * raster.res
        foot[px == lab] = centres[np.arange((px == lab).sum()) % centres.shape[0]]
    assert _select(px, raster, foot, SensingParams(target='nearest_center'), intr)[0] == 2


def test_minimum_width_object_height_and_nearest_pixel():
    c, s = np.cos(0.3), np.sin(0.3)
    corners = np.array([[0, 0], [0.08, 0], [0.08, 0.03], [0, 0.03]]) @ np.array([[c, s], [-s, c]])
    assert minimum_width(corners) == pytest.approx(0.03)
    h = np.linspace(0.0, 0.1, 101)
    assert object_height(h, np.ones(101, bool)) == pytest.approx(0.095)
    assert object_height(h, np.zeros(101, bool)) == 0.0
    mask = np.zeros((5, 7), bool)
    mask[1, 2] = True
    dist, near = nearest_pixel(mask)
    assert dist[1, 2] == 0 and dist[4, 6] == pytest.approx(5.0, abs=0.05)
    assert (near == [1, 2]).all()


@pytest.mark.parametrize('tilt', [0.0, 40.0])
def test_an_inseparable_cluster_wider_than_the_gripper_is_refused_with_how_to_select_a_part(tilt):
    """Two 7 x 12 x 3 cm boxes of one colour side by side (14 x 12 cm, no step, no neck between them) are one
    object too wide for the 9 cm opening: refused with the reason and the roi_table to select one by; the
    roi_table of one box's half gives that box alone (its pixels, no more than a tenth of the other's)."""
    import re

    from gpis_grasp_ros.core.sensing import segment_frames
    from support.tilted_scene import Box, TiltedScene

    colour = (40.0, 90.0, 200.0)
    scene = TiltedScene(tilt, boxes=[Box(-0.035, 0.0, 0.035, 0.06, 0.03, rgb=colour),
                                     Box(0.035, 0.0, 0.035, 0.06, 0.03, rgb=colour)])
    rgb, depth, label = scene.frames(2, seed=3)
    vv, uu = np.nonzero(label == 1)
    params = SensingParams(target='pixel', target_point=(float(np.median(uu)), float(np.median(vv))))
    with pytest.raises(ValueError, match='wide in its narrowest direction') as err:
        segment_frames(rgb, depth, scene.intrinsics, params)
    msg = str(err.value)
    assert 'roi_table' in msg and 'touching' in msg
    span = re.search(r'spans x (-?[\d.]+) \.\. (-?[\d.]+), y (-?[\d.]+) \.\. (-?[\d.]+)', msg)
    x0, x1, y0, y1 = (float(g) for g in span.groups())
    assert x1 - x0 == pytest.approx(0.14, abs=0.01) and y1 - y0 == pytest.approx(0.12, abs=0.01 + 0.03 * tilt / 40)
    # the table frame's x is the camera's x projected, as the renderer's: box 1 is the half at lower x
    mid = 0.5 * (x0 + x1)
    res = segment_frames(rgb, depth, scene.intrinsics, SensingParams(
        target='pixel', target_point=params.target_point, roi_table=(x0 - 0.01, y0 - 0.01, mid - 0.002, y1 + 0.01)))
    assert res.object_mask[label == 1].mean() > 0.8
    assert res.object_mask[label == 2].mean() < 0.1
