"""Evidence stage (core.sensing.evidence): the shadow line and the inverse-variance combination."""

from __future__ import annotations

import numpy as np
import pytest

from gpis_grasp_ros.core.sensing import SensingParams, shadow_line_distance
from gpis_grasp_ros.core.sensing.evidence import Evidence, combine


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
