"""Sensor effects per frame: depth noise, quantisation, drop-outs and colour noise.

Depth ~ N(z, sigma_z(z)^2) (:class:`noise_model.SensorModel` of the sensor, times the material's noise
factor), then the sensor's quantisation (Carmine: :func:`disparity_quantise`, levels spaced by
``noise_model.quantisation_step``; D400: 1 mm depth units); random drop-outs (0.2 % everywhere, 30 %
within one pixel of a depth edge > 4 mm, plus the material's rate). RGB gets N(0, 2^2) per-frame noise;
specular pixels flicker with N(0, 25^2).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage

from gpis_grasp_ros.core import noise_model

if TYPE_CHECKING:
    from gpis_grasp_ros.sim.scene.render import StaticImage

# Depth-noise multiplier and extra per-frame drop-out probability per material label (index = label).
NOISE_FACTOR = np.array([1.0, 1.0, 1.0, 1.0, 2.5, 4.0])
DROPOUT = np.array([0.0, 0.0, 0.03, 1.0, 0.15, 0.05])
BASE_DROPOUT = 0.002
EDGE_DROPOUT = 0.30
EDGE_THRESHOLD_M = 0.004
RGB_NOISE_SIGMA = 2.0
SPECULAR_FLICKER_SIGMA = 25.0


@dataclass
class Frame:
    """One simulated frame: ``depth`` (H, W) float32 m (NaN = no return), ``rgb`` (H, W, 3) uint8,
    ``xyz`` (H, W, 3) float32 m in the optical frame (NaN = no return), ``stamp_ns``."""

    stamp_ns: int
    depth: np.ndarray
    rgb: np.ndarray
    xyz: np.ndarray


def disparity_quantise(depth_m: np.ndarray) -> np.ndarray:
    """Snap depths (m) to the structured-light sensor's depth levels (:func:`noise_model.quantise`).

    Levels are uniformly spaced in 1/z (the sensor measures disparity in fixed sub-pixel steps),
    so every output is one of a fixed set of levels (repeated values also compress well in the bags).
    """
    return noise_model.quantise(depth_m)


def quantise(depth_m: np.ndarray, sensor: str, sensor_model: noise_model.SensorModel) -> np.ndarray:
    """The sensor's depth quantisation (Carmine: disparity levels; D400: 1 mm depth units)."""
    if sensor == 'carmine':
        return disparity_quantise(depth_m)
    step = float(sensor_model.quantisation_constant_m)
    z = np.asarray(depth_m, dtype=np.float64)
    return np.round(z / step) * step if step > 0 else z


def depth_edges(depth: np.ndarray) -> np.ndarray:
    """Pixels within one pixel of a depth jump > EDGE_THRESHOLD_M or of a no-return pixel."""
    valid = np.isfinite(depth)
    d = np.where(valid, depth, 0.0)
    jump = np.zeros(depth.shape, dtype=bool)
    for axis in (0, 1):
        big = (np.abs(np.diff(d, axis=axis)) > EDGE_THRESHOLD_M) | (np.diff(valid.astype(np.int8), axis=axis) != 0)
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis], hi[axis] = slice(None, -1), slice(1, None)
        jump[tuple(lo)] |= big
        jump[tuple(hi)] |= big
    return ndimage.binary_dilation(jump, iterations=1) & np.isfinite(depth)


def noisy_frames(static: StaticImage, rng_state: dict, sensor: str, sensor_model: noise_model.SensorModel,
                 table_depth: float, stamps: Sequence[int]) -> Iterator[Frame]:
    """One noisy frame per stamp from the static images, drawing from a generator started at ``rng_state``
    (the same state gives the same frames); pixels without a clean return never get one."""
    rng = np.random.default_rng()
    rng.bit_generator.state = rng_state
    shape = static.clean_depth.shape
    clean = static.clean_depth
    valid = np.isfinite(clean)
    z0 = np.where(valid, clean, table_depth)
    sigma = sensor_model.sigma(z0) * NOISE_FACTOR[static.label]
    p_drop = np.clip(BASE_DROPOUT + EDGE_DROPOUT * static.edge + DROPOUT[static.label], 0.0, 1.0)
    for stamp in stamps:
        noisy = z0 + sigma * rng.standard_normal(shape)
        drop = rng.random(shape) < p_drop
        depth = quantise(noisy, sensor, sensor_model)
        depth = np.where(valid & ~drop, depth, np.nan).astype(np.float32)
        rgb_f = static.colour + RGB_NOISE_SIGMA * rng.standard_normal(shape + (3,))
        rgb_f += (SPECULAR_FLICKER_SIGMA * static.spec_frac)[..., None] * rng.standard_normal(shape + (1,))
        rgb = np.clip(np.round(rgb_f), 0, 255).astype(np.uint8)
        xyz = np.concatenate([static.rays * depth[..., None], depth[..., None]], axis=-1).astype(np.float32)
        yield Frame(stamp, depth, rgb, xyz)
