"""The target's window: the pixels it holds, and segmentation in it against the whole frame and a crop."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from gpis_grasp_ros.core.sensing import CameraIntrinsics, SensingParams
from gpis_grasp_ros.core.sensing import segment as seg
from gpis_grasp_ros.core.sensing.camera import average_frames, validate_frames
from gpis_grasp_ros.core.sensing.table import fit_table
from gpis_grasp_ros.core.sensing.window import _meets, square, target_point, window
from gpis_grasp_ros.sim.scene import CameraModel, Distractor, Scene, SceneSpec


def _orient(a, b, c):
    return np.sign((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))


def _segments_cross(p1, p2, q1, q2) -> bool:
    """Closed segments p1p2 and q1q2 meet (orientation tests, collinear overlaps included)."""
    o1, o2, o3, o4 = _orient(p1, p2, q1), _orient(p1, p2, q2), _orient(q1, q2, p1), _orient(q1, q2, p2)
    if o1 != o2 and o3 != o4:
        return True

    def on(a, b, c):  # c on segment ab, given collinear
        return min(a[0], b[0]) <= c[0] <= max(a[0], b[0]) and min(a[1], b[1]) <= c[1] <= max(a[1], b[1])

    return bool((o1 == 0 and on(p1, p2, q1)) or (o2 == 0 and on(p1, p2, q2)) or (o3 == 0 and on(q1, q2, p1))
                or (o4 == 0 and on(q1, q2, p2)))


def _reference_meets(f, t, rect) -> bool:
    x0, y0, x1, y1 = rect
    inside = [x0 <= p[0] <= x1 and y0 <= p[1] <= y1 for p in (f, t)]
    if any(inside):
        return True
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    return any(_segments_cross(f, t, corners[k], corners[(k + 1) % 4]) for k in range(4))


def test_segment_meets_rectangle_as_an_independent_geometric_test():
    rng = np.random.default_rng(3)
    agree = hits = 0
    for _ in range(3000):
        f, t = rng.uniform(-1, 1, 2), rng.uniform(-1, 1, 2)
        if rng.random() < 0.1:
            t = f.copy()  # a point (a pixel on the table)
        c, half = rng.uniform(-0.5, 0.5, 2), rng.uniform(0.05, 0.5, 2)
        rect = (c[0] - half[0], c[1] - half[1], c[0] + half[0], c[1] + half[1])
        want = _reference_meets(f, t, rect)
        agree += _meets(f[0], f[1], t[0], t[1], *rect) == want
        hits += want
    assert agree == 3000
    assert 300 < hits < 2700  # both outcomes well represented


@functools.cache
def _scene(tilt: float, width: int = 320, height: int = 240, long: bool = False) -> tuple:
    """A whole frame: the target (a box, or a 24 cm bar), a tall box beside it that hides part of its table from
    a tilted camera, and a can far away."""
    f = 570.3 * width / 640.0
    cam = CameraModel(fx=f, fy=f, cx=(width - 1) / 2.0, cy=(height - 1) / 2.0, width=width, height=height)
    length = 0.24 if long else 0.06
    outline = np.array([[-length / 2, -0.02], [length / 2, -0.02], [length / 2, 0.02], [-length / 2, 0.02]])
    spec = SceneSpec(outline=outline, frames=2, camera=cam, crop_margin_px=10 ** 6, camera_tilt=tilt,
                     camera_height=0.6, height=0.03,
                     distractors=(Distractor.box(0.0, -0.07, 0.05, 0.04, 0.12),
                                  Distractor.cylinder(-0.17, -0.12, 0.03, 0.08, color=(150, 60, 60))))
    scene = Scene(spec)
    fr = list(scene.frames())
    rgb = np.stack([x.rgb for x in fr])
    depth = np.stack([x.depth for x in fr]).astype(np.float64)
    target = np.argwhere(scene.static.object == 1)
    v, u = target[len(target) // 2]
    return rgb, depth, CameraIntrinsics(*scene.intrinsics), (float(u), float(v))


def _segment(rgb, depth, intr, params, half_side, monkeypatch):
    monkeypatch.setattr(seg, 'WINDOW_HALF_SIDE_M', half_side)
    return seg.segment_frames(rgb, depth, intr, params)


def _windowed(monkeypatch, rgb, depth, intr, params):
    """The segmentation and the windows it segmented."""
    seen = []
    real = seg.window

    def spy(*args):
        w = real(*args)
        seen.append(w)
        return w

    monkeypatch.setattr(seg, 'window', spy)
    return _segment(rgb, depth, intr, params, seg.SUPPORT_RADIUS_M, monkeypatch), seen


def test_window_holds_every_pixel_whose_ray_or_column_reaches_the_region():
    rgb, depth, intr, px = _scene(40.0)
    params = SensingParams(target='pixel', target_point=px)
    frames = average_frames(*validate_frames(rgb, depth, intr), params)
    fit, meas = fit_table(frames, intr, params)
    point = target_point(fit, intr, params)
    region = square(point, 0.1)
    win = window(fit, meas, region, params)
    # reference: numpy over all pixels, the column sampled densely
    hit, ok = fit.table.ray_intersection(fit.rays)
    t_xy = fit.table.to_table(hit)[0]
    f_xy = fit.table.to_table(meas.points)[0]
    inside = np.zeros(fit.inlier.shape, bool)
    for s in np.linspace(0.0, 1.0, 201):
        xy = np.where(np.isfinite(meas.height)[..., None], f_xy + s * (t_xy - f_xy), t_xy)
        inside |= ok & (xy[..., 0] >= region[0]) & (xy[..., 0] <= region[2]) & (xy[..., 1] >= region[1]) \
            & (xy[..., 1] <= region[3])
    vv, uu = np.nonzero(inside)
    assert (win.u0, win.v0, win.u1, win.v1) == (uu.min(), vv.min(), uu.max(), vv.max())
    # the tall box beside the target hides table in the region: its top is in the window though its foot is not
    assert win.shape[0] * win.shape[1] < 0.6 * inside.size


@pytest.mark.parametrize('tilt, long', [(0.0, False), (40.0, False), (40.0, True)])
def test_window_gives_the_whole_frames_grid(tilt, long, monkeypatch):
    """The window's segmentation is the whole frame's: the same grid, noise, cells and target pixels, occupancy
    within 0.05; a long target grows the window; the pixel maps cover the whole image."""
    rgb, depth, intr, px = _scene(tilt, long=long)
    params = SensingParams(target='pixel', target_point=px, max_opening_m=0.0)
    frames = average_frames(*validate_frames(rgb, depth, intr), params)
    plane = fit_table(frames, intr, params)[0].table.plane_coefficients()
    params = dataclasses.replace(params, table_plane=plane)
    whole = _segment(rgb, depth, intr, params, 0.0, monkeypatch)
    win, windows = _windowed(monkeypatch, rgb, depth, intr, params)
    assert windows[-1] is not None
    if long:
        assert len(windows) >= 2  # the first window cut the bar
    else:
        assert windows[-1].shape[0] * windows[-1].shape[1] < 0.7 * intr.width * intr.height
    assert win.geometry == whole.geometry
    for name in ('noise_variance', 'missing', 'observed', 'occluded', 'obstacles'):
        assert np.array_equal(getattr(win, name), getattr(whole, name)), name
    # 3-9 cells differ by at most 0.031 here (the window's pixels meet fewer of them: their fill and hidden parts)
    assert np.abs(win.occupancy - whole.occupancy).max() <= 0.05
    assert np.array_equal(win.occupancy >= 0.5, whole.occupancy >= 0.5)
    assert np.array_equal(win.object_mask, whole.object_mask) and win.bbox_px == whole.bbox_px
    assert win.object_mask.shape == whole.object_mask.shape == (intr.height, intr.width)
    w = windows[-1]
    assert whole.window_px is None and win.window_px == (w.u0, w.v0, w.u1, w.v1)
    outside = np.ones(win.object_mask.shape, bool)
    outside[w.slices] = False
    assert not win.depth_mask[outside].any() and not win.labels_px[outside].any()
    assert np.array_equal(win.mean_depth[~np.isnan(win.mean_depth)], whole.mean_depth[~np.isnan(whole.mean_depth)])
