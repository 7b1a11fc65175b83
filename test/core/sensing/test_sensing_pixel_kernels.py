"""The per-pixel passes and the column drawing against the array code they replace, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from gpis_grasp_ros.core.median import median
from gpis_grasp_ros.core.sensing.pixel_kernels import (
    all_finite,
    distinct_cells_per_label,
    has_label,
    mask_bounds,
    masked_rows,
    max_tangent,
    nan_to_num,
    nearer_difference_area,
    norm_of,
    pixel_feet,
    ray_cosine,
    vector_norm,
)
from gpis_grasp_ros.core.sensing.ray_kernels import draw_columns


def _awkward(rng: np.random.Generator, shape: tuple[int, ...], dtype=np.float64) -> np.ndarray:
    """Values over many magnitudes (additions that round differently in another order), with NaN and inf."""
    x = (rng.standard_normal(shape) * np.exp(rng.uniform(-30, 30, shape))).astype(dtype)
    x.ravel()[rng.choice(x.size, x.size // 50, replace=False)] = np.nan
    x.ravel()[rng.choice(x.size, x.size // 100, replace=False)] = np.inf
    return x


@pytest.mark.parametrize('dtype', [np.float64, np.float32])
@pytest.mark.parametrize('k', [2, 3])
def test_vector_norm_and_all_finite_equal_numpy(dtype, k):
    x = _awkward(np.random.default_rng(k), (97, 131, k), dtype)
    got, want = vector_norm(x), np.linalg.norm(x, axis=-1)
    assert got.dtype == want.dtype and np.array_equal(got, want, equal_nan=True)
    assert np.array_equal(all_finite(x), np.isfinite(x).all(axis=-1))
    y = _awkward(np.random.default_rng(k + 10), (k,), dtype)
    want = np.linalg.norm(x - y, axis=-1)
    got = norm_of([x[..., i] - y[i] for i in range(k)])
    assert got.dtype == want.dtype and np.array_equal(got, want, equal_nan=True)
    mask = np.random.default_rng(k).random(x.shape[:2]) < 0.4
    assert np.array_equal(masked_rows(x, mask), x[mask], equal_nan=True)


@pytest.mark.parametrize('dtype', [np.float64, np.float32])
@pytest.mark.parametrize('nan', [0.0, 1.0, np.inf, -np.inf])
def test_nan_to_num_equals_numpy(dtype, nan):
    x = _awkward(np.random.default_rng(7), (53, 71), dtype)
    x.ravel()[::37] = -np.inf
    x.ravel()[::41] = -0.0
    for arr in (x, x[:, ::2], x[5]):
        got, want = nan_to_num(arr, nan=nan), np.nan_to_num(arr, nan=nan)
        assert got.dtype == want.dtype and got.shape == want.shape
        assert np.array_equal(got.view(np.uint8), np.ascontiguousarray(want).view(np.uint8))  # -0.0 kept too
    assert nan_to_num(x[3, 4]) == np.nan_to_num(x[3, 4])
    ints = np.arange(12).reshape(3, 4)
    assert np.array_equal(nan_to_num(ints), ints)


def test_masked_rows_of_other_dtypes_and_empty_masks():
    rng = np.random.default_rng(8)
    x = rng.integers(0, 255, (40, 30, 3)).astype(np.uint8)
    mask = rng.random((40, 30)) < 0.3
    got = masked_rows(x, mask)
    assert got.dtype == np.uint8 and np.array_equal(got, x[mask])
    assert masked_rows(x, np.zeros((40, 30), bool)).shape == (0, 3)
    y = rng.standard_normal((40, 30, 3))[:, ::-1]  # not contiguous
    assert np.array_equal(masked_rows(y, mask), y[mask])


def _nearer_difference(xy: np.ndarray, axis: int) -> np.ndarray:
    """The array code of the nearer one-sided differences (rasterise's table area weights)."""
    d = np.diff(xy, axis=axis)
    pad = [(0, 0)] * 3
    pad[axis] = (1, 0)
    back = np.pad(d, pad, constant_values=np.nan)
    pad[axis] = (0, 1)
    fwd = np.pad(d, pad, constant_values=np.nan)
    n_back = np.nan_to_num(back[..., 0] ** 2 + back[..., 1] ** 2, nan=np.inf)
    n_fwd = np.nan_to_num(fwd[..., 0] ** 2 + fwd[..., 1] ** 2, nan=np.inf)
    return np.where((n_back <= n_fwd)[..., None], back, fwd)


def test_nearer_difference_area_equals_the_array_code():
    rng = np.random.default_rng(9)
    xy = np.stack(np.meshgrid(np.linspace(-0.2, 0.2, 83), np.linspace(0.1, 0.5, 61)), axis=-1)
    xy = (xy + rng.normal(0.0, 1e-3, xy.shape)).astype(np.float32).astype(np.float64)
    xy[rng.random(xy.shape[:2]) < 0.05] = np.nan
    xy[rng.random(xy.shape[:2]) < 0.01, 1] = np.nan
    xy[rng.random(xy.shape[:2]) < 0.01, 0] = 1e200  # squared lengths that overflow
    xy[5, 7] = xy[5, 6] + (xy[5, 8] - xy[5, 7])  # ties
    with np.errstate(invalid='ignore', over='ignore'):
        a, b = _nearer_difference(xy, 1), _nearer_difference(xy, 0)
        want = np.abs(a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0])
        got = nearer_difference_area(xy)
    assert np.array_equal(got, want, equal_nan=True)


def test_distinct_cells_per_label_equals_unique():
    rng = np.random.default_rng(10)
    n_cells, n_labels = 500, 9
    cells = rng.integers(0, n_cells, 3000)
    owner = rng.integers(1, n_labels - 2, n_cells)
    for labels in (owner[cells], rng.integers(1, n_labels, 3000)):  # one label per cell, and shared cells
        want = np.bincount(np.unique(labels * n_cells + cells) // n_cells, minlength=n_labels)
        got = distinct_cells_per_label(labels, cells, n_cells, n_labels)
        assert got.dtype == want.dtype and np.array_equal(got, want)
    assert np.array_equal(distinct_cells_per_label(np.zeros(0, int), np.zeros(0, int), n_cells, n_labels),
                          np.zeros(n_labels, int))


def test_pixel_feet_and_max_tangent_equal_the_array_code():
    rng = np.random.default_rng(3)
    h, w = 60, 80
    rays = np.stack([*np.meshgrid(rng.uniform(-0.6, 0.6, w), rng.uniform(-0.5, 0.5, h)), np.ones((h, w))], axis=-1)
    normal = np.array([0.1, -0.6, -0.79])
    normal /= np.linalg.norm(normal)
    ray_dot = rays @ normal
    hit = ray_dot < -1e-9
    points = rays * rng.uniform(0.3, 1.2, (h, w, 1))
    height = _awkward(rng, (h, w))
    h_missing = np.where(rng.random((h, w)) < 0.5, 0.0, rng.uniform(0.0, 0.1, (h, w)))
    valid = rng.random((h, w)) < 0.6
    offset = 0.7
    with np.errstate(invalid='ignore', divide='ignore', over='ignore'):
        t_missing = np.where(hit, (h_missing - offset) / np.where(hit, ray_dot, -1.0), np.nan)
        missing_points = rays * t_missing[..., None] - h_missing[..., None] * normal
        want = np.where(valid[..., None], points - np.nan_to_num(height)[..., None] * normal, missing_points)
        got = pixel_feet(rays, ray_dot, points, height, h_missing, valid, hit, normal, offset)
    assert np.array_equal(got, want, equal_nan=True)
    ray_cos = np.maximum(np.abs(ray_dot) / np.linalg.norm(rays, axis=-1), 1e-3)
    odd = ray_dot.copy()
    odd.ravel()[::13] = np.nan
    odd.ravel()[::19] = 1e-9  # below the floor
    assert np.array_equal(ray_cosine(rays, odd), np.maximum(np.abs(odd) / np.linalg.norm(rays, axis=-1), 1e-3),
                          equal_nan=True)
    assert np.array_equal(ray_cosine(rays, ray_dot), ray_cos)
    ray_cos.ravel()[::17] = np.nan
    ray_cos.ravel()[::23] = 1.5  # 1 - cos^2 < 0
    assert max_tangent(ray_cos) == float(np.nanmax(np.sqrt(np.maximum(1.0 - ray_cos ** 2, 0.0)) / ray_cos))


@pytest.mark.parametrize('include_point', [False, True])
def test_draw_columns_equals_the_array_code(include_point):
    rng = np.random.default_rng(5)
    cam = np.array([600.0, 610.0, 64.3, 47.8])
    rows, cols = 96, 128
    normal = np.array([0.0, -0.5, -np.sqrt(0.75)])
    n_col = 400
    foot = np.stack([rng.uniform(-0.15, 0.15, n_col), rng.uniform(-0.1, 0.1, n_col), rng.uniform(0.5, 0.8, n_col)],
                    axis=1)
    h = rng.uniform(0.0, 0.12, n_col)
    n = rng.integers(2, 40, n_col)
    want = np.full((rows, cols), np.inf)
    for i in range(n_col):
        k = np.arange(n[i])
        s = (k / (n[i] - 1 if include_point else n[i])) * h[i]
        p = foot[i] + s[:, None] * normal
        u, v = np.rint(cam[2] + cam[0] * p[:, 0] / p[:, 2]), np.rint(cam[3] + cam[1] * p[:, 1] / p[:, 2])
        ok = (p[:, 2] > 0) & (u >= 0) & (u < cols) & (v >= 0) & (v < rows)
        np.minimum.at(want, (v[ok].astype(np.int64), u[ok].astype(np.int64)), p[ok, 2])
    got = np.full((rows, cols), np.inf)
    draw_columns(foot, h, n, normal, include_point, cam, got, 0, 0, True)
    assert np.array_equal(got, want)
    shifted = np.full((rows, cols), np.inf)  # a buffer over other pixels (u0, v0) = (10, -5)
    draw_columns(foot, h, n, normal, include_point, cam, shifted, 10, -5, False)
    assert np.array_equal(shifted[5:, :cols - 10], want[:rows - 5, 10:])


def test_mask_bounds_are_the_extremes_of_nonzero():
    rng = np.random.default_rng(11)
    for density in (0.3, 0.001):
        mask = rng.random((70, 90)) < density
        mask[rng.integers(70), rng.integers(90)] = True
        vs, us = np.nonzero(mask)
        assert mask_bounds(mask) == (vs.min(), vs.max(), us.min(), us.max())
    with pytest.raises(ValueError):
        mask_bounds(np.zeros((4, 5), bool))


@pytest.mark.parametrize('dtype', [np.float32, np.float64])
@pytest.mark.parametrize('n', [5000, 5001, 70001])
def test_median_equals_numpy(dtype, n):
    rng = np.random.default_rng(n)
    cases = [rng.normal(0.3, 0.01, n), rng.exponential(1.0, n) * np.exp(rng.uniform(-30, 30, n)),
             np.round(rng.normal(5.0, 2.0, n)),  # ties
             np.concatenate([np.full(n - 10, 0.7), rng.normal(0.7, 1e-3, 10)]),  # one value nearly everywhere
             np.concatenate([rng.normal(0.0, 1.0, n - 2), [-1e308, 1e308]]),  # a range that overflows
             np.where(rng.random(n) < 0.3, 0.0, rng.normal(0.0, 1.0, n))]  # zeros
    signed = cases[-1].copy()
    signed[::7] = -0.0
    with_nan = cases[0].copy()
    with_nan[3] = np.nan
    for x in [*cases, signed, with_nan, np.full(n, 2.5)]:
        with np.errstate(over='ignore'):
            x = x.astype(dtype)
        got, want = median(x), np.median(x)
        assert type(got) is type(want) and np.asarray(got).tobytes() == np.asarray(want).tobytes()


def test_has_label_equals_isin():
    rng = np.random.default_rng(14)
    labels = rng.integers(0, 40, (30, 50)).astype(np.int32)
    for wanted in (np.array([3, 7, 39]), np.array([0, 55]), np.zeros(0, np.int64), np.arange(40)):
        assert np.array_equal(has_label(labels, wanted), np.isin(labels, wanted))
