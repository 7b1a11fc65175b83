"""Checks of incoming messages against size and value limits, BEFORE anything is allocated.

A message that claims huge dimensions (a 100000 x 100000 image with a few bytes of data, a grid
of 10^10 cells, intrinsics with fx = 1e-300, a GPIS with training points 10^6 m away) is rejected
here with a ``ValueError`` naming the offending field; the node logs it as a warning and keeps
its previous state (a rejected message leaves no trace). Only the message *headers* (sizes,
steps, a few scalars) are read here, plus a finiteness scan of already-received float arrays
(no copies beyond one boolean mask of the message's own size).

Limits are node parameters (see each node); the defaults are in :class:`Limits`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from gpis_grasp_ros.data import messages


@dataclass(frozen=True)
class Limits:
    """Accepted sizes and values of incoming messages (lengths in m)."""

    max_image_pixels: int = 4_000_000       # per camera frame (e.g. 2048 x 1952)
    max_grid_cells: int = 10_000            # per grid (100 x 100); the GP fit costs ~8 n^2 bytes for n cells
    min_resolution: float = 1e-4            # m per grid cell
    max_resolution: float = 1.0             # m per grid cell
    max_distance: float = 100.0             # m: |positions| in the sensor frame (grid origins, points)
    min_focal_px: float = 1.0
    max_focal_px: float = 1e5


def _finite(name: str, value: float) -> float:
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f'{name} must be finite, got {v}')
    return v


def _count(name: str, value: int, low: int, high: int) -> int:
    v = int(value)
    if not (low <= v <= high):
        raise ValueError(f'{name}={v} outside [{low}, {high}]')
    return v


def _data_size(data: Any) -> int:
    """Length of a primitive sequence field without copying it."""
    return len(data)


def check_image(msg: Any, limits: Limits, what: str = 'Image') -> None:
    """Size, step and data length of a ``sensor_msgs/Image`` (before :func:`messages.image_to_numpy`)."""
    h = _count(f'{what}.height', msg.height, 1, limits.max_image_pixels)
    w = _count(f'{what}.width', msg.width, 1, limits.max_image_pixels)
    if h * w > limits.max_image_pixels:
        raise ValueError(f'{what} is {w} x {h} = {h * w} pixels, more than max_image_pixels={limits.max_image_pixels}')
    enc = str(msg.encoding)
    if enc not in messages.IMAGE_ENCODINGS:
        raise ValueError(f"{what}.encoding '{enc}' is not supported; supported: {sorted(messages.IMAGE_ENCODINGS)}")
    channels, scalar = messages.IMAGE_ENCODINGS[enc]
    row = w * channels * np.dtype(scalar).itemsize
    step = int(msg.step)
    if not (row <= step <= 4 * row + 64):
        raise ValueError(f'{what}.step={step} does not fit width {w} of {enc} ({row} bytes per row)')
    if _data_size(msg.data) != h * step:
        raise ValueError(f'{what}.data has {_data_size(msg.data)} bytes, expected height {h} * step {step} = '
                         f'{h * step}')


def check_pointcloud(msg: Any, limits: Limits) -> None:
    """Size, steps and data length of a ``sensor_msgs/PointCloud2`` (before parsing it)."""
    h = _count('PointCloud2.height', msg.height, 1, limits.max_image_pixels)
    w = _count('PointCloud2.width', msg.width, 1, limits.max_image_pixels)
    if h * w > limits.max_image_pixels:
        raise ValueError(f'PointCloud2 has {w} x {h} = {h * w} points, more than max_image_pixels='
                         f'{limits.max_image_pixels}')
    point_step = _count('PointCloud2.point_step', msg.point_step, 1, 256)
    row_step = int(msg.row_step)
    if not (w * point_step <= row_step <= w * point_step + 4096):
        raise ValueError(f'PointCloud2.row_step={row_step} does not fit width {w} * point_step {point_step}')
    if _data_size(msg.data) != h * row_step:
        raise ValueError(f'PointCloud2.data has {_data_size(msg.data)} bytes, expected height {h} * row_step '
                         f'{row_step} = {h * row_step}')


def check_camera_info(msg: Any, limits: Limits) -> tuple[float, float, float, float, int, int]:
    """Validated ``(fx, fy, cx, cy, width, height)`` of a ``sensor_msgs/CameraInfo``."""
    w = _count('CameraInfo.width', msg.width, 1, limits.max_image_pixels)
    h = _count('CameraInfo.height', msg.height, 1, limits.max_image_pixels)
    if w * h > limits.max_image_pixels:
        raise ValueError(f'CameraInfo is {w} x {h} pixels, more than max_image_pixels={limits.max_image_pixels}')
    if _data_size(msg.k) != 9:
        raise ValueError(f'CameraInfo.k must have 9 elements, got {_data_size(msg.k)}')
    k = [float(v) for v in msg.k]
    for name, value in (('k[0] (fx)', k[0]), ('k[4] (fy)', k[4])):
        if not (math.isfinite(value) and limits.min_focal_px <= value <= limits.max_focal_px):
            raise ValueError(f'CameraInfo.{name}={value} outside [{limits.min_focal_px:g}, {limits.max_focal_px:g}] '
                             'pixels; is the camera calibrated?')
    for name, value, size in (('k[2] (cx)', k[2], w), ('k[5] (cy)', k[5], h)):
        if not (math.isfinite(value) and -size <= value <= 2 * size):
            raise ValueError(f'CameraInfo.{name}={value} is not near the {w} x {h} image')
    return k[0], k[4], k[2], k[5], w, h


def check_map_meta_data(info: Any, limits: Limits, what: str) -> None:
    """``nav_msgs/MapMetaData`` of a grid: size, resolution, finite pose and a unit quaternion."""
    w = _count(f'{what}.info.width', info.width, 1, limits.max_grid_cells)
    h = _count(f'{what}.info.height', info.height, 1, limits.max_grid_cells)
    if w * h > limits.max_grid_cells:
        raise ValueError(f'{what} has {w} x {h} = {w * h} cells, more than max_grid_cells={limits.max_grid_cells}')
    res = float(info.resolution)
    if not (math.isfinite(res) and limits.min_resolution <= res <= limits.max_resolution):
        raise ValueError(f'{what}.info.resolution={res} m outside [{limits.min_resolution:g}, '
                         f'{limits.max_resolution:g}] m')
    p = info.origin.position
    for axis in ('x', 'y', 'z'):
        v = _finite(f'{what}.info.origin.position.{axis}', getattr(p, axis))
        if abs(v) > limits.max_distance:
            raise ValueError(f'{what}.info.origin.position.{axis}={v} m is farther than {limits.max_distance:g} m')
    q = info.origin.orientation
    quat = np.array([float(q.x), float(q.y), float(q.z), float(q.w)])
    if not np.isfinite(quat).all() or abs(float(np.linalg.norm(quat)) - 1.0) > 1e-3:
        raise ValueError(f'{what}.info.origin.orientation must be a finite unit quaternion, got {quat.tolist()}')


def _finite_array(name: str, data: Any, allow_nan: bool = False, low: float = -np.inf,
                  high: float = np.inf) -> np.ndarray:
    a = messages._as_array(data, np.float64) if not isinstance(data, np.ndarray) else data.astype(np.float64)
    bad = ~np.isfinite(a)
    if allow_nan:
        bad &= ~np.isnan(a)
    if bad.any():
        raise ValueError(f'{name} has {int(bad.sum())} non-finite value(s)')
    vals = a[np.isfinite(a)]
    if vals.size and (vals.min() < low or vals.max() > high):
        raise ValueError(f'{name} has values outside [{low:g}, {high:g}] (min {vals.min():g}, max {vals.max():g})')
    return a


def check_occupancy_grid(msg: Any, limits: Limits) -> None:
    """OccupancyGrid header, data length and values in [-1, 100]."""
    check_map_meta_data(msg.info, limits, 'OccupancyGrid')
    n = int(msg.info.width) * int(msg.info.height)
    if _data_size(msg.data) != n:
        raise ValueError(f'OccupancyGrid.data has {_data_size(msg.data)} values, expected width * height = {n}')
    occ = messages._as_array(msg.data, np.int8)
    if occ.size and (occ.min() < -1 or occ.max() > 100):
        raise ValueError('OccupancyGrid.data values must lie in [-1, 100]')


def check_float_grid(msg: Any, limits: Limits, what: str, allow_nan: bool, low: float, high: float) -> None:
    """FloatGrid header, data length and values (NaN allowed only where ``allow_nan``)."""
    check_map_meta_data(msg.info, limits, what)
    n = int(msg.info.width) * int(msg.info.height)
    if _data_size(msg.data) != n:
        raise ValueError(f'{what}.data has {_data_size(msg.data)} values, expected width * height = {n}')
    values = _finite_array(f'{what}.data', msg.data, allow_nan=allow_nan, low=low, high=high)
    if allow_nan and values.size and np.isnan(values).all():
        raise ValueError(f'{what}.data is all NaN')


def check_gpis_model(msg: Any, limits: Limits) -> None:
    """A ``GpisModel``: grid, hyperparameters, training data near the grid, finite values.

    Training points must lie within one grid extent of the grid, SDF targets within a few grid
    diagonals, variances/jitter non-negative and bounded, the centre of mass finite.
    """
    check_map_meta_data(msg.info, limits, 'GpisModel')
    w, h = int(msg.info.width), int(msg.info.height)
    res = float(msg.resolution) if float(msg.resolution) != 0.0 else float(msg.info.resolution)
    if not (math.isfinite(res) and limits.min_resolution <= res <= limits.max_resolution):
        raise ValueError(f'GpisModel.resolution={res} m outside [{limits.min_resolution:g}, '
                         f'{limits.max_resolution:g}] m')
    diag = res * math.hypot(w, h)
    c = _finite('GpisModel.signal_variance', msg.signal_variance)
    ell = _finite('GpisModel.length_scale', msg.length_scale)
    if not (0 < c <= max(100 * diag ** 2, 1e-6)):
        raise ValueError(f'GpisModel.signal_variance={c} m^2 outside (0, {100 * diag ** 2:g}]')
    if not (0.01 * res <= ell <= 100 * diag):
        raise ValueError(f'GpisModel.length_scale={ell} m outside [{0.01 * res:g}, {100 * diag:g}] m')
    m = _finite('GpisModel.prior_mean', msg.prior_mean)
    if abs(m) > 10 * diag:
        raise ValueError(f'GpisModel.prior_mean={m} m is larger than 10 grid diagonals')
    jitter = _finite('GpisModel.jitter', msg.jitter)
    if not (0.0 <= jitter <= c):
        raise ValueError(f'GpisModel.jitter={jitter} m^2 outside [0, signal_variance={c:g}]')
    n = _data_size(msg.train_y)
    if not (1 <= n <= limits.max_grid_cells):
        raise ValueError(f'GpisModel has {n} training points; expected 1..{limits.max_grid_cells}')
    if _data_size(msg.train_x) != 2 * n or _data_size(msg.train_noise_variance) != n:
        raise ValueError(f'GpisModel training arrays disagree: train_x has {_data_size(msg.train_x)} values '
                         f'(expected 2 * {n}), train_noise_variance {_data_size(msg.train_noise_variance)} '
                         f'(expected {n})')
    for name in ('mean', 'variance'):
        size = _data_size(getattr(msg, name))
        if size not in (0, w * h):
            raise ValueError(f'GpisModel.{name} has {size} values, expected width * height = {w * h}')
    # Training inputs are grid-frame (x, y): within one grid extent around the grid.
    geometry = messages.map_meta_data_to_geometry(msg.info, str(msg.header.frame_id))
    x = _finite_array('GpisModel.train_x', msg.train_x).reshape(-1, 2)
    lo = np.array([geometry.origin_x, geometry.origin_y]) - res * np.array([w, h])
    hi = np.array([geometry.origin_x, geometry.origin_y]) + 2 * res * np.array([w, h])
    outside = ~np.all((x >= lo) & (x <= hi), axis=1)
    if outside.any():
        raise ValueError(f'GpisModel.train_x has {int(outside.sum())} point(s) more than one grid extent away from '
                         'the grid')
    _finite_array('GpisModel.train_y', msg.train_y, low=-10 * diag, high=10 * diag)
    _finite_array('GpisModel.train_noise_variance', msg.train_noise_variance, low=0.0, high=100 * diag ** 2)
    if _data_size(msg.mean):
        _finite_array('GpisModel.mean', msg.mean, low=-100 * diag, high=100 * diag)
    if _data_size(msg.variance):
        _finite_array('GpisModel.variance', msg.variance, low=0.0, high=100 * diag ** 2 + c)
    for name in ('train_grad_x', 'train_grad', 'train_grad_noise_variance'):  # gradient observations, if any
        data = getattr(msg, name, None)
        if data is not None and _data_size(data):
            if _data_size(data) > 4 * limits.max_grid_cells:
                raise ValueError(f'GpisModel.{name} has {_data_size(data)} values, more than 4 * max_grid_cells')
            _finite_array(f'GpisModel.{name}', data)
    com = msg.center_of_mass
    for axis in ('x', 'y', 'z'):
        _finite(f'GpisModel.center_of_mass.{axis}', getattr(com, axis))
    _finite('GpisModel.center_of_mass_std', msg.center_of_mass_std)


def check_posterior(posterior: Any) -> None:
    """The rebuilt posterior has finite mean, variance and gradient (never plan on NaN)."""
    for name in ('mean', 'variance', 'gradient'):
        arr = np.asarray(getattr(posterior, name))
        if not np.isfinite(arr).all():
            raise ValueError(f'GpisModel gives a non-finite posterior {name} (ill-conditioned kernel?)')


def check_point(msg: Any, what: str, limits: Limits) -> np.ndarray:
    """Finite (x, y, z) of a ``geometry_msgs/Point(Stamped)`` within ``max_distance``."""
    p = msg.point if hasattr(msg, 'point') else msg
    xyz = np.array([_finite(f'{what}.{axis}', getattr(p, axis)) for axis in ('x', 'y', 'z')])
    if np.abs(xyz).max() > limits.max_distance:
        raise ValueError(f'{what} is farther than {limits.max_distance:g} m')
    return xyz


def check_pose(pose_stamped: Any, what: str, limits: Limits) -> np.ndarray:
    """Position (x, y, z) of a ``PoseStamped`` with a finite position and a finite unit orientation."""
    pose = pose_stamped.pose
    xyz = check_point(pose.position, f'{what}.pose.position', limits)
    q = pose.orientation
    quat = np.array([float(q.x), float(q.y), float(q.z), float(q.w)])
    if not np.isfinite(quat).all():
        raise ValueError(f'{what}.pose.orientation is not finite: {quat.tolist()}')
    norm = float(np.linalg.norm(quat))
    if norm > 0 and abs(norm - 1.0) > 1e-3:
        raise ValueError(f'{what}.pose.orientation is not a unit quaternion (norm {norm:.4g})')
    return xyz
