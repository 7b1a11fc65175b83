"""The compiled morphology (reconstruction, flooding), raster cells and group maxima against the array code they
replace, bit for bit."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gpis_grasp_ros.core.sensing.morphology import _flood, _reconstruct, box_max_at
from gpis_grasp_ros.core.sensing.pixel_kernels import raster_cells
from gpis_grasp_ros.core.sensing.ray_kernels import coarse_to_fine
from gpis_grasp_ros.core.sensing.steps import _group_max


def reference_reconstruct(marker: np.ndarray, mask: np.ndarray) -> np.ndarray:
    kernel = np.ones((3, 3), np.uint8)
    out = np.minimum(marker, mask).astype(np.float32)
    mask = mask.astype(np.float32)
    while True:
        nxt = np.minimum(cv2.dilate(out, kernel), mask)
        if np.array_equal(nxt, out):
            return out
        out = nxt


def reference_flood(markers: np.ndarray, dist: np.ndarray, mask: np.ndarray) -> np.ndarray:
    result = np.zeros(mask.shape, np.int32)
    rows, cols = np.nonzero(mask)
    if rows.size == 0:
        return result
    box = np.s_[max(int(rows.min()) - 1, 0):int(rows.max()) + 2, max(int(cols.min()) - 1, 0):int(cols.max()) + 2]
    markers, dist, mask = markers[box], dist[box], mask[box]
    out = np.where(mask, markers, 0).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    levels = np.unique(np.floor(dist[mask & (markers == 0)] * 2.0) / 2.0)[::-1]
    for level in levels:
        allowed = mask & (dist >= level)
        while True:
            free = allowed & (out == 0)
            grown = cv2.dilate(out, kernel)
            take = free & (grown > 0)
            if not take.any():
                break
            out[take] = grown[take]
    result[box] = out.astype(np.int32)
    return result


def reference_cells(xy, origin, res, shape):
    idx = np.floor((np.asarray(xy) - origin) / res)
    ny, nx = shape
    ok = np.isfinite(idx).all(axis=-1) & (idx[..., 0] >= 0) & (idx[..., 0] < nx) & (idx[..., 1] >= 0) \
        & (idx[..., 1] < ny)
    idx = np.where(ok[..., None], idx, 0).astype(np.int64)
    return idx[..., 0], idx[..., 1], ok


def _blobs(rng: np.random.Generator, h: int, w: int, sigma: float = 3.0) -> np.ndarray:
    img = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), sigma)
    return (img > np.median(img)).astype(np.uint8)


@pytest.mark.parametrize('seed', range(12))
def test_reconstruction_matches_iterated_dilation(seed):
    rng = np.random.default_rng(seed)
    h, w = (int(v) for v in rng.integers(4, 90, 2))
    blobs = _blobs(rng, h, w)
    dist = cv2.distanceTransform(np.pad(blobs, 1), cv2.DIST_L2, 5)[1:-1, 1:-1]
    for neck in (0.5, 1.5, 3.0):  # the h-maxima of a distance transform, as split_touching takes them
        got = _reconstruct(np.maximum(dist - neck, 0.0), dist)
        assert got.dtype == np.float32 and np.array_equal(got, reference_reconstruct(np.maximum(dist - neck, 0.0),
                                                                                      dist))
    noise = rng.random((h, w)).astype(np.float32)  # many regional maxima, ties
    assert np.array_equal(_reconstruct(0.5 * noise, noise), reference_reconstruct(0.5 * noise, noise))
    levels = np.round(4 * noise) / 4
    assert np.array_equal(_reconstruct(levels * 0.5, levels), reference_reconstruct(levels * 0.5, levels))


def test_reconstruction_of_two_peaks_is_the_known_h_dome():
    # a 1-D profile with peaks 3 and 5 joined at a saddle 1: reconstructing (profile - 1) keeps the h-maxima
    profile = np.array([[0, 1, 2, 3, 2, 1, 2, 3, 4, 5, 4, 0]], np.float32)
    got = _reconstruct(profile - 1.0, profile)
    assert got.tolist() == [[0, 1, 2, 2, 2, 1, 2, 3, 4, 4, 4, 0]]


@pytest.mark.parametrize('seed', range(12))
def test_flooding_matches_the_dilation_steps(seed):
    rng = np.random.default_rng(100 + seed)
    h, w = (int(v) for v in rng.integers(4, 90, 2))
    blobs = _blobs(rng, h, w)
    dist = cv2.distanceTransform(np.pad(blobs, 1), cv2.DIST_L2, 5)[1:-1, 1:-1]
    mask = blobs > 0
    markers = np.where((rng.random((h, w)) < 0.02) & mask, rng.integers(1, 7, (h, w)), 0).astype(np.int32)
    got = _flood(markers, dist, mask)
    assert got.dtype == np.int32 and np.array_equal(got, reference_flood(markers, dist, mask))


def test_flooding_splits_two_discs_at_their_neck():
    mask = np.zeros((21, 41), np.uint8)
    cv2.circle(mask, (10, 10), 8, 1, -1)
    cv2.circle(mask, (30, 10), 8, 1, -1)
    mask[9:12, 10:31] = 1
    dist = cv2.distanceTransform(np.pad(mask, 1), cv2.DIST_L2, 5)[1:-1, 1:-1]
    markers = np.zeros(mask.shape, np.int32)
    markers[10, 10], markers[10, 30] = 1, 2
    got = _flood(markers, dist, mask > 0)
    assert (got[mask > 0] > 0).all() and not got[mask == 0].any()
    yy, xx = np.mgrid[:21, :41]
    assert (got[np.hypot(yy - 10, xx - 10) <= 7] == 1).all() and (got[np.hypot(yy - 10, xx - 30) <= 7] == 2).all()
    assert 0.4 < (got == 1).sum() / (got > 0).sum() < 0.6  # the neck is shared


def test_raster_cells_match_the_array_code():
    rng = np.random.default_rng(5)
    xy = rng.uniform(-0.05, 0.35, size=(40, 30, 2))
    xy[rng.random((40, 30)) < 0.1] = np.nan
    xy[0, 0, 0] = np.inf
    xy[0, 1] = [0.1, 0.2]  # on a cell edge
    origin = np.array([0.0, 0.02])
    for res in (0.01, 0.0033):
        for got, want in zip(raster_cells(xy, origin, res, (50, 20)), reference_cells(xy, origin, res, (50, 20)),
                             strict=True):
            assert got.dtype == want.dtype and np.array_equal(got, want)


def test_raster_cells_of_a_part_of_the_lattice_are_the_whole_rasters_shifted():
    rng = np.random.default_rng(6)
    xy = rng.uniform(-0.05, 0.35, size=(60, 2))
    xy[:5] = np.round(xy[:5] / 0.01) * 0.01  # on cell edges
    origin = np.array([0.0, 0.02])
    ix, iy, ok = raster_cells(xy, origin, 0.01, (50, 20))
    for first, shape in (((3, 7), (20, 11)), ((0, 0), (50, 20)), ((12, 2), (1, 1))):
        sx, sy, sok = raster_cells(xy, origin, 0.01, shape, first)
        inside = ok & (ix >= first[0]) & (ix < first[0] + shape[1]) & (iy >= first[1]) & (iy < first[1] + shape[0])
        assert np.array_equal(sok, inside)
        assert np.array_equal(sx[sok], ix[sok] - first[0]) and np.array_equal(sy[sok], iy[sok] - first[1])


def test_group_max_matches_maximum_at():
    rng = np.random.default_rng(9)
    keys = rng.integers(0, 17, 500)
    values = rng.random(500).astype(np.float32)
    want = np.zeros(20)
    np.maximum.at(want, keys, values)
    assert np.array_equal(_group_max(keys, values, 20), want)


@pytest.mark.parametrize('n', [0, 1, 2, 3, 7, 16, 62])
def test_coarse_to_fine_visits_every_sample_once_middle_first(n):
    order = coarse_to_fine(n)
    assert sorted(order.tolist()) == list(range(n))
    if n >= 3:
        assert order[0] == (n - 1) // 2
        assert {int(order[1]), int(order[2])} == {((n - 1) // 2 - 1) // 2, ((n - 1) // 2 + 1 + n - 1) // 2}


@pytest.mark.parametrize('shape', [(31, 47), (1, 9), (8, 1)])
def test_grid_components_number_as_scipy(shape):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from gpis_grasp_ros.core.sensing.morphology import grid_components

    rng = np.random.default_rng(shape[0])
    ny, nx = shape
    for p in (0.3, 0.6, 0.9):
        right, down = rng.random((ny, nx - 1)) < p, rng.random((ny - 1, nx)) < p
        idx = np.arange(ny * nx).reshape(ny, nx)
        r = np.concatenate([idx[:, :-1][right], idx[:-1, :][down]])
        c = np.concatenate([idx[:, 1:][right], idx[1:, :][down]])
        _, want = connected_components(coo_matrix((np.ones(r.size), (r, c)), shape=(ny * nx, ny * nx)), directed=False)
        got = grid_components(right, down)
        assert got.dtype == want.dtype and np.array_equal(got.ravel(), want)


@pytest.mark.parametrize('seed', range(6))
def test_box_max_at_is_the_whole_image_dilation_read_at_the_pixels(seed):
    """The k x k maximum computed on the box of the asked pixels' windows equals the whole image's dilation there,
    at the image's edges too."""
    rng = np.random.default_rng(seed)
    h, w = rng.integers(5, 60, 2)
    image = rng.standard_normal((h, w)).astype(np.float32)
    k = int(rng.choice([3, 5, 9, 21]))
    n = int(rng.integers(0, 12))
    rows, cols = rng.integers(0, h, n), rng.integers(0, w, n)
    if seed == 0:  # the corners
        rows, cols = np.array([0, 0, h - 1, h - 1]), np.array([0, w - 1, 0, w - 1])
    whole = cv2.dilate(image, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
    assert np.array_equal(box_max_at(image, rows, cols, k), whole[rows, cols])
