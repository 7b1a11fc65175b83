"""Checks of incoming messages against size and value limits, BEFORE anything is allocated.

A message that claims huge dimensions (a 100000 x 100000 image with a few bytes of data, a grid
of 10^10 cells, intrinsics with fx = 1e-300, a GPIS with training points 10^6 m away) is rejected
here with a ``ValueError`` naming the offending field; the node logs it as a warning and keeps
its previous state (a rejected message leaves no trace). Only the message *headers* (sizes,
steps, a few scalars) are read here, plus a finiteness scan of already-received float arrays
(no copies beyond one boolean mask of the message's own size).

Limits are node parameters (see each node); the defaults are in :class:`Limits`.

**What the planner and the gripper can use.** A grid (occupancy, noise map, GPIS model, ground truth)
has at least :data:`MIN_GRID_SIDE` cells per side and an aspect of at most :data:`MAX_GRID_ASPECT`; a
GPIS mean must cross zero (an object surface with free space around it); an object is at most
:data:`MAX_OBJECT_HEIGHT` m high (one limit for segmentation, gpis_node and planner_node); header
stamps are non-negative. See :func:`check_map_meta_data` for the reasons.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from gpis_grasp_ros.core.sensing import SensingParams
from gpis_grasp_ros.data import messages

#: Fewest cells per grid side. The contact search interpolates bilinearly (2 x 2 nodes at least) and the
#: jaws start in free space on either side of the object, so a grid needs object cells with free cells
#: around them on both sides: 1 free + 2 object + 1 free = 4 (segmentation_node's smallest grid_size).
MIN_GRID_SIDE = 4
#: Largest ratio of the longer to the shorter grid side. The heuristic grasps approach along the surface
#: normal or toward the centre of mass, in any direction; across the short side of a long strip the jaws
#: (w_g apart) would start on the SDF the contact search extrapolates beyond the grid, not on the GPIS.
#: segmentation_node makes square grids; 4:1 leaves room for other producers.
MAX_GRID_ASPECT = 4.0
#: Highest object accepted (m above the table), everywhere: segmentation's evidence cap
#: (``SensingParams.max_object_height_m``: higher is an arm or a person, not an object on the table).
MAX_OBJECT_HEIGHT = float(SensingParams.max_object_height_m)


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
    min_extent: float = 0.0                 # m: shorter grid side at least this long (the planner: its jaw width)


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


def check_stamp(header: Any, what: str) -> None:
    """A ``std_msgs/Header`` stamp is a time since the epoch: sec >= 0 and nanosec < 10^9."""
    stamp = header.stamp
    sec, nanosec = int(stamp.sec), int(stamp.nanosec)
    if sec < 0 or not (0 <= nanosec < 1_000_000_000):
        raise ValueError(f'{what}.header.stamp ({sec} s, {nanosec} ns) is not a time since the epoch '
                         '(sec must be >= 0, nanosec < 10^9)')


def _data_size(data: Any) -> int:
    """Length of a primitive sequence field without copying it."""
    return len(data)


def check_image(msg: Any, limits: Limits, what: str = 'Image') -> None:
    """Stamp, size, step and data length of a ``sensor_msgs/Image`` (before :func:`messages.image_to_numpy`)."""
    check_stamp(msg.header, what)
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
    """Stamp, size, steps and data length of a ``sensor_msgs/PointCloud2`` (before parsing it)."""
    check_stamp(msg.header, 'PointCloud2')
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
    """``nav_msgs/MapMetaData`` of a grid: size (at least :data:`MIN_GRID_SIDE` cells a side, aspect at most
    :data:`MAX_GRID_ASPECT`, the shorter side at least ``limits.min_extent`` m), resolution, finite pose and a
    unit quaternion."""
    w = _count(f'{what}.info.width', info.width, 1, limits.max_grid_cells)
    h = _count(f'{what}.info.height', info.height, 1, limits.max_grid_cells)
    if w * h > limits.max_grid_cells:
        raise ValueError(f'{what} has {w} x {h} = {w * h} cells, more than max_grid_cells={limits.max_grid_cells}')
    if min(w, h) < MIN_GRID_SIDE:
        raise ValueError(f'{what} is {w} x {h} cells: the contact search and the jaws need at least '
                         f'{MIN_GRID_SIDE} x {MIN_GRID_SIDE} (free space on both sides of the object)')
    if max(w, h) > MAX_GRID_ASPECT * min(w, h):
        raise ValueError(f'{what} is {w} x {h} cells: sides more unequal than {MAX_GRID_ASPECT:g}:1 leave the jaws '
                         'no room across the short side')
    res = float(info.resolution)
    if not (math.isfinite(res) and limits.min_resolution <= res <= limits.max_resolution):
        raise ValueError(f'{what}.info.resolution={res} m outside [{limits.min_resolution:g}, '
                         f'{limits.max_resolution:g}] m')
    if min(w, h) * res < limits.min_extent:
        raise ValueError(f'{what} is {min(w, h) * res * 1000:.3g} mm across its shorter side, narrower than the '
                         f'jaw width {limits.min_extent * 1000:.3g} mm')
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
    """OccupancyGrid stamp, grid, data length and values in [-1, 100]."""
    check_stamp(msg.header, 'OccupancyGrid')
    check_map_meta_data(msg.info, limits, 'OccupancyGrid')
    n = int(msg.info.width) * int(msg.info.height)
    if _data_size(msg.data) != n:
        raise ValueError(f'OccupancyGrid.data has {_data_size(msg.data)} values, expected width * height = {n}')
    occ = messages._as_array(msg.data, np.int8)
    if occ.size and (occ.min() < -1 or occ.max() > 100):
        raise ValueError('OccupancyGrid.data values must lie in [-1, 100]')


def check_float_grid(msg: Any, limits: Limits, what: str, allow_nan: bool, low: float, high: float) -> None:
    """FloatGrid stamp, grid, data length and values (NaN allowed only where ``allow_nan``)."""
    check_stamp(msg.header, what)
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
    diagonals, variances/jitter non-negative and bounded, the centre of mass finite and on the grid,
    the object height in [0, :data:`MAX_OBJECT_HEIGHT`] m.
    """
    check_stamp(msg.header, 'GpisModel')
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
    height = _finite('GpisModel.object_height', getattr(msg, 'object_height', 0.0))
    if not (0.0 <= height <= MAX_OBJECT_HEIGHT):
        raise ValueError(f'GpisModel.object_height={height} m outside [0, {MAX_OBJECT_HEIGHT:g}] m')


def check_on_grid(xy: np.ndarray, geometry: Any, what: str, margin_cells: float = 1.0) -> None:
    """Table-frame ``xy`` (m) lies on the grid of ``geometry`` (within ``margin_cells`` of its border)."""
    lo = np.array([geometry.origin_x, geometry.origin_y]) - margin_cells * geometry.resolution
    hi = lo + np.asarray(geometry.size_m, dtype=np.float64) + 2 * margin_cells * geometry.resolution
    xy = np.asarray(xy, dtype=np.float64)[:2]
    if not (np.isfinite(xy).all() and np.all(xy >= lo) and np.all(xy <= hi)):
        raise ValueError(f'{what} is at ({xy[0]:.3g}, {xy[1]:.3g}) m in the table frame, off the grid '
                         f'[{lo[0]:.3g}, {hi[0]:.3g}] x [{lo[1]:.3g}, {hi[1]:.3g}] m')


def object_height_of(top_sensor: np.ndarray, geometry: Any) -> float:
    """Height (m) above the table of an ``object/top`` point (camera frame), checked: on the grid and in
    (0, :data:`MAX_OBJECT_HEIGHT`]; ValueError says why not (0 = on the table plane: unknown)."""
    xy, height = geometry.from_sensor(np.asarray(top_sensor, dtype=np.float64))
    check_on_grid(xy, geometry, 'object/top')
    height = float(height)
    if not (math.isfinite(height) and height <= MAX_OBJECT_HEIGHT):
        raise ValueError(f'object/top is {height * 1000:.0f} mm above the table, more than the highest object '
                         f'{MAX_OBJECT_HEIGHT * 1000:.0f} mm')
    return max(height, 0.0)


def check_posterior(posterior: Any) -> None:
    """The posterior has finite mean, variance and gradient (never plan on NaN), and its mean crosses zero:
    an object surface (mean < 0 inside) with free space (mean > 0) for the jaws to start in."""
    for name in ('mean', 'variance', 'gradient'):
        arr = np.asarray(getattr(posterior, name))
        if not np.isfinite(arr).all():
            raise ValueError(f'GpisModel gives a non-finite posterior {name} (ill-conditioned kernel?)')
    mean = np.asarray(posterior.mean)
    if not (mean < 0).any():
        raise ValueError('the GPIS mean is >= 0 on every cell: no object to grasp')
    if not (mean > 0).any():
        raise ValueError('the GPIS mean is <= 0 on every cell: no free space for the jaws')


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
