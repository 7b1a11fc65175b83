"""The compiled loops of the occlusion stage (core.sensing.ray_kernels) against the array code they replace.

The references below are that array code: every sample of every column (or ray) is made as a temporary
array, projected with ``CameraIntrinsics.pixel_index`` and reduced with ``np.minimum.at`` (or a first-true
search). The compiled loops must give the same numbers, bit for bit, on tilted scenes with boxes."""

from __future__ import annotations

import numpy as np
import pytest

from gpis_grasp_ros.core.noise_model import SensorModel
from gpis_grasp_ros.core.sensing.camera import CameraIntrinsics
from gpis_grasp_ros.core.sensing.clear_body import prism_footprint
from gpis_grasp_ros.core.sensing.occlusion import column_zbuffer, see_through_pixels
from gpis_grasp_ros.core.sensing.ray_kernels import camera_vector, grid_point, prism_heights, under_seen_surface
from gpis_grasp_ros.core.table_frame import TableFrame
from support.tilted_scene import Box, TiltedScene

D435 = SensorModel.named('realsense_d400')
BOXES = [Box(0.0, 0.0, 0.03, 0.02, 0.06), Box(0.07, 0.03, 0.015, 0.04, 0.03)]


def _samples(foot, h, n, normal, include_point):
    column = np.repeat(np.arange(foot.shape[0]), n)
    ends = np.cumsum(n)
    k = np.arange(column.size) - (ends[column] - n[column])
    frac = k / (n[column] - 1) if include_point else k / n[column]
    return foot[column] + (frac * h[column])[:, None] * normal


def _entry_reference(points, height, solid, table, intr, max_samples=64):
    entry = np.full(height.shape, np.inf)
    top = points[solid]
    h = np.nan_to_num(height[solid])
    foot = top - h[:, None] * table.n
    span = np.linalg.norm(intr.project(top) - intr.project(foot), axis=-1)
    n = np.clip(np.ceil(np.nan_to_num(span)).astype(np.int64) + 1, 1, max_samples)
    samples = _samples(foot, h, n, table.n, False)
    u, v, inside = intr.pixel_index(samples)
    np.minimum.at(entry, (v[inside], u[inside]), samples[inside, 2])
    return entry


def _zbuffer_reference(top, h, table, intr, origin, bounds, max_samples=64):
    u0, v0, u1, v1 = bounds
    zbuf = np.full((v1 - v0 + 1, u1 - u0 + 1), np.inf)
    foot = top - h[:, None] * table.n - origin
    top = top - origin
    uv_top, uv_foot = intr.project(top), intr.project(foot)
    n = np.clip(np.ceil(np.linalg.norm(uv_top - uv_foot, axis=-1)).astype(np.int64) + 1, 2, max_samples)
    samples = _samples(foot, h, n, table.n, True)
    uv = np.round(intr.project(samples)).astype(np.int64) - np.array([u0, v0])
    keep = (uv[:, 0] >= 0) & (uv[:, 0] < zbuf.shape[1]) & (uv[:, 1] >= 0) & (uv[:, 1] < zbuf.shape[0])
    np.minimum.at(zbuf, (uv[keep, 1], uv[keep, 0]), samples[keep, 2])
    return zbuf


def _prism_reference(ray, ray_n, top_h, table, fractions, inner, intr, obj):
    def on_object(points):
        u, v, inside = intr.pixel_index(points)
        return inside & obj[v, u]

    lift = top_h[:, None] * table.n
    h_k = top_h[:, None] * fractions[None, :]
    foot = ray[:, None, :] * ((h_k - table.offset_m) / ray_n[:, None])[..., None] - h_k[..., None] * table.n
    under = on_object(foot) & on_object(foot + lift[:, None, :])
    for f in inner:
        under &= on_object(foot + f * lift[:, None, :])
    done = under.any(axis=1)
    return np.where(done, h_k[np.arange(ray.shape[0]), np.argmax(under, axis=1)], 0.0)


def _footprint_reference(cells_xy, silhouette, table, intr, height_m, step_m=0.003):
    import cv2
    sil = cv2.dilate(silhouette.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    base = table.to_camera(cells_xy)
    under = np.ones(base.shape[:-1], dtype=bool)
    for h in np.linspace(0.0, height_m, max(2, int(np.ceil(height_m / step_m)) + 1)):
        u, v, inside = intr.pixel_index(base + h * table.n)
        under &= inside & sil[v, u]
    return under


def _scene(tilt):
    scene = TiltedScene(tilt, boxes=BOXES)
    _, depth, _ = scene.frames(1, seed=0, model=D435)
    table = TableFrame.from_plane(*scene.normal, scene.offset)
    points = scene.intrinsics.rays() * depth[0][..., None]
    height = points @ table.n + table.offset_m
    return scene.intrinsics, table, points, height, np.isfinite(height) & (height > 0.005)


@pytest.mark.parametrize('tilt', [0.0, 30.0, 50.0])
def test_see_through_entry_depths_equal_the_array_code(tilt):
    intr, table, points, height, solid = _scene(tilt)
    _, entry = see_through_pixels(points, height, solid, points[..., 2], table, intr, D435)
    assert solid.sum() > 1000 and np.isfinite(entry).sum() > 1000
    assert np.array_equal(entry, _entry_reference(points, height, solid, table, intr))


@pytest.mark.parametrize('tilt', [30.0, 50.0])
def test_column_zbuffer_equals_the_array_code(tilt):
    intr, table, points, height, solid = _scene(tilt)
    origin = np.array([0.05, 0.0, 0.0])
    top, h = points[solid], height[solid]
    bounds = (-40, -10, intr.width + 20, intr.height + 5)  # reaching past the image, as a viewpoint aside does
    zbuf = column_zbuffer(top, h, table, intr, origin, bounds)
    assert np.isfinite(zbuf).sum() > 1000
    assert np.array_equal(zbuf, _zbuffer_reference(top, h, table, intr, origin, bounds))


@pytest.mark.parametrize('tilt', [0.0, 30.0, 50.0])
def test_prism_heights_equal_the_array_code(tilt):
    intr, table, points, height, solid = _scene(tilt)
    rng = np.random.default_rng(1)
    vs, us = np.nonzero(np.ones(solid.shape, bool))
    on_vs, on_us = np.nonzero(solid)
    pick, on = rng.choice(vs.size, 2000, replace=False), rng.choice(on_vs.size, 1000, replace=False)
    ray = intr.rays()[np.r_[vs[pick], on_vs[on]], np.r_[us[pick], on_us[on]]]  # anywhere, and on the boxes
    top_h = rng.uniform(0.0, 0.07, ray.shape[0])
    ray_n = ray @ table.n
    fractions, inner = np.linspace(1.0, 0.0, 24)[:-1], np.linspace(0.0, 1.0, 9)[1:-1]
    got = prism_heights(ray, ray_n, top_h, table.n, float(table.offset_m), fractions, inner, camera_vector(intr), solid)
    assert (got > 0).sum() > 100 and (got == 0).sum() > 100
    assert np.array_equal(got, _prism_reference(ray, ray_n, top_h, table, fractions, inner, intr, solid))


@pytest.mark.parametrize('tilt', [0.0, 30.0, 50.0])
def test_prism_footprint_equals_the_array_code(tilt):
    intr, table, points, height, solid = _scene(tilt)
    xy = table.to_table(points[solid])[0]
    lo, hi = xy.min(axis=0) - 0.01, xy.max(axis=0) + 0.01
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], 0.002), np.arange(lo[1], hi[1], 0.002))
    cells = np.stack([gx, gy], axis=-1)
    for h in (0.0, 0.02, 0.05):
        got = prism_footprint(cells, solid, table, intr, h)
        assert got.shape == gx.shape and got.sum() > 50
        assert np.array_equal(got, _footprint_reference(cells, solid, table, intr, h))


def _grid_points(xy, h, rot, z0):
    """``ray_kernels.grid_point`` as array code: (N, 2) grid points at height h -> (N, 3) sensor points."""
    x, y = xy[:, 0], xy[:, 1]
    lz = z0 - h
    return np.stack([x * rot[0, 0] + y * rot[0, 1] + lz * rot[0, 2],
                     x * rot[1, 0] + y * rot[1, 1] + lz * rot[1, 2],
                     x * rot[2, 0] + y * rot[2, 1] + lz * rot[2, 2]], axis=-1)


def _under_reference(pts, heights, intr, foot_xy, above, tol, points_of):
    """The array march the compiled loop replaced: every remaining point projected at each height in turn."""
    under = np.zeros(pts.shape[0], dtype=bool)
    for h in heights:
        rest = np.flatnonzero(~under)
        if rest.size == 0:
            break
        u, v, inside = intr.pixel_index(points_of(pts[rest], float(h)))
        with np.errstate(invalid='ignore'):
            near = np.linalg.norm(foot_xy[v, u] - pts[rest], axis=-1) <= tol
        under[rest[inside & above[v, u] & near]] = True
    return under


@pytest.mark.parametrize('tilt', [0.0, 30.0, 50.0])
def test_under_seen_surface_equals_the_array_march(tilt):
    intr, table, points, height, solid = _scene(tilt)
    foot = points - np.nan_to_num(height)[..., None] * table.n
    xy = table.to_table(points[solid])[0]
    lo = xy.min(axis=0) - 0.03
    res = 0.0015
    n = int(np.ceil((xy.max(axis=0) - lo + 0.03).max() / res))
    geometry = table.grid(float(lo[0]), float(lo[1]), res, n, n)
    foot_xy = np.where(solid[..., None], geometry.from_sensor(foot)[0], np.nan)  # feet of the seen surfaces
    pts = geometry.cell_centers().reshape(-1, 2)
    heights = np.linspace(0.0, float(np.nanmax(height[solid])), 40)
    tol = 0.002
    got = under_seen_surface(np.ascontiguousarray(pts), heights, geometry.rotation_matrix, float(geometry.z),
                             camera_vector(intr), np.ascontiguousarray(foot_xy), solid, tol)
    rot, z0 = geometry.rotation_matrix, float(geometry.z)
    assert got.sum() > 200 and (~got).sum() > 200
    assert np.array_equal(got, _under_reference(pts, heights, intr, foot_xy, solid, tol,
                                                lambda q, h: _grid_points(q, h, rot, z0)))
    # and the grid's own placement (a BLAS product, rounded otherwise in the last bit) finds the same points
    assert np.array_equal(got, _under_reference(pts, heights, intr, foot_xy, solid, tol, geometry.to_sensor))


def test_grid_point_places_points_as_the_grid_does():
    g = TableFrame.from_plane(0.1, -0.5, -0.86, 0.6).grid(-0.05, -0.04, 0.002, 50, 40)
    xy = np.random.default_rng(3).uniform(-0.05, 0.05, (500, 2))
    rot, z0 = g.rotation_matrix, float(g.z)
    got = np.array([grid_point(float(x), float(y), 0.03, rot, z0) for x, y in xy])
    np.testing.assert_allclose(got, g.to_sensor(xy, 0.03), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(got, _grid_points(xy, 0.03, rot, z0))  # the array reference, bit for bit


def test_a_ray_leaving_the_image_is_under_no_prism():
    intr = CameraIntrinsics(100.0, 100.0, 9.5, 9.5, 20, 20)
    table = TableFrame.from_plane(0.0, 0.0, -1.0, 0.5)
    obj = np.ones((20, 20), bool)
    ray = np.array([[0.0, 0.0, 1.0], [0.09, 0.0, 1.0], [0.11, 0.0, 1.0]])  # centre, last column, beyond it
    got = prism_heights(ray, ray @ table.n, np.full(3, 0.05), table.n, 0.5, np.linspace(1.0, 0.0, 5)[:-1],
                        np.zeros(0), camera_vector(intr), obj)
    assert got.tolist() == [0.05, 0.05, 0.0]
