"""Evidence stage (core.sensing.evidence): the shadow line, the chromaticity distance and the inverse-variance
combination."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gpis_grasp_ros.core.sensing import SensingParams, shadow_line_distance
from gpis_grasp_ros.core.sensing.chroma import chromaticity_distance
from gpis_grasp_ros.core.sensing.evidence import Evidence, combine
from gpis_grasp_ros.core.sensing.params import CHROMA_MIN_SIGMA


def test_shadow_line_distance_is_analytic():
    t = np.array([100.0, 80.0, 60.0])
    colours = np.stack([0.4 * t, t, 1.5 * t, t + np.array([0.0, 0.0, 30.0])])
    dist, ratio = shadow_line_distance(colours, t)
    assert dist[0] == pytest.approx(0.0, abs=1e-9) and ratio[0] == pytest.approx(0.4)  # a shadow
    assert dist[1] == pytest.approx(0.0, abs=1e-9)
    assert dist[2] == pytest.approx(0.5 * np.linalg.norm(t))  # brighter: measured from t itself
    off = t + np.array([0.0, 0.0, 30.0])  # a tint: its distance from the line through t
    a = off @ t / (t @ t)
    assert dist[3] == pytest.approx(np.linalg.norm(off - min(a, 1.0) * t))


def test_combination_trusts_depth_and_makes_missing_object():
    params = SensingParams()
    p_d = np.array([1.0, 0.0, 0.5, 0.2])
    p_c = np.array([1.0, 1.0, 0.5, 0.9])
    missing = np.array([False, False, False, True])
    occ, rho = combine(Evidence(p_d, p_c, None), missing, params)
    v_d, v_c = params.depth_floor_variance, params.color_floor_variance
    assert occ[0] == pytest.approx(1.0)
    assert occ[1] == pytest.approx((1.0 / v_c) / (1.0 / v_d + 1.0 / v_c))  # colour only: below 1/2
    assert occ[1] < 0.5 and occ[2] == pytest.approx(0.5)
    assert occ[3] == 1.0 and rho[3] == 0.0  # missing = object, no disagreement
    assert np.allclose(rho[:3], np.abs(p_d - p_c)[:3])


def _chromaticity_reference(rgb, train, smooth_px=1.5, dark=20.0):
    """The array code of :func:`chromaticity_distance`."""
    img = np.asarray(rgb, dtype=np.float32)
    if smooth_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), smooth_px, borderType=cv2.BORDER_REPLICATE)
    total = img[..., 0] + img[..., 1] + img[..., 2]
    chroma = img / np.maximum(total, 1e-3)[..., None]
    samples = chroma[train]
    if samples.shape[0] < 20:
        return np.zeros(total.shape), 0.0, 1.0
    c_table = np.median(samples, axis=0)
    dist = np.linalg.norm(chroma - c_table, axis=-1)
    med = float(np.median(dist[train]))
    scale = max(CHROMA_MIN_SIGMA, 1.4826 * float(np.median(np.abs(dist[train] - med))))
    spread = scale * np.sqrt(np.maximum(1.0, float(np.median(total[train])) / np.maximum(total, 1e-3)))
    z = np.where(total / 3.0 >= dark, (dist - med) / spread, 0.0)
    return z.astype(np.float64), med, scale


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_chromaticity_distance_and_shadow_line_equal_the_array_code(seed):
    rng = np.random.default_rng(seed)
    h, w = 67 + seed, 91
    img = rng.uniform(0.0, 255.0, (h, w, 3))
    img[rng.random((h, w)) < 0.2] = rng.uniform(0.0, 30.0, 3)  # dark pixels
    img[rng.random((h, w)) < 0.05] = 0.0  # black: brightness below the floor
    img[: h // 2, : w // 2] = [120.0, 100.0, 90.0] + rng.normal(0.0, 3.0, (h // 2, w // 2, 3))  # a table
    train = rng.random((h, w)) < 0.5
    for smooth, dark in ((1.5, 20.0), (0.0, 20.1), (2.0, 7.3)):
        got, want = chromaticity_distance(img, train, smooth, dark), _chromaticity_reference(img, train, smooth, dark)
        assert got[1:] == want[1:] and got[0].dtype == want[0].dtype
        assert np.array_equal(got[0], want[0], equal_nan=True)
    small = np.zeros((h, w), bool)
    small[0, :10] = True
    assert np.array_equal(chromaticity_distance(img, small)[0], np.zeros((h, w)))
    t = np.median(img[train], axis=0)
    dist, ratio = shadow_line_distance(img, t)
    want_ratio = (img @ t) / float(t @ t)
    alpha = np.clip(want_ratio, 0.0, 1.0)
    assert np.array_equal(ratio, want_ratio)
    assert np.array_equal(dist, np.linalg.norm(img - alpha[..., None] * t, axis=-1))


@pytest.mark.parametrize('floors', [(0.01, 0.04), (1e-300, 1e-12)])
def test_combination_equals_the_array_code(floors):
    from dataclasses import replace

    rng = np.random.default_rng(15)
    p_d, p_c = rng.random((40, 60)), rng.random((40, 60))
    p_d[::7, ::3], p_c[::5, ::4], p_d[1, 1], p_c[2, 2] = 0.0, 1.0, np.nan, np.nan
    missing = rng.random((40, 60)) < 0.2
    params = replace(SensingParams(), depth_floor_variance=floors[0], color_floor_variance=floors[1])
    with np.errstate(invalid='ignore', divide='ignore'):
        v_d = p_d * (1.0 - p_d) + params.depth_floor_variance
        v_c = p_c * (1.0 - p_c) + params.color_floor_variance
        occ = np.where(missing, 1.0, (p_d / v_d + p_c / v_c) / (1.0 / v_d + 1.0 / v_c))
    rho = np.where(missing, 0.0, np.abs(p_d - p_c))
    got = combine(Evidence(p_d, p_c, None), missing, params)
    assert np.array_equal(got[0], occ, equal_nan=True) and np.array_equal(got[1], rho, equal_nan=True)
