"""Touching objects split at height steps (core.sensing.steps): rendered boxes, a wedge and lying cylinders at tilts
0-60 degrees, and raster cases (slivers between steps, the sensor's noise on one surface)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpis_grasp_ros.core.noise_model import SensorModel
from gpis_grasp_ros.core.sensing import SensingParams, segment_frames
from gpis_grasp_ros.core.sensing.params import FLAT_JUMP_M, FLAT_MIN_AREA_M2, FLAT_STEP_M
from gpis_grasp_ros.core.sensing.steps import CellHeights, split_height_steps, step_limit
from support.tilted_scene import Box, Cylinder, TiltedScene

COLOUR = (40.0, 90.0, 200.0)  # one colour for all: only depth can tell the objects apart


def _segment(scene: TiltedScene, rendered=None, target: int = 1, n: int = 4, seed: int = 0):
    """The scene's frames (``rendered`` = (depth, rgb, label) replaces its own rendering) segmented at the
    median pixel of object ``target``; returns the result and the label image."""
    depth, rgb, label = scene.render() if rendered is None else rendered
    rng = np.random.default_rng(seed)
    sigma = SensorModel().sigma(np.nan_to_num(depth, nan=1.0))
    d = depth[None] + sigma[None] * rng.standard_normal((n,) + depth.shape)
    c = np.clip(np.round(rgb[None] + 2.0 * rng.standard_normal((n,) + rgb.shape)), 0, 255).astype(np.uint8)
    vv, uu = np.nonzero(label == target)
    params = SensingParams(target='pixel', target_point=(float(np.median(uu)), float(np.median(vv))))
    return segment_frames(c, d, scene.intrinsics, params), label


@pytest.mark.parametrize('tilt', [0.0, 30.0, 60.0])
@pytest.mark.parametrize('target', [1, 2])
def test_touching_boxes_of_different_heights_are_two_objects(tilt, target):
    """A 4 x 4 x 3 cm box against a 4 x 4 x 8 cm one (side by side across the view; the low top is 16 cm^2, less
    than a flat support): the target pixel on either selects that box, >= 80 % of its pixels and < 10 % of the
    other's."""
    scene = TiltedScene(tilt, boxes=[Box(-0.02, 0.0, 0.02, 0.02, 0.03, rgb=COLOUR),
                                     Box(0.02, 0.0, 0.02, 0.02, 0.08, rgb=COLOUR)])
    assert 0.04 * 0.04 < FLAT_MIN_AREA_M2
    res, label = _segment(scene, target=target, seed=int(tilt) + target)
    assert res.objects_seen == 2
    assert res.object_mask[label == target].mean() >= 0.8
    assert res.object_mask[label == 3 - target].mean() < 0.1


@pytest.mark.parametrize('tilt', [0.0, 30.0])
def test_touching_boxes_one_behind_the_other_are_two_objects(tilt):
    """The same boxes one behind the other along the view, the low one nearer the camera (at 60 degrees the tall
    one would hide a low one behind it): two objects, each target selecting its box."""
    scene = TiltedScene(tilt, boxes=[Box(0.0, -0.02, 0.02, 0.02, 0.03, rgb=COLOUR),
                                     Box(0.0, 0.02, 0.02, 0.02, 0.08, rgb=COLOUR)])
    for target in (1, 2):
        res, label = _segment(scene, target=target, seed=target)
        assert res.object_mask[label == target].mean() >= 0.8
        assert res.object_mask[label == 3 - target].mean() < 0.1


@pytest.mark.parametrize('tilt', [0.0, 30.0, 60.0])
def test_touching_boxes_of_one_height_stay_one_object(tilt):
    """Two 4 x 4 x 3 cm boxes side by side: no step between them, one object (8 x 4 cm, narrow enough to grasp)."""
    scene = TiltedScene(tilt, boxes=[Box(-0.02, 0.0, 0.02, 0.02, 0.03, rgb=COLOUR),
                                     Box(0.02, 0.0, 0.02, 0.02, 0.03, rgb=COLOUR)])
    res, label = _segment(scene, seed=int(tilt))
    assert res.objects_seen == 1
    assert res.object_mask[label == 1].mean() >= 0.8 and res.object_mask[label == 2].mean() >= 0.8


def _wedge(scene: TiltedScene, x0: float, x1: float, half_y: float, h0: float, h1: float):
    """``scene`` rendered with a wedge added (label = boxes + cylinders + 1): x0..x1 (m, along the table frame's x),
    |y| <= half_y, its top rising linearly from h0 at x0 to h1 at x1 (m); ray / convex polyhedron (Cyrus-Beck)."""
    depth, rgb, label = scene.render()
    intr = scene.intrinsics
    u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(u.shape)], axis=-1)
    local = rays @ scene.frame
    ox, oy = scene.origin_xy
    d = scene.offset
    slope = (h1 - h0) / (x1 - x0)
    ax0, ax1 = ox + x0, ox + x1
    # half-spaces n . p <= c in the table frame (camera at the origin, the table at z = d, heights towards -z)
    planes = [((1.0, 0.0, 0.0), ax1), ((-1.0, 0.0, 0.0), -ax0), ((0.0, 1.0, 0.0), oy + half_y),
              ((0.0, -1.0, 0.0), -(oy - half_y)), ((0.0, 0.0, 1.0), d),
              ((-slope, 0.0, -1.0), -(d - h0 + slope * ax0))]
    t_in = np.zeros(u.shape)
    t_out = np.full(u.shape, np.inf)
    for n, c in planes:
        nd = local @ np.asarray(n)
        with np.errstate(divide='ignore', invalid='ignore'):
            t = c / nd
        t_in = np.where(nd < 0, np.maximum(t_in, t), t_in)
        t_out = np.where(nd > 0, np.minimum(t_out, t), t_out)
        t_out = np.where((nd == 0) & (c < 0), -np.inf, t_out)
    hit = (t_in <= t_out) & (t_in > 0) & ~(np.nan_to_num(depth, nan=np.inf) < t_in)
    k = int(label.max()) + 1
    return np.where(hit, t_in, depth), np.where(hit[..., None], np.asarray(COLOUR), rgb), np.where(hit, k, label)


@pytest.mark.parametrize('tilt', [0.0, 30.0, 60.0])
def test_parts_at_several_heights_joined_by_a_slope_stay_one_object(tilt):
    """A wedge rising from 1 to 6 cm over 10 cm (27 degrees; 5 cm wide) with a 6 cm box at its high end, and a
    lying cylinder (r 2 cm): each is one object, its target covering >= 95 % of it."""
    scene = TiltedScene(tilt, boxes=[Box(0.065, 0.0, 0.015, 0.025, 0.06, rgb=COLOUR)])
    res, label = _segment(scene, _wedge(scene, -0.05, 0.05, 0.025, 0.01, 0.06), target=2, seed=int(tilt))
    assert res.objects_seen == 1
    assert res.object_mask[label == 2].mean() >= 0.95 and res.object_mask[label == 1].mean() >= 0.95
    scene = TiltedScene(tilt, cylinders=[Cylinder(-0.06, 0.06, 0.0, 0.02, rgb=COLOUR)])
    res, label = _segment(scene, seed=int(tilt))
    assert res.objects_seen == 1 and res.object_mask[label == 1].mean() >= 0.95


@pytest.mark.parametrize('tilt', [0.0, 30.0, 60.0])
def test_a_lying_cylinder_with_a_taller_end_cap_of_another_colour_stays_one_object(tilt):
    """A grey lying cylinder whose smooth crest is not flat (it spans 1.25 FLAT_JUMP_M at the raster's cells) with a
    red head 8 mm wider in radius (a capped bottle, a flashlight with a coloured head), 10 Carmine frames at 0.8 m:
    one object, a target pixel on either part covering > 95 % of both. A colour change across a step whose lower
    side is not flat does not tell two objects from one (docs/perception.md, colour as a split cue)."""
    res = 2.0 * 0.8 / 570.0 / math.cos(math.radians(tilt))
    r = 1.25 * FLAT_JUMP_M / (1.0 - 1.0 / math.sqrt(1.0 + (FLAT_STEP_M / res) ** 2))  # crest spans 1.25 FLAT_JUMP_M
    scene = TiltedScene(tilt, cylinders=[Cylinder(-0.10, 0.06, 0.0, r, rgb=(60.0, 60.0, 60.0)),
                                         Cylinder(0.06, 0.10, 0.0, r + 0.008, rgb=(200.0, 40.0, 40.0))])
    rgb, depth, label = scene.frames(10, seed=int(tilt))
    for target in (1, 2):
        vv, uu = np.nonzero(label == target)
        k = vv.size // 2
        params = SensingParams(target='pixel', target_point=(float(uu[k]), float(vv[k])), max_opening_m=0.0)
        result = segment_frames(rgb, depth, scene.intrinsics, params)
        assert result.objects_seen == 1
        assert result.object_mask[label == 1].mean() > 0.95 and result.object_mask[label == 2].mean() > 0.95


RES = 0.003  # raster cell (m)


def _cells(h: np.ndarray, sigma: float) -> CellHeights:
    """Cells whose heights are ``h`` (m, NaN = no depth), each seen by 4 pixels of height noise ``sigma`` (m)."""
    seen = np.isfinite(h)
    return CellHeights(h, np.where(seen, sigma, np.nan), np.where(seen, 0.0, np.nan), 4 * seen.astype(int),
                       4 * seen.astype(int), np.zeros(h.shape, bool))


def test_a_sliver_between_two_steps_is_no_object():
    """A 1 cm top and a 6 cm top, 30 x 30 cells each, joined by a 2-cell strip at 3.5 cm (a wall's cells): two
    objects, the strip in one of them; with the strip 3 cells wide (9 mm, less than a 1 cm jaw face) still two."""
    for width in (2, 3):
        h = np.full((30, 60 + width), np.nan)
        h[:, :30] = 0.01
        h[:, 30:30 + width] = 0.035
        h[:, 30 + width:] = 0.06
        labels = np.ones(h.shape, np.int32)
        out, origin = split_height_steps(labels, _cells(h, 0.001), RES, 0.01, 1e-4)
        assert len(np.unique(out)) == 2 and list(origin) == [0, 1, 1]
        assert len(np.unique(out[:, :30])) == 1 and len(np.unique(out[:, 30 + width:])) == 1
        assert out[0, 0] != out[0, -1]


def test_the_sensors_noise_and_specks_never_split_one_surface():
    """400 random cases: a 12 x 12 cm top at 0.5-8 cm (half of them within 5 mm of the height at which a surface
    is continuous with the table, where noise makes islands above it), flat or sloped up to 40 degrees, with the
    sensor's noise (1-3 mm) and up to 5 single-cell specks 2-5 cm above it: always one object."""
    rng = np.random.default_rng(0)
    for k in range(400):
        sigma = rng.uniform(0.001, 0.003)
        yy, xx = np.mgrid[:40, :40]
        ground = float(step_limit(np.array(sigma), np.array(sigma), RES))
        top = rng.uniform(0.005, 0.08) if k % 2 else ground + rng.uniform(-0.005, 0.005)
        h = top + xx * RES * math.tan(math.radians(rng.uniform(0.0, 40.0)))
        h = h + sigma * rng.standard_normal(h.shape)
        for _ in range(rng.integers(0, 6)):
            h[rng.integers(0, 40), rng.integers(0, 40)] += rng.uniform(0.02, 0.05)
        out, _ = split_height_steps(np.ones(h.shape, np.int32), _cells(h, sigma), RES, 0.01, 1e-4)
        assert np.all(out == 1)


def test_step_limit_is_the_noise_of_a_difference_plus_a_45_degree_rise():
    assert step_limit(np.array(0.0), np.array(0.0), RES) == pytest.approx(RES)
    assert step_limit(np.array(0.001), np.array(0.001), 0.0) == pytest.approx(3.29 * math.sqrt(2) * 0.001, rel=1e-3)


def test_cell_heights_equal_the_array_code():
    from gpis_grasp_ros.core.sensing.steps import cell_heights

    rng = np.random.default_rng(12)
    shape, img = (23, 31), (90, 120)
    iy, ix = rng.integers(0, shape[0], img), rng.integers(0, shape[1], img)
    evidence = rng.random(img) < 0.6
    height = rng.normal(0.02, 0.01, img) * np.exp(rng.uniform(-20, 20, img))
    height[rng.random(img) < 0.1] = np.nan
    height[rng.random(img) < 0.02] = 0.0
    height[rng.random(img) < 0.02] = -0.0
    sigma = rng.uniform(0.0, 0.003, img)
    missing = rng.random(img) < 0.1
    ny, nx = shape
    size = nx * ny
    key = iy * nx + ix
    seen = evidence & np.isfinite(height) & ~missing
    k, h = key[seen], height[seen]
    count = np.bincount(k, minlength=size)
    hi, lo = np.full(size, -np.inf), np.full(size, np.inf)
    np.maximum.at(hi, k, h)
    np.minimum.at(lo, k, h)
    with np.errstate(invalid='ignore', divide='ignore'):
        mean = np.where(count > 0, np.bincount(k, weights=h, minlength=size) / np.maximum(count, 1), np.nan)
        rms = np.sqrt(np.where(count > 0, np.bincount(k, weights=sigma[seen] ** 2, minlength=size)
                               / np.maximum(count, 1), np.nan))
    blind = (np.bincount(key[evidence & missing], minlength=size) > 0) & (count == 0)
    want = (mean.reshape(shape), rms.reshape(shape), np.where(count > 0, hi - lo, np.nan).reshape(shape),
            count.reshape(shape), np.bincount(key[evidence], minlength=size).reshape(shape), blind.reshape(shape))
    got = cell_heights(iy, ix, evidence, height, sigma, missing, shape)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype and np.array_equal(np.asarray(g).view(np.uint8), np.asarray(w).view(np.uint8))
