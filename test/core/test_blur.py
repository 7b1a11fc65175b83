"""GPIS-Blur (gpis_grasp_ros.core.blur, section IV) and the figure helpers of gpis_grasp_ros.viz.images."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from gpis_grasp_ros.core.blur import _dilate_any, equalize_uncertain, gpis_blur, zero_crossing_frequency
from gpis_grasp_ros.core.gpis import GpisParams, GpisPosterior, KernelParams, fit_gpis
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.sdf import signed_distance
from gpis_grasp_ros.viz.images import (
    draw_grasp,
    grasp_overlay,
    metric_to_pixel,
    save_gpis_figure,
    to_color,
    upscale,
    write_png,
)

M = 24
RES = 0.005


def _geometry() -> GridGeometry:
    return GridGeometry(-M * RES / 2, -M * RES / 2, RES, M, M, z=0.7)


def _handmade_posterior() -> tuple[GpisPosterior, np.ndarray, np.ndarray, np.ndarray]:
    """Disc SDF as the mean; one shared 1 cm shift of the SDF on a boundary patch (rank-1 covariance)."""
    g = _geometry()
    c = g.cell_centers()
    true = np.hypot(c[..., 0], c[..., 1]) - 0.035
    patch = (c[..., 0] > 0.02) & (np.abs(c[..., 1]) < 0.015) & (np.abs(true) < 0.012)
    factor = np.where(patch, 0.01, 0.0).reshape(-1, 1)
    post = GpisPosterior(geometry=g, mean=true, variance=(factor[:, 0] ** 2).reshape(g.shape),
                         gradient=np.zeros((*g.shape, 2)), cov_factor=factor, params=KernelParams(1e-4, 0.01, -0.01))
    certain_in = (true < -0.015) & (c[..., 0] < 0.0)
    certain_out = true > 0.02
    return post, patch, certain_in, certain_out


def test_certain_object_is_dark_uncertain_is_grey_free_is_light():
    post, patch, certain_in, certain_out = _handmade_posterior()
    img = gpis_blur(post, n_samples=400, rng=np.random.default_rng(0))
    assert img.dtype == np.uint8 and img.shape == post.geometry.shape
    assert img[certain_in].mean() < 5
    assert img[certain_out].min() == 255
    grey = img[patch & (post.mean > -0.004)]  # the patch's boundary cells: inside or outside by chance
    assert 50 < grey.mean() < 205


def test_gpis_posterior_blur_darker_where_certain():
    g = _geometry()
    c = g.cell_centers()
    ang, r = np.arctan2(c[..., 1], c[..., 0]), np.hypot(c[..., 0], c[..., 1])
    sdf = signed_distance(r < 0.035, g.resolution)
    missing = (np.abs(ang) < 0.6) & (r > 0.02)  # the disc's right side is not observed
    post = fit_gpis(sdf, np.full(g.shape, 2.5e-7), ~missing, g,
                    GpisParams(optimize_hyperparameters=False, signal_variance=4e-4, length_scale=0.01))
    img = gpis_blur(post, n_samples=500, rng=np.random.default_rng(1), neighborhood=1, upsample=1)
    certain = (r < 0.025) & (c[..., 0] < 0)
    uncertain = missing & (np.abs(r - 0.035) < 0.01)
    assert np.sqrt(post.variance[uncertain]).mean() > 10 * np.sqrt(post.variance[certain]).mean()
    assert img[certain].mean() + 30 < img[uncertain].mean()


def test_upsampling_shape_and_reproducibility():
    post, *_ = _handmade_posterior()
    a = gpis_blur(post, 200, np.random.default_rng(7), upsample=4)
    b = gpis_blur(post, 200, np.random.default_rng(7), upsample=4)
    assert a.shape == (4 * M, 4 * M) and a.dtype == np.uint8
    assert np.array_equal(a, b)


def test_indicator_is_dilated_object_region():
    post, *_ = _handmade_posterior()
    p0 = zero_crossing_frequency(post, 50, np.random.default_rng(0), neighborhood=0)
    p1 = zero_crossing_frequency(post, 50, np.random.default_rng(0), neighborhood=1)
    certain = ~binary_dilation(post.variance > 0, structure=np.ones((3, 3)))  # no uncertain cell in N(x)
    assert np.array_equal(p0[certain], (post.mean[certain] <= 0).astype(float))
    dilated = binary_dilation(post.mean <= 0, structure=np.ones((3, 3)))
    assert np.array_equal(p1[certain], dilated[certain].astype(float))
    assert np.all(p1 >= p0)


@pytest.mark.parametrize('k', [0, 1, 2])
def test_dilate_any_matches_scipy(k):
    rng = np.random.default_rng(k)
    masks = rng.random((5, 13, 11)) < 0.08
    ours = _dilate_any(masks, k)
    ref = np.stack([binary_dilation(m, structure=np.ones((2 * k + 1, 2 * k + 1))) if k else m for m in masks])
    assert np.array_equal(ours, ref)


def test_equalisation_spreads_greys_and_keeps_extremes():
    img = np.full((10, 10), 255, np.uint8)
    img[:4] = 0
    img[5, :5] = [20, 21, 22, 23, 24]
    out = equalize_uncertain(img)
    assert np.all(out[:4] == 0) and out[9, 9] == 255
    assert list(out[5, :5]) == sorted(out[5, :5]) and out[5, 0] < 60 and out[5, 4] > 200
    # global equalisation would have squashed these greys to black (documented reason)
    assert cv2.equalizeHist(img)[5, 4] < 30


def test_invalid_arguments():
    post, *_ = _handmade_posterior()
    with pytest.raises(ValueError):
        gpis_blur(post, 0)
    with pytest.raises(ValueError):
        gpis_blur(post, 10, neighborhood=-1)
    with pytest.raises(ValueError):
        gpis_blur(post, 10, upsample=0)


# ---------------------------------------------------------------------------------------------- viz

def test_metric_to_pixel_and_upscale():
    g = _geometry()
    centre00 = g.cell_centers()[0, 0]
    assert np.allclose(metric_to_pixel(g, centre00, 10), [5.0, 5.0])
    corner = np.array([g.origin_x + g.size_m[0], g.origin_y])
    assert np.allclose(metric_to_pixel(g, corner, 3), [3 * M, 0.0])
    img = upscale(np.arange(6, dtype=np.uint8).reshape(2, 3), 4)
    assert img.shape == (8, 12) and img[7, 11] == 5 and img[0, 4] == 1
    assert to_color(np.linspace(0, 1, 12).reshape(3, 4)).shape == (3, 4, 3)


def test_draw_grasp_marks_both_jaws_and_the_closing_line():
    g = _geometry()
    scale = 10
    img = np.zeros((M * scale, M * scale, 3), np.uint8)
    j1, j2 = np.array([-0.04, 0.0]), np.array([0.04, 0.0])
    out = draw_grasp(img, g, j1, j2, scale, color=(0, 255, 0), label='GP-G')
    assert out is img
    green = img[..., 1] > 100  # anti-aliased lines
    for jaw in (j1, j2):
        px, py = np.rint(metric_to_pixel(g, jaw, scale) - 0.5).astype(int)
        assert green[py - 5:py + 6, px].sum() >= 8  # jaw bar perpendicular to the (horizontal) closing line
    mid_x, mid_y = np.rint(metric_to_pixel(g, np.zeros(2), scale) - 0.5).astype(int)
    assert green[mid_y - 1:mid_y + 2, mid_x].any()


def test_save_gpis_figure_writes_three_panels(tmp_path):
    post, *_ = _handmade_posterior()
    blur = gpis_blur(post, 100, np.random.default_rng(0), upsample=2)
    path = save_gpis_figure(tmp_path / 'sub' / 'gpis.png', post, blur)
    img = cv2.imread(str(path))
    assert img is not None and img.ndim == 3
    panel = M * round(300 / M)
    assert img.shape[1] == 3 * panel + 2 * 6
    two = cv2.imread(str(save_gpis_figure(tmp_path / 'two.png', post)))
    assert two.shape[1] == 2 * panel + 6


def test_grasp_overlay_and_write_png(tmp_path):
    post, *_ = _handmade_posterior()
    blur = gpis_blur(post, 50, np.random.default_rng(0))
    result = SimpleNamespace(jaw1=np.array([-0.04, 0.0]), jaw2=np.array([0.04, 0.0]), method='GP-G', p_f=0.9)
    rgb = grasp_overlay(blur, post.geometry, [result, (np.array([0.0, -0.04]), np.array([0.0, 0.04]), 'GP-M')],
                        scale=6)
    assert rgb.shape == (M * 6, M * 6, 3) and rgb.dtype == np.uint8
    assert (np.abs(rgb[..., 0].astype(int) - rgb[..., 2].astype(int)) > 100).any()  # coloured grasps drawn
    path = write_png(tmp_path / 'o.png', rgb)
    back = cv2.imread(str(path))
    assert np.array_equal(back[..., ::-1], rgb)  # RGB in, correct colours on disk
    assert write_png(tmp_path / 'g.png', upscale(blur, 2)).exists()
