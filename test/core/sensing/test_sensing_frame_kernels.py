"""The compiled frame averaging and effective frame count against the array code they replace (bit for bit)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from gpis_grasp_ros.core.noise_model import SensorModel, distinct_frames, effective_frame_count
from gpis_grasp_ros.core.sensing import SensingParams
from gpis_grasp_ros.core.sensing.camera import average_frames

D400 = SensorModel.named('realsense_d400')


def reference_distinct(frames: np.ndarray) -> np.ndarray:
    keep: list[int] = []
    for i in range(frames.shape[0]):
        if not any(np.array_equal(frames[i], frames[j], equal_nan=True) for j in keep):
            keep.append(i)
    return np.asarray(keep, dtype=np.int64)


def reference_effective_frame_count(depth_frames: np.ndarray, model: SensorModel, min_pixels: int = 50) -> float:
    """The array code: exact repeats removed, median temporal variance over the pixels valid in all frames."""
    frames = np.asarray(depth_frames, dtype=np.float64)
    frames = np.where(np.isfinite(frames) & (frames > 0), frames, np.nan)
    idx = reference_distinct(frames)
    n = int(idx.size)
    if n <= 1:
        return 1.0
    sub = frames[idx]
    ok = np.all(np.isfinite(sub) & (sub > 0), axis=0)
    if int(ok.sum()) < min_pixels:
        return float(n)
    values = sub[:, ok]
    s2 = values.var(axis=0, ddof=1)
    model_var = model.variance(values.mean(axis=0))
    unbias = float(chi2.ppf(0.5, n - 1) / (n - 1))
    ratio = float(np.median(s2) / unbias / max(float(np.median(model_var)), 1e-18))
    return float(1.0 + (n - 1) * min(1.0, ratio))


def reference_average(depth_in: np.ndarray, min_valid: int) -> tuple[np.ndarray, np.ndarray]:
    depth = depth_in.astype(np.float64)
    valid_f = np.isfinite(depth) & (depth > 0)
    count = valid_f.sum(axis=0)
    valid = count >= max(1, min_valid)
    with np.errstate(invalid='ignore', divide='ignore'):
        z_mean = np.where(valid, np.where(valid_f, depth, 0.0).sum(axis=0) / np.maximum(count, 1), np.nan)
    return count, z_mean


def _frames(rng: np.random.Generator, n: int, h: int = 37, w: int = 53, sigma: float = 0.003) -> np.ndarray:
    base = rng.uniform(0.5, 1.2, size=(h, w))
    frames = base + sigma * rng.standard_normal((n, h, w))
    drop = rng.random((n, h, w))
    frames[drop < 0.05] = np.nan
    frames[(drop >= 0.05) & (drop < 0.08)] = 0.0  # another encoding of no return
    frames[(drop >= 0.08) & (drop < 0.09)] = np.inf
    return frames


@pytest.mark.parametrize('seed', range(4))
def test_effective_frame_count_matches_the_array_code(seed):
    rng = np.random.default_rng(seed)
    frames = _frames(rng, 6)
    frames[3] = frames[1]  # an exact repeat
    frames[4] = np.where(np.isnan(frames[2]), 0.0, frames[2])  # a repeat with no return encoded differently
    for model in (SensorModel(), D400):
        got = effective_frame_count(frames, model)
        assert got == reference_effective_frame_count(frames, model)
    assert distinct_frames(frames).tolist() == [0, 1, 2, 5]
    # independent frames with the model's own noise: about n (here 4 distinct)
    assert 1.0 < effective_frame_count(frames, D400) <= 4.0


def test_effective_frame_count_of_repeats_and_too_few_pixels():
    rng = np.random.default_rng(7)
    one = _frames(rng, 1)
    assert effective_frame_count(np.repeat(one, 5, axis=0), D400) == 1.0
    frames = _frames(rng, 3, h=4, w=5)  # at most 20 pixels valid in all: nothing measured
    assert effective_frame_count(frames, D400) == 3.0 == reference_effective_frame_count(frames, D400)


@pytest.mark.parametrize('dtype', [np.float64, np.float32])
@pytest.mark.parametrize('min_valid', [1, 3])
def test_average_frames_matches_the_array_code(dtype, min_valid):
    rng = np.random.default_rng(11)
    depth = _frames(rng, 5).astype(dtype)
    rgb = rng.integers(0, 256, size=(*depth.shape, 3), dtype=np.uint8)
    params = SensingParams(min_valid_returns=min_valid)
    out = average_frames(rgb, depth, params)
    count, z_mean = reference_average(depth, min_valid)
    assert out.count.dtype == count.dtype and np.array_equal(out.count, count)
    assert np.array_equal(out.z_mean, z_mean, equal_nan=True)
    assert np.array_equal(out.missing, count < min_valid)
    assert out.n_eff == reference_effective_frame_count(depth, params.sensor)
    assert np.array_equal(out.rgb_mean, rgb.astype(np.float64).mean(axis=0))


def test_average_frames_refuses_frames_without_a_return():
    depth = np.zeros((2, 4, 4))
    with pytest.raises(ValueError, match='no valid return'):
        average_frames(np.zeros((2, 4, 4, 3), np.uint8), depth, SensingParams())


def test_temporal_moments_sum_frame_after_frame():
    from gpis_grasp_ros.core.noise_model import _temporal_moments

    rng = np.random.default_rng(4)
    flat = rng.normal(0.8, 0.01, (6, 5000)) * np.exp(rng.uniform(-20, 20, 5000))
    flat[rng.random(flat.shape) < 0.02] = np.nan
    flat[rng.random(flat.shape) < 0.01] = -1.0
    flat[rng.random(flat.shape) < 0.01] = np.inf
    idx = np.array([0, 2, 3, 5])
    rows = flat[idx]
    ok = (np.isfinite(rows) & (rows > 0)).all(axis=0)
    s = rows[0].copy()
    with np.errstate(invalid='ignore'):  # inf - inf at the pixels dropped
        for j in range(1, idx.size):
            s = s + rows[j]
        m = s / idx.size
        q = (rows[0] - m) ** 2
        for j in range(1, idx.size):
            q = q + (rows[j] - m) ** 2
    s2, mean = _temporal_moments(flat, idx)
    assert np.array_equal(s2, q[ok] / (idx.size - 1)) and np.array_equal(mean, m[ok])
