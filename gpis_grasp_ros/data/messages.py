"""Message <-> numpy conversion: the single place where ROS message layouts are interpreted.

ROS-agnostic at import time (no rclpy import here): the *readers* are duck-typed and accept
both ``rosbags`` dataclasses (primitive arrays are numpy arrays) and rclpy messages (``uint8[]``
is ``array.array('B')`` or ``bytes``, fixed-size arrays are numpy arrays), because both use the
same field names. The *builders* take a message factory so one code path makes either kind:

* :class:`RosbagsFactory` (``RosbagsFactory(typestore)``) builds rosbags dataclasses, e.g. for
  writing bags with :mod:`gpis_grasp_ros.data.bagio`;
* :class:`gpis_grasp_ros.ros.conversions.RclpyFactory` builds rclpy messages (the ROS layer).

Also here: ``GpisModel`` ↔ :class:`~gpis_grasp_ros.core.gpis.GpisPosterior`
(:func:`posterior_to_gpis_model`, :func:`gpis_model_to_posterior`). The planner's rclpy outputs
(``GraspPlan`` response, markers) are in :mod:`gpis_grasp_ros.ros.conversions`.

Conventions (see :mod:`gpis_grasp_ros.core.grid`): lengths in metres, grids row-major ``[row, col]``
with rows along +y and columns along +x of ``header.frame_id``; colour arrays on the numpy side
are always RGB order ``uint8`` (``bgr8`` messages are swapped on the way in and out); depth
arrays are ``float32`` metres with NaN for "no return".
"""

from __future__ import annotations

import array
import math
from dataclasses import replace
from typing import Any, Protocol

import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry

# sensor_msgs/PointField datatype constants -> numpy scalar type (byte order added later).
POINTFIELD_DTYPES: dict[int, str] = {1: 'i1', 2: 'u1', 3: 'i2', 4: 'u2', 5: 'i4', 6: 'u4', 7: 'f4', 8: 'f8'}
POINTFIELD_FLOAT32 = 7
POINTFIELD_UINT32 = 6

# Image encodings understood here: encoding -> (channels, numpy scalar type).
IMAGE_ENCODINGS: dict[str, tuple[int, str]] = {
    'rgb8': (3, 'u1'),
    'bgr8': (3, 'u1'),
    'mono8': (1, 'u1'),
    '32FC1': (1, 'f4'),
    '16UC1': (1, 'u2'),
}


# --------------------------------------------------------------------------- factories
class MessageFactory(Protocol):
    """Makes messages of one flavour (rosbags dataclasses or rclpy messages)."""

    def new(self, type_name: str, **fields: Any) -> Any:
        """A message of ``type_name`` (``'pkg/msg/Type'``) with the given fields."""

    def seq(self, values: np.ndarray, dtype: Any) -> Any:
        """Representation of an unbounded primitive sequence (e.g. ``uint8[]``)."""

    def fixed(self, values: np.ndarray, dtype: Any) -> Any:
        """Representation of a fixed-size primitive array (e.g. ``float64[9]``)."""


class RosbagsFactory:
    """Builds ``rosbags`` message dataclasses from a typestore (every field must be given)."""

    def __init__(self, typestore: Any) -> None:
        self.typestore = typestore

    def new(self, type_name: str, **fields: Any) -> Any:
        try:
            cls = self.typestore.types[type_name]
        except KeyError:
            raise ValueError(f"message type '{type_name}' is not in the rosbags typestore") from None
        return cls(**fields)

    def seq(self, values: np.ndarray, dtype: Any) -> np.ndarray:
        return np.ascontiguousarray(np.asarray(values, dtype=dtype).ravel())

    def fixed(self, values: np.ndarray, dtype: Any) -> np.ndarray:
        return np.ascontiguousarray(np.asarray(values, dtype=dtype).ravel())


# --------------------------------------------------------------------------- small helpers
def _as_array(data: Any, dtype: Any) -> np.ndarray:
    """A flat numpy view/copy of a primitive sequence field (numpy, array.array, bytes or list)."""
    dtype = np.dtype(dtype)
    if isinstance(data, np.ndarray):
        return data.ravel().astype(dtype, copy=False)
    if isinstance(data, (bytes, bytearray, memoryview)):
        return np.frombuffer(data, dtype=dtype)
    if isinstance(data, array.array):
        if data.itemsize == dtype.itemsize:
            return np.frombuffer(data, dtype=dtype)
        return np.asarray(data.tolist(), dtype=dtype)
    return np.asarray(list(data), dtype=dtype)


def _raw_bytes(data: Any) -> np.ndarray:
    """The bytes of a ``uint8[]`` field as a flat ``uint8`` array (no copy when possible)."""
    if isinstance(data, np.ndarray):
        if data.dtype != np.uint8:
            raise ValueError(f'byte buffer must be uint8, got {data.dtype}')
        return np.ascontiguousarray(data.ravel())
    if isinstance(data, array.array) and data.typecode not in ('B', 'b'):
        raise ValueError(f"byte buffer must be array('B'), got array('{data.typecode}')")
    return _as_array(data, np.uint8)


def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` (or anything with a ``stamp``, e.g. a Header) → integer ns."""
    if hasattr(stamp, 'stamp'):
        stamp = stamp.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def time_msg(f: MessageFactory, stamp_ns: int) -> Any:
    """``builtin_interfaces/Time`` for ``stamp_ns`` (ns since the epoch, must be >= 0)."""
    stamp_ns = int(stamp_ns)
    if stamp_ns < 0:
        raise ValueError(f'time stamps must be non-negative, got {stamp_ns} ns')
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    return f.new('builtin_interfaces/msg/Time', sec=sec, nanosec=nanosec)


def header(f: MessageFactory, stamp_ns: int, frame_id: str) -> Any:
    """``std_msgs/Header`` with stamp ``stamp_ns`` (ns) and ``frame_id``."""
    return f.new('std_msgs/msg/Header', stamp=time_msg(f, stamp_ns), frame_id=str(frame_id))


def _header_or_default(f: MessageFactory, hdr: Any, frame_id: str) -> Any:
    return header(f, 0, frame_id) if hdr is None else hdr


# --------------------------------------------------------------------------- PointCloud2
def pointcloud2_to_xyz_rgb(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """Organized (or flat) ``sensor_msgs/PointCloud2`` with x, y, z and rgb/rgba fields → arrays.

    Returns ``xyz`` (H, W, 3) float32 in metres (NaN where the sensor had no return) and ``rgb``
    (H, W, 3) uint8. ``rgb`` may be a float32- or uint32-typed field holding 0x00RRGGBB.
    Raises ValueError when fields are missing or of the wrong type, or sizes are inconsistent.
    """
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    fields = {str(fl.name): fl for fl in msg.fields}
    order = '>' if bool(msg.is_bigendian) else '<'
    missing = [n for n in ('x', 'y', 'z') if n not in fields]
    color_name = 'rgb' if 'rgb' in fields else ('rgba' if 'rgba' in fields else None)
    if missing or color_name is None:
        need = missing + ([] if color_name else ['rgb'])
        raise ValueError(f'PointCloud2 lacks field(s) {need}; has {sorted(fields)}')
    names, formats, offsets = [], [], []
    for name in ('x', 'y', 'z', color_name):
        fl = fields[name]
        want = (POINTFIELD_FLOAT32,) if name in 'xyz' else (POINTFIELD_FLOAT32, POINTFIELD_UINT32)
        if int(fl.datatype) not in want:
            raise ValueError(f"PointCloud2 field '{name}' has datatype {int(fl.datatype)}, expected one of {want} "
                             '(7 = FLOAT32, 6 = UINT32)')
        if int(fl.count) > 1:
            raise ValueError(f"PointCloud2 field '{name}' has count {int(fl.count)}, expected 1")
        if int(fl.offset) + 4 > point_step:
            raise ValueError(f"PointCloud2 field '{name}' at offset {int(fl.offset)} does not fit in "
                             f'point_step {point_step}')
        names.append(name)
        formats.append(order + ('u4' if name == color_name else 'f4'))
        offsets.append(int(fl.offset))
    if height < 0 or width < 0 or point_step <= 0:
        raise ValueError(f'PointCloud2 has invalid size {height} x {width}, point_step {point_step}')
    if row_step < width * point_step:
        raise ValueError(f'PointCloud2 row_step {row_step} < width {width} * point_step {point_step}')
    data = _raw_bytes(msg.data)
    if data.size < height * row_step:
        raise ValueError(f'PointCloud2 data has {data.size} bytes, expected height {height} * row_step {row_step} '
                         f'= {height * row_step}')
    dtype = np.dtype({'names': names, 'formats': formats, 'offsets': offsets, 'itemsize': point_step})
    rows = data[:height * row_step].reshape(height, row_step)[:, :width * point_step]
    pts = np.ascontiguousarray(rows).view(dtype).reshape(height, width)
    xyz = np.stack([pts['x'], pts['y'], pts['z']], axis=-1).astype(np.float32)
    packed = pts[color_name].astype(np.uint32)
    rgb = np.stack([(packed >> 16) & 0xFF, (packed >> 8) & 0xFF, packed & 0xFF], axis=-1).astype(np.uint8)
    return xyz, rgb


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) uint8 RGB → (...) float32 carrying the packed 0x00RRGGBB bits (PCL convention)."""
    rgb = np.asarray(rgb, dtype=np.uint8)
    packed = (rgb[..., 0].astype(np.uint32) << 16) | (rgb[..., 1].astype(np.uint32) << 8) | rgb[..., 2]
    return packed.astype(np.uint32).view(np.float32)


def xyz_rgb_to_pointcloud2(f: MessageFactory, xyz: np.ndarray, rgb: np.ndarray, header: Any) -> Any:
    """Organized ``sensor_msgs/PointCloud2`` (fields x, y, z, rgb; float32; 16-byte points).

    ``xyz`` (H, W, 3) metres, NaN for no return; ``rgb`` (H, W, 3) uint8. ``is_dense`` is true
    only when no coordinate is NaN.
    """
    xyz = np.asarray(xyz)
    rgb = np.asarray(rgb)
    if xyz.ndim != 3 or xyz.shape[-1] != 3:
        raise ValueError(f'xyz must have shape (H, W, 3), got {xyz.shape}')
    if rgb.shape != xyz.shape:
        raise ValueError(f'rgb shape {rgb.shape} differs from xyz shape {xyz.shape}')
    h, w = xyz.shape[:2]
    pts = np.empty((h, w, 4), dtype='<f4')
    pts[..., :3] = xyz
    pts[..., 3] = pack_rgb(rgb)
    fields = [f.new('sensor_msgs/msg/PointField', name=n, offset=4 * i, datatype=POINTFIELD_FLOAT32, count=1)
              for i, n in enumerate(('x', 'y', 'z', 'rgb'))]
    return f.new('sensor_msgs/msg/PointCloud2', header=header, height=h, width=w, fields=fields, is_bigendian=False,
                 point_step=16, row_step=16 * w, data=f.seq(pts.view(np.uint8), np.uint8),
                 is_dense=bool(np.isfinite(xyz).all()))


# --------------------------------------------------------------------------- Image
def image_to_numpy(msg: Any) -> np.ndarray:
    """``sensor_msgs/Image`` → numpy.

    ``rgb8``/``bgr8`` → (H, W, 3) uint8 in **RGB** order; ``mono8`` → (H, W) uint8;
    ``32FC1`` → (H, W) float32 metres; ``16UC1`` (millimetres) → (H, W) float32 metres with
    0 mapped to NaN. Rows may be padded (``step`` > width * bytes per pixel).
    """
    enc = str(msg.encoding)
    if enc not in IMAGE_ENCODINGS:
        raise ValueError(f"unsupported image encoding '{enc}'; supported: {sorted(IMAGE_ENCODINGS)}")
    channels, scalar = IMAGE_ENCODINGS[enc]
    dtype = np.dtype(('>' if bool(msg.is_bigendian) else '<') + scalar)
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = width * channels * dtype.itemsize
    if step < row_bytes:
        raise ValueError(f"image step {step} < width {width} * {channels * dtype.itemsize} bytes for '{enc}'")
    data = _raw_bytes(msg.data)
    if data.size < height * step:
        raise ValueError(f'image data has {data.size} bytes, expected height {height} * step {step} = '
                         f'{height * step}')
    rows = np.ascontiguousarray(data[:height * step].reshape(height, step)[:, :row_bytes])
    arr = rows.view(dtype).reshape((height, width, channels) if channels > 1 else (height, width))
    if enc == 'bgr8':
        return np.ascontiguousarray(arr[..., ::-1])
    if enc == '16UC1':
        mm = arr.astype(np.float32)
        return np.where(mm > 0, mm * np.float32(1e-3), np.float32(np.nan)).astype(np.float32)
    if enc == '32FC1':
        return arr.astype(np.float32)
    return arr.copy()


def numpy_to_image(f: MessageFactory, arr: np.ndarray, encoding: str, header: Any) -> Any:
    """numpy → ``sensor_msgs/Image`` (little-endian, unpadded rows).

    ``rgb8``/``bgr8`` expect (H, W, 3) RGB uint8; ``mono8`` (H, W) uint8; ``32FC1`` (H, W)
    metres; ``16UC1`` (H, W) metres, written as millimetres with NaN / non-positive → 0.
    """
    if encoding not in IMAGE_ENCODINGS:
        raise ValueError(f"unsupported image encoding '{encoding}'; supported: {sorted(IMAGE_ENCODINGS)}")
    channels, scalar = IMAGE_ENCODINGS[encoding]
    a = np.asarray(arr)
    want_ndim = 3 if channels > 1 else 2
    if a.ndim != want_ndim or (channels > 1 and a.shape[-1] != channels):
        raise ValueError(f"'{encoding}' needs an array of shape {'(H, W, 3)' if channels > 1 else '(H, W)'}, "
                         f'got {a.shape}')
    if encoding == 'bgr8':
        a = a[..., ::-1]
    if encoding == '16UC1':
        mm = np.round(np.asarray(a, dtype=np.float64) * 1e3)
        a = np.where(np.isfinite(mm) & (mm > 0), np.clip(mm, 0, 65535), 0)
    if scalar == 'u1' and a.dtype != np.uint8:
        if not np.issubdtype(a.dtype, np.integer) or a.min(initial=0) < 0 or a.max(initial=0) > 255:
            raise ValueError(f"'{encoding}' needs uint8 values, got {a.dtype}")
    out = np.ascontiguousarray(a, dtype=np.dtype('<' + scalar))
    h, w = out.shape[:2]
    return f.new('sensor_msgs/msg/Image', header=header, height=h, width=w, encoding=encoding, is_bigendian=0,
                 step=w * channels * out.dtype.itemsize, data=f.seq(out.view(np.uint8), np.uint8))


# --------------------------------------------------------------------------- CameraInfo
def camera_info_to_intrinsics(msg: Any) -> tuple[float, float, float, float, int, int]:
    """``sensor_msgs/CameraInfo`` → ``(fx, fy, cx, cy, width, height)`` (pixels)."""
    k = _as_array(msg.k, np.float64)
    if k.size != 9:
        raise ValueError(f'CameraInfo.k must have 9 elements, got {k.size}')
    fx, fy, cx, cy = float(k[0]), float(k[4]), float(k[2]), float(k[5])
    if not (fx > 0 and fy > 0):
        raise ValueError(f'CameraInfo has no valid focal length (fx={fx}, fy={fy}); is the camera calibrated?')
    return fx, fy, cx, cy, int(msg.width), int(msg.height)


def intrinsics_to_camera_info(f: MessageFactory, fx: float, fy: float, cx: float, cy: float, width: int,
                              height: int, header: Any, distortion: np.ndarray | None = None,
                              distortion_model: str = 'plumb_bob') -> Any:
    """Pinhole ``sensor_msgs/CameraInfo`` (pixels; no rectification, identity R, P = [K | 0])."""
    if not (fx > 0 and fy > 0) or width < 1 or height < 1:
        raise ValueError(f'invalid intrinsics fx={fx}, fy={fy}, size {width} x {height}')
    d = np.zeros(5) if distortion is None else np.asarray(distortion, dtype=np.float64)
    k = np.array([fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0])
    p = np.array([fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0])
    roi = f.new('sensor_msgs/msg/RegionOfInterest', x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return f.new('sensor_msgs/msg/CameraInfo', header=header, height=int(height), width=int(width),
                 distortion_model=distortion_model, d=f.seq(d, np.float64), k=f.fixed(k, np.float64),
                 r=f.fixed(np.eye(3), np.float64), p=f.fixed(p, np.float64), binning_x=0, binning_y=0, roi=roi)


# --------------------------------------------------------------------------- grids
def map_meta_data_to_geometry(info: Any, frame_id: str = '') -> GridGeometry:
    """``nav_msgs/MapMetaData`` → :class:`GridGeometry`: the origin pose (position **and**
    orientation) is the grid's pose in ``frame_id`` (see :mod:`gpis_grasp_ros.core.grid`).

    The float32 ``resolution`` is read back as the shortest decimal with the same float32 value.
    A non-unit or non-finite orientation quaternion raises ValueError.
    """
    q = info.origin.orientation
    pos = info.origin.position
    # resolution is float32 on the wire: take the shortest decimal that maps to the same float32,
    # so 0.001 written comes back as 0.001 (not 0.0010000000474974513).
    resolution = float(str(np.float32(info.resolution)))
    quat = np.array([float(q.x), float(q.y), float(q.z), float(q.w)])
    position = np.array([float(pos.x), float(pos.y), float(pos.z)])
    if np.allclose(quat, [0.0, 0.0, 0.0, 1.0], atol=1e-12):  # fronto-parallel: exact, no round-off
        return GridGeometry(position[0], position[1], resolution, int(info.width), int(info.height),
                            position[2], str(frame_id))
    return GridGeometry.from_corner_pose(position, quat, resolution, int(info.width), int(info.height),
                                         str(frame_id))


def geometry_to_map_meta_data(f: MessageFactory, geometry: GridGeometry, load_time_ns: int = 0) -> Any:
    """:class:`GridGeometry` → ``nav_msgs/MapMetaData`` whose origin is the grid's full pose."""
    position, quat = geometry.corner_pose()
    origin = f.new('geometry_msgs/msg/Pose',
                   position=f.new('geometry_msgs/msg/Point', x=float(position[0]), y=float(position[1]),
                                  z=float(position[2])),
                   orientation=f.new('geometry_msgs/msg/Quaternion', x=float(quat[0]), y=float(quat[1]),
                                     z=float(quat[2]), w=float(quat[3])))
    return f.new('nav_msgs/msg/MapMetaData', map_load_time=time_msg(f, load_time_ns),
                 resolution=float(geometry.resolution), width=int(geometry.width), height=int(geometry.height),
                 origin=origin)


def _grid_values(msg: Any, dtype: Any, what: str) -> tuple[np.ndarray, GridGeometry]:
    geometry = map_meta_data_to_geometry(msg.info, str(msg.header.frame_id))
    values = _as_array(msg.data, dtype)
    if values.size != geometry.width * geometry.height:
        raise ValueError(f'{what} has {values.size} values, expected width {geometry.width} * height '
                         f'{geometry.height} = {geometry.width * geometry.height}')
    return values.reshape(geometry.height, geometry.width), geometry


def occupancy_grid_to_numpy(msg: Any) -> tuple[np.ndarray, GridGeometry]:
    """``nav_msgs/OccupancyGrid`` → (int8 (H, W) array: 0 free, 100 occupied, -1 unknown; geometry)."""
    values, geometry = _grid_values(msg, np.int8, 'OccupancyGrid')
    return values.copy(), geometry


def numpy_to_occupancy_grid(f: MessageFactory, occ: np.ndarray, geometry: GridGeometry, header: Any = None) -> Any:
    """(H, W) occupancy (int8-compatible values in [-1, 100]) → ``nav_msgs/OccupancyGrid``."""
    occ = np.asarray(occ)
    if occ.shape != geometry.shape:
        raise ValueError(f'occupancy shape {occ.shape} differs from grid shape {geometry.shape}')
    if occ.size and (occ.min() < -1 or occ.max() > 100):
        raise ValueError('occupancy values must lie in [-1, 100]')
    header = _header_or_default(f, header, geometry.frame_id)
    return f.new('nav_msgs/msg/OccupancyGrid', header=header, info=geometry_to_map_meta_data(f, geometry),
                 data=f.seq(occ.astype(np.int8), np.int8))


def float_grid_to_numpy(msg: Any, expect_unit: str | None = None) -> tuple[np.ndarray, GridGeometry]:
    """``gpis_grasp_interfaces/FloatGrid`` → (float32 (H, W) array in ``msg.unit``, geometry).

    With ``expect_unit`` set, a different ``msg.unit`` raises ValueError.
    """
    if expect_unit is not None and str(msg.unit) != expect_unit:
        raise ValueError(f"FloatGrid unit is '{msg.unit}', expected '{expect_unit}'")
    values, geometry = _grid_values(msg, np.float32, 'FloatGrid')
    return values.copy(), geometry


def numpy_to_float_grid(f: MessageFactory, arr: np.ndarray, geometry: GridGeometry, header: Any = None,
                        unit: str = 'm') -> Any:
    """(H, W) float array (values in ``unit``) → ``gpis_grasp_interfaces/FloatGrid``."""
    arr = np.asarray(arr, dtype=np.float32)
    if arr.shape != geometry.shape:
        raise ValueError(f'array shape {arr.shape} differs from grid shape {geometry.shape}')
    header = _header_or_default(f, header, geometry.frame_id)
    return f.new('gpis_grasp_interfaces/msg/FloatGrid', header=header, info=geometry_to_map_meta_data(f, geometry),
                 unit=str(unit), data=f.seq(arr, np.float32))


# --------------------------------------------------------------------------- geometry messages
def point_stamped(f: MessageFactory, xyz: np.ndarray, header: Any) -> Any:
    """``geometry_msgs/PointStamped`` at ``xyz`` (m)."""
    x, y, z = (float(v) for v in np.asarray(xyz, dtype=np.float64).ravel()[:3])
    return f.new('geometry_msgs/msg/PointStamped', header=header, point=f.new('geometry_msgs/msg/Point', x=x, y=y, z=z))


def point_stamped_to_numpy(msg: Any) -> np.ndarray:
    """``geometry_msgs/PointStamped`` (or Point) → (3,) float64 metres."""
    p = msg.point if hasattr(msg, 'point') else msg
    return np.array([float(p.x), float(p.y), float(p.z)])


def polygon_stamped(f: MessageFactory, xy: np.ndarray, z: float, header: Any) -> Any:
    """``geometry_msgs/PolygonStamped`` with vertices ``xy`` (N, 2) m, all at depth ``z`` (m)."""
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(f'polygon vertices must have shape (N, 2), got {xy.shape}')
    pts = [f.new('geometry_msgs/msg/Point32', x=float(x), y=float(y), z=float(z)) for x, y in xy.astype(np.float32)]
    return f.new('geometry_msgs/msg/PolygonStamped', header=header, polygon=f.new('geometry_msgs/msg/Polygon',
                                                                                points=pts))


def polygon_stamped_to_numpy(msg: Any) -> np.ndarray:
    """``geometry_msgs/PolygonStamped`` (or Polygon) → (N, 3) float64 vertices (m)."""
    poly = msg.polygon if hasattr(msg, 'polygon') else msg
    return np.array([[float(p.x), float(p.y), float(p.z)] for p in poly.points], dtype=np.float64).reshape(-1, 3)


# --------------------------------------------------------------------------- GPIS model
def posterior_to_gpis_model(posterior: Any, header: Any, f: MessageFactory, com_samples: int = 200,
                            object_height: float = 0.0) -> Any:
    """:class:`~gpis_grasp_ros.core.gpis.GpisPosterior` → ``gpis_grasp_interfaces/GpisModel``.

    Carries the kernel, the training data - values and gradient observations - (so a consumer can rebuild the
    exact posterior with
    :func:`gpis_model_to_posterior`), mean and variance on the grid, and the centre of mass of the
    mean shape with its RMS spread over ``com_samples`` posterior samples (seeded, deterministic), and the
    object's measured ``object_height`` (m above the table, 0 = unknown; not part of the posterior), and the
    posterior's ``obstacles`` (``obstacle_distance``, empty without). ``f`` builds the messages (rosbags or
    rclpy flavour). Lengths in m, variances in m^2.
    """
    height = float(object_height)
    if not (math.isfinite(height) and height >= 0):
        raise ValueError(f'object_height must be a finite height >= 0 m (0 = unknown), got {object_height}')
    g = posterior.geometry
    p = posterior.params
    com_xy = np.asarray(posterior.center_of_mass(), dtype=np.float64)
    com_std = float(posterior.com_spread(n=com_samples, rng=np.random.default_rng(0))) if com_samples > 0 else 0.0
    return f.new(
        'gpis_grasp_interfaces/msg/GpisModel', header=header, info=geometry_to_map_meta_data(f, g),
        resolution=float(g.resolution), signal_variance=float(p.signal_variance), length_scale=float(p.length_scale),
        prior_mean=float(p.prior_mean), jitter=float(getattr(posterior, 'jitter', 0.0)),
        hyperparameters_optimized=bool(getattr(posterior, 'hyperparameters_optimized', False)),
        train_x=f.seq(np.asarray(posterior.train_xy, dtype=np.float64).ravel(), np.float64),
        train_y=f.seq(np.asarray(posterior.train_y, dtype=np.float64), np.float64),
        train_noise_variance=f.seq(np.asarray(posterior.train_noise, dtype=np.float64), np.float64),
        train_grad_x=f.seq(np.asarray(getattr(posterior, 'train_grad_xy', np.zeros((0, 2))), dtype=np.float64).ravel(),
                           np.float64),
        train_grad_axis=f.seq(np.asarray(getattr(posterior, 'train_grad_axis', np.zeros(0)), dtype=np.uint8), np.uint8),
        train_grad=f.seq(np.asarray(getattr(posterior, 'train_grad', np.zeros(0)), dtype=np.float64), np.float64),
        train_grad_noise_variance=f.seq(np.asarray(getattr(posterior, 'train_grad_noise', np.zeros(0)),
                                                   dtype=np.float64), np.float64),
        mean=f.seq(np.asarray(posterior.mean, dtype=np.float64), np.float64),
        variance=f.seq(np.asarray(posterior.variance, dtype=np.float64), np.float64),
        obstacle_distance=f.seq(np.zeros(0) if getattr(posterior, 'obstacles', None) is None
                                else np.asarray(posterior.obstacles, dtype=np.float64), np.float64),
        center_of_mass=f.new('geometry_msgs/msg/Point', x=float(com_xy[0]), y=float(com_xy[1]), z=float(g.z)),
        center_of_mass_std=com_std, object_height=height)


def gpis_model_object_height(msg: Any) -> float:
    """``GpisModel.object_height`` (m above the table) or 0 (unknown) when absent, non-finite or negative."""
    height = float(getattr(msg, 'object_height', 0.0) or 0.0)
    return height if math.isfinite(height) and height > 0 else 0.0


def gpis_model_to_posterior(msg: Any) -> Any:
    """``gpis_grasp_interfaces/GpisModel`` → :class:`~gpis_grasp_ros.core.gpis.GpisPosterior`.

    The grid uses the float64 ``resolution`` field when set (``info.resolution`` is float32).
    The posterior (mean, variance, gradient, sampling factor) is rebuilt from the kernel and
    training data (values and gradient observations; a model without gradient arrays is a
    value-only GP) with :func:`gpis_grasp_ros.core.gpis.posterior_from_data`; ValueError on
    inconsistent array lengths or invalid hyperparameters.
    """
    from gpis_grasp_ros.core import gpis

    geometry = map_meta_data_to_geometry(msg.info, str(msg.header.frame_id))
    resolution = float(getattr(msg, 'resolution', 0.0) or 0.0)  # float64 copy of info.resolution
    if resolution > 0:
        if abs(resolution - geometry.resolution) > 1e-6 * resolution:
            raise ValueError(f'GpisModel.resolution {resolution} m disagrees with info.resolution '
                             f'{geometry.resolution} m')
        geometry = replace(geometry, resolution=resolution)
    train_x = _as_array(msg.train_x, np.float64)
    train_y = _as_array(msg.train_y, np.float64)
    noise = _as_array(msg.train_noise_variance, np.float64)
    n = train_y.size
    if n == 0:
        raise ValueError('GpisModel has no training data')
    if train_x.size != 2 * n or noise.size != n:
        raise ValueError(f'GpisModel training arrays disagree: train_x has {train_x.size} values (expected 2 * '
                         f'{n}), train_noise_variance {noise.size} (expected {n})')
    cells = geometry.width * geometry.height
    for name in ('mean', 'variance'):
        size = _as_array(getattr(msg, name), np.float64).size
        if size not in (0, cells):
            raise ValueError(f'GpisModel.{name} has {size} values, expected width * height = {cells}')
    c, ell = float(msg.signal_variance), float(msg.length_scale)
    if not (np.isfinite(c) and c > 0 and np.isfinite(ell) and ell > 0):
        raise ValueError(f'GpisModel needs positive signal_variance and length_scale, got {c}, {ell}')
    if not (np.isfinite(noise).all() and (noise >= 0).all() and np.isfinite(train_x).all()
            and np.isfinite(train_y).all()):
        raise ValueError('GpisModel training data must be finite with non-negative noise variances')
    grad_x = _as_array(getattr(msg, 'train_grad_x', ()), np.float64)
    grad_axis = _as_array(getattr(msg, 'train_grad_axis', ()), np.uint8).astype(np.int64)
    grad = _as_array(getattr(msg, 'train_grad', ()), np.float64)
    grad_noise = _as_array(getattr(msg, 'train_grad_noise_variance', ()), np.float64)
    k = grad.size
    if grad_x.size != 2 * k or grad_axis.size != k or grad_noise.size != k:
        raise ValueError(f'GpisModel gradient arrays disagree: train_grad has {k} values, train_grad_x '
                         f'{grad_x.size} (expected {2 * k}), train_grad_axis {grad_axis.size}, '
                         f'train_grad_noise_variance {grad_noise.size} (expected {k})')
    if k and not (np.isfinite(grad_x).all() and np.isfinite(grad).all() and np.isfinite(grad_noise).all()
                  and (grad_noise >= 0).all() and np.isin(grad_axis, (0, 1)).all()):
        raise ValueError('GpisModel gradient observations must be finite with axis 0 or 1 and non-negative noise')
    obstacles = _as_array(getattr(msg, 'obstacle_distance', ()), np.float64)
    if obstacles.size not in (0, cells) or not np.isfinite(obstacles).all():
        raise ValueError(f'GpisModel.obstacle_distance has {obstacles.size} values, expected none or width * height '
                         f'= {cells}, all finite')
    kp = gpis.KernelParams(signal_variance=c, length_scale=ell, prior_mean=float(msg.prior_mean))
    posterior = gpis.posterior_from_data(geometry, kp, train_x.reshape(-1, 2), train_y, noise, float(msg.jitter),
                                         train_grad_xy=grad_x.reshape(-1, 2), train_grad_axis=grad_axis,
                                         train_grad=grad, train_grad_noise=grad_noise,
                                         hyperparameters_optimized=bool(msg.hyperparameters_optimized))
    if obstacles.size:
        posterior = replace(posterior, obstacles=obstacles.reshape(geometry.shape))
    return posterior

