"""Camera input: pinhole intrinsics, organized clouds to frames, frame validation and per-pixel averaging."""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numba import njit

from gpis_grasp_ros.core.noise_model import effective_frame_count
from gpis_grasp_ros.core.sensing.pixel_kernels import nan_to_num

if TYPE_CHECKING:
    from gpis_grasp_ros.core.sensing.params import SensingParams


@functools.lru_cache(maxsize=4)
def _rays(fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> np.ndarray:
    u = (np.arange(width, dtype=np.float64) - cx) / fx
    v = (np.arange(height, dtype=np.float64) - cy) / fy
    out = np.empty((height, width, 3))
    out[..., 0] = u[None, :]
    out[..., 1] = v[:, None]
    out[..., 2] = 1.0
    out.setflags(write=False)
    return out


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels: x = (u - cx) z / fx, y = (v - cy) z / fy (u = column, v = row)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        if not (math.isfinite(self.fx) and math.isfinite(self.fy) and self.fx > 0 and self.fy > 0):
            raise ValueError(f'focal lengths must be positive pixels, got fx={self.fx}, fy={self.fy}')
        if not (math.isfinite(self.cx) and math.isfinite(self.cy)):
            raise ValueError('principal point must be finite')
        if self.width < 1 or self.height < 1:
            raise ValueError(f'image size must be positive, got {self.width} x {self.height}')

    def rays(self) -> np.ndarray:
        """(H, W, 3) camera-frame rays ((u - cx) / fx, (v - cy) / fy, 1) of every pixel (read-only: the same array
        for every frame of a camera)."""
        return _rays(self.fx, self.fy, self.cx, self.cy, self.width, self.height)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Camera-frame points (..., 3) (m) → pixel coordinates (..., 2) as (u, v)."""
        p = np.asarray(points, dtype=np.float64)
        z = p[..., 2]
        return np.stack([self.cx + self.fx * p[..., 0] / z, self.cy + self.fy * p[..., 1] / z], axis=-1)

    def pixel_index(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera-frame points (..., 3) (m) → the image pixel each projects onto: (u, v) int64 column and row
        (clipped into the image, so they can index an (H, W) map) and ``inside`` (in front of the camera and
        in the image)."""
        p = np.asarray(points, dtype=np.float64)
        with np.errstate(invalid='ignore', divide='ignore'):
            uv = np.round(self.project(p))
        u, v = uv[..., 0], uv[..., 1]
        inside = (p[..., 2] > 0) & np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < self.width) & (v >= 0) \
            & (v < self.height)
        return (np.clip(nan_to_num(u), 0, self.width - 1).astype(np.int64),
                np.clip(nan_to_num(v), 0, self.height - 1).astype(np.int64), inside)


def _as_frames(frames: np.ndarray | Sequence[np.ndarray], name: str, channels: int | None) -> np.ndarray:
    try:
        arr = np.asarray(frames)
    except ValueError as exc:  # ragged list of frames
        raise ValueError(f'{name}: frames have different shapes ({exc})') from None
    if arr.dtype == object:
        raise ValueError(f'{name}: frames have different shapes')
    want = 3 if channels is None else 4
    if arr.ndim == want - 1:
        arr = arr[None]
    if arr.ndim != want or (channels is not None and arr.shape[-1] != channels):
        shape = '(N, H, W)' if channels is None else f'(N, H, W, {channels})'
        raise ValueError(f'{name}: expected shape {shape} (or one frame without N), got {arr.shape}')
    if arr.shape[0] == 0 or arr.shape[1] == 0 or arr.shape[2] == 0:
        raise ValueError(f'{name}: no frames or empty images, got shape {arr.shape}')
    return arr


def frames_from_clouds(xyz: np.ndarray, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, CameraIntrinsics]:
    """Organized XYZRGB clouds → ``(rgb_frames, depth_frames, intrinsics)``.

    Depth is z (m; NaN where the point is invalid). The intrinsics are recovered by least
    squares from the pinhole model u = fx x / z + cx, v = fy y / z + cy over all valid points
    (u = column index, v = row index).

    Args:
        xyz: ``(N, H, W, 3)`` float points in the camera optical frame (m), NaN = no return.
        rgb: ``(N, H, W, 3)`` uint8 colours.
    """
    pts = _as_frames(xyz, 'xyz', 3)
    col = _as_frames(rgb, 'rgb', 3)
    if not np.issubdtype(pts.dtype, np.floating):
        raise ValueError(f'xyz must be floating point metres, got dtype {pts.dtype}')
    if col.dtype != np.uint8:
        raise ValueError(f'rgb must be uint8, got dtype {col.dtype}')
    if pts.shape != col.shape:
        raise ValueError(f'xyz {pts.shape} and rgb {col.shape} must have the same shape')
    n, h, w, _ = pts.shape
    x, y, z = (pts[..., i].astype(np.float64) for i in range(3))
    valid = np.isfinite(x) & np.isfinite(y) & np.isfinite(z) & (z > 0)
    if valid.sum() < 3:
        raise ValueError('clouds have fewer than 3 valid points: cannot recover the intrinsics')
    u = np.broadcast_to(np.arange(w, dtype=np.float64)[None, None, :], (n, h, w))[valid]
    v = np.broadcast_to(np.arange(h, dtype=np.float64)[None, :, None], (n, h, w))[valid]
    xz, yz = x[valid] / z[valid], y[valid] / z[valid]

    def fit(a: np.ndarray, b: np.ndarray, axis: str) -> tuple[float, float]:
        if np.ptp(a) <= 0:
            raise ValueError(f'valid points span a single {axis} ray direction: cannot recover the intrinsics')
        design = np.stack([a, np.ones_like(a)], axis=1)
        (f, c), *_ = np.linalg.lstsq(design, b, rcond=None)
        return float(f), float(c)

    fx, cx = fit(xz, u, 'x')
    fy, cy = fit(yz, v, 'y')
    depth = np.where(valid, z, np.nan)
    return col, depth, CameraIntrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h)


def validate_frames(rgb_frames, depth_frames, intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """The frames as (N, H, W, 3) uint8 and (N, H, W) float arrays matching ``intrinsics``, or ValueError."""
    if not isinstance(intrinsics, CameraIntrinsics):
        raise ValueError(f'intrinsics must be a CameraIntrinsics, got {type(intrinsics).__name__}')
    rgb = _as_frames(rgb_frames, 'rgb_frames', 3)
    depth_in = _as_frames(depth_frames, 'depth_frames', None)
    if rgb.dtype != np.uint8:
        raise ValueError(f'rgb_frames must be uint8, got dtype {rgb.dtype}')
    if not np.issubdtype(depth_in.dtype, np.floating):
        raise ValueError(f'depth_frames must be floating point metres, got dtype {depth_in.dtype} '
                         '(convert 16-bit millimetre depth with depth / 1000.0 and 0 -> NaN)')
    if rgb.shape[:3] != depth_in.shape:
        raise ValueError(f'rgb_frames {rgb.shape[:3]} and depth_frames {depth_in.shape} differ in number of '
                         'frames or image size')
    if depth_in.shape[1:] != (intrinsics.height, intrinsics.width):
        raise ValueError(f'images are {depth_in.shape[2]} x {depth_in.shape[1]} but the intrinsics are for '
                         f'{intrinsics.width} x {intrinsics.height}')
    return rgb, depth_in


class AveragedFrames(NamedTuple):
    """The frames averaged per pixel over their valid returns."""

    rgb_mean: np.ndarray  # (H, W, 3) float, colour averaged over all frames (0-255)
    z_mean: np.ndarray  # (H, W) m, depth averaged over the valid returns, NaN where missing
    count: np.ndarray  # (H, W) int, valid returns per pixel
    valid: np.ndarray  # (H, W) bool, enough valid returns
    missing: np.ndarray  # (H, W) bool, not valid: no return
    n_eff: float  # independent frames the average is worth
    count_eff: np.ndarray  # (H, W) effective number of averaged returns, count n_eff / N


@njit(cache=True, nogil=True)
def _depth_sums(depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Valid returns (finite, > 0) per pixel of ``depth`` (N, P) and the sum of their depths, frame after frame
    (the sum ``np.where(valid, depth, 0).sum(axis=0)`` makes, in the same order)."""
    count = np.zeros(depth.shape[1], dtype=np.int64)
    total = np.zeros(depth.shape[1])
    for i in range(depth.shape[0]):
        for p in range(depth.shape[1]):  # without branches: adding 0.0 to a sum of positive returns keeps it
            x = np.float64(depth[i, p])
            ok = (x > 0.0) & (x < np.inf)  # finite and > 0
            count[p] += ok
            total[p] += x if ok else 0.0
    return count, total


def average_frames(rgb: np.ndarray, depth_in: np.ndarray, params: SensingParams) -> AveragedFrames:
    """Depth averaged over the frames with a valid return (finite, > 0), colour over all frames; the frames are
    worth n_eff <= N independent measurements, measured from their frame-to-frame depth differences."""
    n_frames, h, w = depth_in.shape
    depth = np.ascontiguousarray(depth_in if depth_in.dtype in (np.float32, np.float64) else
                                 depth_in.astype(np.float64))
    count, total = _depth_sums(depth.reshape(n_frames, -1))
    count, total = count.reshape(h, w), total.reshape(h, w)
    if count.max() == 0:
        raise ValueError('depth_frames contain no valid return (all NaN or <= 0)')
    missing_px = count < max(1, params.min_valid_returns)
    valid = ~missing_px
    with np.errstate(invalid='ignore', divide='ignore'):
        z_mean = np.where(valid, total / np.maximum(count, 1), np.nan)
    rgb_mean = rgb.sum(axis=0, dtype=np.uint32) / float(n_frames)  # exact; no float64 copy of the frames
    n_eff = effective_frame_count(depth, params.sensor) if n_frames > 1 else 1.0
    count_eff = count * (n_eff / n_frames)
    return AveragedFrames(rgb_mean, z_mean, count, valid, missing_px, n_eff, count_eff)
