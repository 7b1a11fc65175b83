"""Real RGB-D captures as users have them → bags in the shipped layout (ROS-free).

Inputs (:func:`load_capture`):

* **colour**: any image OpenCV reads (PNG, JPEG, ...), 8-bit, converted to RGB.
* **depth**: a 16-bit PNG in millimetres (0 = no return; ``depth_scale`` m per unit, default
  0.001), a 32-bit float image in metres (TIFF or PFM through OpenCV; OpenEXR ``.exr``, as
  ClearGrasp ships its depth, through the ``openexr`` library: :func:`read_exr`), or a ``.npy``
  array (integer = millimetres, float = metres). Non-finite and <= 0 values are "no return" (NaN).
* **intrinsics** (:func:`load_intrinsics`): a YAML or JSON file (or mapping) with ``fx, fy, cx, cy``
  (or ``_fx, _fy, _cx, _cy``, the JSON form many grasping data sets ship) and optionally
  ``width, height`` (aliases ``xres, yres``), or CameraInfo-like values: ``K`` / ``k``
  (row-major 3 x 3) with ``width``, ``height``, or the ROS camera_calibration layout
  ``camera_matrix: {data: [...]}`` with ``image_width``, ``image_height``. Images must be
  registered (depth in the colour camera's frame) and undistorted.

Optional **crop** (pixel box) and **downscale** factor keep bags small; the intrinsics follow
(crop: cx, cy shift; scaling by s: f' = s f, c' = s (c + 0.5) - 0.5). Depth is downscaled by
taking the nearest sample (no mixing of foreground and background depths), colour by area
averaging.

Optional **ground truth** (:func:`~gpis_grasp_ros.data.ground_truth.ground_truth_from_mask`, construction in
docs/ground-truth.md) for evaluation: the target's footprint on the table plane fitted to the capture's own
depth exactly as :func:`~gpis_grasp_ros.core.sensing.segment_frames` fits it, from a target mask and a depth
image of the true shape. ``import-rgbd`` builds it from the *cropped, unscaled* mask and true depth (the table
plane is the one fitted to the bag's scaled capture, so the frames agree): halving a mask doubles its stair steps.

:func:`write_capture_bag` writes one frame (one frame is one frame: no repeats) with the topics
and QoS of the simulated bags (:func:`gpis_grasp_ros.sim.scene.write_scene_bag`).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from gpis_grasp_ros.core.noise_model import SensorModel
from gpis_grasp_ros.core.sensing import CameraIntrinsics
from gpis_grasp_ros.core.table_frame import TableFrame, fit_table_plane
from gpis_grasp_ros.data import bagio, messages
from gpis_grasp_ros.data.bags import BagScene, scene_from_messages
from gpis_grasp_ros.data.ground_truth import GroundTruth, ground_truth_from_mask  # noqa: F401 (this module's API)
from gpis_grasp_ros.data.topics import TOPIC_TYPES, TOPICS

FRAME_ID = 'camera_color_optical_frame'
DEFAULT_START_NS = 1_600_000_000_000_000_000


@dataclass
class Capture:
    """One registered RGB-D frame: rgb (H, W, 3) uint8, depth (H, W) m (NaN = no return), intrinsics."""

    rgb: np.ndarray
    depth: np.ndarray
    intrinsics: CameraIntrinsics


# ------------------------------------------------------------------------------------------ reading
def _check_file(path: str | os.PathLike[str], what: str) -> Path:
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f'{what} file {p} does not exist')
    return p


def load_rgb(path: str | os.PathLike[str]) -> np.ndarray:
    """8-bit colour image → (H, W, 3) uint8 RGB."""
    p = _check_file(path, 'colour image')
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f'{p}: not an image OpenCV can read')
    if img.dtype != np.uint8:
        raise ValueError(f'{p}: colour image must be 8-bit, got {img.dtype}')
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    elif img.shape[2] == 4:
        img = img[..., :3]
    return np.ascontiguousarray(img[..., ::-1])


def depth_to_metres(raw: np.ndarray, depth_scale: float = 0.001, what: str = 'depth') -> np.ndarray:
    """Integer depth (``depth_scale`` m per unit, 0 = no return) or float metres → float64 m, NaN = no return."""
    raw = np.asarray(raw)
    if raw.ndim == 3 and raw.shape[2] == 1:
        raw = raw[..., 0]
    if raw.ndim != 2:
        raise ValueError(f'{what}: expected a single-channel (H, W) depth image, got shape {raw.shape}')
    if np.issubdtype(raw.dtype, np.integer):
        if not (math.isfinite(depth_scale) and depth_scale > 0):
            raise ValueError(f'depth_scale must be positive metres per unit, got {depth_scale}')
        depth = raw.astype(np.float64) * depth_scale
    elif np.issubdtype(raw.dtype, np.floating):
        depth = raw.astype(np.float64)
    else:
        raise ValueError(f'{what}: unsupported depth dtype {raw.dtype}')
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.nan)
    if not np.isfinite(depth).any():
        raise ValueError(f'{what}: no valid depth (all zero / NaN)')
    if np.nanmedian(depth) > 50.0:
        raise ValueError(f'{what}: median depth {np.nanmedian(depth):.0f} m is not plausible; float depth must be in '
                         'metres (give depth_scale for integer millimetre images)')
    return depth


#: Channel names tried, in order, when an EXR holds several channels (ClearGrasp writes depth into R, G and B).
EXR_DEPTH_CHANNELS = ('Z', 'depth', 'Y', 'R')


def read_exr(path: str | os.PathLike[str]) -> np.ndarray:
    """The depth channel of an OpenEXR file as an (H, W) float array, values as stored (no unit change).

    A single-channel file gives that channel; otherwise the first of :data:`EXR_DEPTH_CHANNELS` present.
    Reads with the ``openexr`` package (OpenCV's wheels ship with their EXR reader disabled)."""
    p = _check_file(path, 'depth')
    try:
        import OpenEXR
    except ImportError as exc:
        raise ValueError(f"{p}: reading OpenEXR needs the 'openexr' package (pip install -r requirements.txt)") \
            from exc
    try:
        with OpenEXR.File(str(p), separate_channels=True) as exr:
            channels = {name: np.array(ch.pixels) for name, ch in exr.channels().items()}
    except Exception as exc:  # noqa: BLE001 - the library raises plain RuntimeError/Exception on bad files
        raise ValueError(f'{p}: not an OpenEXR file the openexr library can read ({exc})') from exc
    if len(channels) == 1:
        return next(iter(channels.values()))
    for name in EXR_DEPTH_CHANNELS:
        if name in channels:
            return channels[name]
    raise ValueError(f'{p}: no depth channel among {sorted(channels)} (expected one channel or one of '
                     f'{list(EXR_DEPTH_CHANNELS)})')


def load_depth(path: str | os.PathLike[str], depth_scale: float = 0.001) -> np.ndarray:
    """16-bit PNG (mm), 32-bit float image (m: TIFF, PFM, EXR) or ``.npy`` → (H, W) float64 m, NaN = no return."""
    p = _check_file(path, 'depth')
    if p.suffix.lower() == '.npy':
        raw = np.load(p, allow_pickle=False)
    elif p.suffix.lower() == '.exr':
        raw = read_exr(p)
    else:
        raw = cv2.imread(str(p), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
        if raw is None:
            raise ValueError(f'{p}: not an image OpenCV can read')
        if raw.dtype == np.uint8:
            raise ValueError(f'{p}: an 8-bit image is not a depth image (need 16-bit mm or 32-bit float m)')
    return depth_to_metres(raw, depth_scale, str(p))


def _intrinsics_from_mapping(data: Mapping[str, Any], width: int | None, height: int | None) -> CameraIntrinsics:
    def get(*names: str) -> Any:
        for n in names:
            if n in data and data[n] is not None:
                return data[n]
        return None

    k = get('K', 'k')
    if k is None and isinstance(data.get('camera_matrix'), Mapping):
        k = data['camera_matrix'].get('data')
    if k is not None:
        k = np.asarray(k, dtype=np.float64).ravel()
        if k.size != 9:
            raise ValueError(f'K must have 9 values (row-major 3 x 3), got {k.size}')
        fx, fy, cx, cy = k[0], k[4], k[2], k[5]
    else:
        vals = [get(n, '_' + n) for n in ('fx', 'fy', 'cx', 'cy')]
        if any(v is None for v in vals):
            raise ValueError('intrinsics need fx, fy, cx, cy (or _fx, _fy, _cx, _cy, or K / camera_matrix)')
        fx, fy, cx, cy = (float(v) for v in vals)
    w = get('width', 'xres', 'image_width', '_width')
    h = get('height', 'yres', 'image_height', '_height')
    w = int(w) if w is not None else width
    h = int(h) if h is not None else height
    if w is None or h is None:
        raise ValueError('intrinsics need the image size (width, height) or an image to take it from')
    return CameraIntrinsics(float(fx), float(fy), float(cx), float(cy), int(w), int(h))


def load_intrinsics(source: str | os.PathLike[str] | Mapping[str, Any], width: int | None = None,
                    height: int | None = None) -> CameraIntrinsics:
    """Intrinsics from a YAML or JSON file or a mapping (module docstring); ``width``/``height`` fill a missing
    size."""
    if isinstance(source, Mapping):
        return _intrinsics_from_mapping(source, width, height)
    p = _check_file(source, 'intrinsics')
    text = p.read_text(encoding='utf8')
    if p.suffix.lower() == '.json':
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f'{p}: not valid JSON ({exc})') from exc
        kind = 'JSON object'
    else:
        data = yaml.safe_load(text)
        kind = 'YAML mapping'
    if not isinstance(data, Mapping):
        raise ValueError(f'{p}: expected a {kind} of intrinsics')
    return _intrinsics_from_mapping(data, width, height)


def load_capture(rgb_path: str | os.PathLike[str], depth_path: str | os.PathLike[str],
                 intrinsics: str | os.PathLike[str] | Mapping[str, Any], depth_scale: float = 0.001) -> Capture:
    """Read a registered colour + depth pair and its intrinsics; sizes must agree."""
    rgb = load_rgb(rgb_path)
    depth = load_depth(depth_path, depth_scale)
    if rgb.shape[:2] != depth.shape:
        raise ValueError(f'colour image {rgb.shape[1]} x {rgb.shape[0]} and depth {depth.shape[1]} x '
                         f'{depth.shape[0]} differ in size (register the depth to the colour camera first)')
    intr = load_intrinsics(intrinsics, width=depth.shape[1], height=depth.shape[0])
    if (intr.width, intr.height) != (depth.shape[1], depth.shape[0]):
        raise ValueError(f'intrinsics are for {intr.width} x {intr.height} but the images are '
                         f'{depth.shape[1]} x {depth.shape[0]}')
    return Capture(rgb, depth, intr)


# ------------------------------------------------------------------------------------------ crop and scale
def crop_and_scale(capture: Capture, crop: tuple[int, int, int, int] | None = None, scale: float = 1.0,
                   extra: dict[str, np.ndarray] | None = None) -> tuple[Capture, dict[str, np.ndarray]]:
    """Crop to ``(u0, v0, u1, v1)`` (exclusive end) then scale by ``scale`` (<= 1); intrinsics follow.

    ``extra`` images (e.g. masks, ground-truth depth) get the same crop and nearest-sample scaling."""
    intr = capture.intrinsics
    extra = dict(extra or {})
    rgb, depth = capture.rgb, capture.depth
    fx, fy, cx, cy = intr.fx, intr.fy, intr.cx, intr.cy
    if crop is not None:
        u0, v0, u1, v1 = (int(c) for c in crop)
        if not (0 <= u0 < u1 <= intr.width and 0 <= v0 < v1 <= intr.height):
            raise ValueError(f'crop {crop} is not inside the {intr.width} x {intr.height} image')
        rgb, depth = rgb[v0:v1, u0:u1], depth[v0:v1, u0:u1]
        extra = {k: v[v0:v1, u0:u1] for k, v in extra.items()}
        cx, cy = cx - u0, cy - v0
    if not 0 < scale <= 1:
        raise ValueError(f'scale must be in (0, 1], got {scale}')
    if scale < 1:
        h, w = depth.shape
        nw, nh = max(1, int(round(w * scale))), max(1, int(round(h * scale)))
        sx, sy = nw / w, nh / h
        rgb = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_AREA)
        depth = cv2.resize(depth, (nw, nh), interpolation=cv2.INTER_NEAREST)
        extra = {k: cv2.resize(v, (nw, nh), interpolation=cv2.INTER_NEAREST) for k, v in extra.items()}
        fx, fy, cx, cy = fx * sx, fy * sy, sx * (cx + 0.5) - 0.5, sy * (cy + 0.5) - 0.5
    h, w = depth.shape
    out = Capture(np.ascontiguousarray(rgb), np.ascontiguousarray(depth), CameraIntrinsics(fx, fy, cx, cy, w, h))
    return out, extra


def map_pixel(u: float, v: float, crop: tuple[int, int, int, int] | None, scale: float) -> tuple[float, float]:
    """A pixel of the original image in the cropped and scaled image (same convention as the intrinsics)."""
    if crop is not None:
        u, v = u - crop[0], v - crop[1]
    return scale * (u + 0.5) - 0.5, scale * (v + 0.5) - 0.5


# ------------------------------------------------------------------------------------------ ground truth
def capture_table(capture: Capture, sensor: SensorModel) -> TableFrame:
    """The table plane fitted to the capture's depth exactly as segment_frames fits it (defaults)."""
    points = capture.intrinsics.rays() * capture.depth[..., None]
    valid = np.isfinite(capture.depth)
    return fit_table_plane(points[valid], sensor)


@dataclass
class ImportedCapture:
    """A capture as its bag holds it: the cropped and scaled frame, its ground truth (or None) and the target
    pixel in the frame (or None)."""

    capture: Capture
    truth: GroundTruth | None
    target_px: tuple[float, float] | None


def import_capture(rgb: str | os.PathLike[str], depth: str | os.PathLike[str],
                   intrinsics: str | os.PathLike[str] | Mapping[str, Any], depth_scale: float = 0.001,
                   crop: tuple[int, int, int, int] | None = None, scale: float = 1.0,
                   gt_mask: str | os.PathLike[str] | None = None, gt_depth: str | os.PathLike[str] | None = None,
                   target_px: tuple[float, float] | None = None, sensor: str = 'realsense_d400',
                   frame_id: str = FRAME_ID) -> ImportedCapture:
    """Read a capture, crop and scale it and build the ground truth of the mask component under ``target_px``
    (a pixel of the full-resolution image) from the cropped, unscaled mask and true depth, in the table plane
    fitted to the cropped and scaled frame (module docstring): what ``gpis-grasp import-rgbd`` writes."""
    capture = load_capture(rgb, depth, intrinsics, depth_scale)
    extra = {}
    if gt_mask or gt_depth or target_px:
        if not (gt_mask and gt_depth and target_px):
            raise ValueError('ground truth needs all of --gt-mask, --gt-depth and --target-pixel')
        extra['mask'] = load_rgb(gt_mask)[..., 0]
        extra['true_depth'] = load_depth(gt_depth, depth_scale)
        if extra['mask'].shape != capture.depth.shape or extra['true_depth'].shape != capture.depth.shape:
            raise ValueError('--gt-mask and --gt-depth must have the size of the capture')
    crop = tuple(crop) if crop else None
    small, _ = crop_and_scale(capture, crop, scale)
    truth, target = None, None
    if target_px:
        target = map_pixel(*target_px, crop, scale)
        table = capture_table(small, SensorModel.named(sensor))
        # the ground truth keeps the full resolution: only the crop applies to it (module docstring)
        full, extra = crop_and_scale(capture, crop, 1.0, extra)
        truth = ground_truth_from_mask(full, extra['mask'], extra['true_depth'], map_pixel(*target_px, crop, 1.0),
                                       table, frame_id=frame_id)
    return ImportedCapture(small, truth, target)


def capture_scene(imported: ImportedCapture, frame_id: str = FRAME_ID) -> BagScene:
    """The scene :func:`~gpis_grasp_ros.data.bags.load_bag` would read from the capture's bag (one frame,
    from the cloud), built from the same messages without writing them."""
    f = messages.RosbagsFactory(bagio.get_typestore())
    return scene_from_messages(capture_messages(imported.capture, f, truth=imported.truth, frame_id=frame_id),
                               frames=1, name='imported capture')


# ------------------------------------------------------------------------------------------ writing
def capture_messages(capture: Capture, f: Any, stamp_ns: int = DEFAULT_START_NS,
                     truth: GroundTruth | None = None,
                     frame_id: str = FRAME_ID) -> list[tuple[str, str, int, Any]]:
    """``(topic, msgtype, t_ns, msg)`` of one frame: latched ground truth (if any) at ``stamp_ns``, then
    the camera infos, RGB image, 32FC1 depth image (m, NaN = no return) and the organized XYZRGB cloud."""
    out: list[tuple[str, str, int, Any]] = []
    hdr = messages.header(f, stamp_ns, frame_id)
    if truth is not None:
        out.append((TOPICS['occupancy'], TOPIC_TYPES[TOPICS['occupancy']], stamp_ns,
                    messages.numpy_to_occupancy_grid(f, truth.occupancy, truth.geometry, hdr)))
        out.append((TOPICS['sdf'], TOPIC_TYPES[TOPICS['sdf']], stamp_ns,
                    messages.numpy_to_float_grid(f, truth.sdf, truth.geometry, hdr, 'm')))
        out.append((TOPICS['com'], TOPIC_TYPES[TOPICS['com']], stamp_ns,
                    messages.point_stamped(f, truth.center_of_mass, hdr)))
        if truth.obstacles is not None:
            out.append((TOPICS['obstacles'], TOPIC_TYPES[TOPICS['obstacles']], stamp_ns,
                        messages.numpy_to_float_grid(f, truth.obstacles, truth.geometry, hdr, 'm')))
        pts = [f.new('geometry_msgs/msg/Point32', x=float(x), y=float(y), z=float(z))
               for x, y, z in truth.outline.astype(np.float32)]
        out.append((TOPICS['outline'], TOPIC_TYPES[TOPICS['outline']], stamp_ns,
                    f.new('geometry_msgs/msg/PolygonStamped', header=hdr,
                          polygon=f.new('geometry_msgs/msg/Polygon', points=pts))))
    t = stamp_ns + 1
    h = messages.header(f, t, frame_id)
    i = capture.intrinsics
    info = messages.intrinsics_to_camera_info(f, i.fx, i.fy, i.cx, i.cy, i.width, i.height, h)
    depth32 = capture.depth.astype(np.float32)
    xyz = (i.rays() * capture.depth[..., None]).astype(np.float32)
    out += [(TOPICS['rgb_info'], TOPIC_TYPES[TOPICS['rgb_info']], t, info),
            (TOPICS['rgb'], TOPIC_TYPES[TOPICS['rgb']], t, messages.numpy_to_image(f, capture.rgb, 'rgb8', h)),
            (TOPICS['depth_info'], TOPIC_TYPES[TOPICS['depth_info']], t, info),
            (TOPICS['depth'], TOPIC_TYPES[TOPICS['depth']], t, messages.numpy_to_image(f, depth32, '32FC1', h)),
            (TOPICS['points'], TOPIC_TYPES[TOPICS['points']], t,
             messages.xyz_rgb_to_pointcloud2(f, xyz, capture.rgb, h))]
    return out


def write_capture_bag(capture: Capture, path: str | os.PathLike[str], truth: GroundTruth | None = None,
                      metadata: Mapping[str, Any] | None = None, overwrite: bool = False,
                      frame_id: str = FRAME_ID) -> Path:
    """One-frame MCAP bag of ``capture`` (and its ground truth) with the simulated bags' topics and QoS."""
    ts = bagio.get_typestore()
    meta = {'gpis_grasp_ros.data.rgbd_import': json.dumps(dict(metadata or {}), sort_keys=True)}
    msgs = capture_messages(capture, messages.RosbagsFactory(ts), truth=truth, frame_id=frame_id)
    with bagio.BagWriter(path, typestore=ts, custom_data=meta, overwrite=overwrite) as bag:
        for topic in dict.fromkeys(m[0] for m in msgs):
            latched = topic.startswith('/ground_truth/')
            bag.add_topic(topic, TOPIC_TYPES[topic],
                          bagio.LATCHED_QOS if latched else bagio.SENSOR_QOS)
        for topic, _type, t_ns, msg in msgs:
            bag.write(topic, t_ns, msg)
    return Path(path)


__all__ = ['Capture', 'GroundTruth', 'ImportedCapture', 'capture_messages', 'capture_scene', 'capture_table',
           'crop_and_scale', 'depth_to_metres', 'ground_truth_from_mask', 'import_capture', 'load_capture',
           'load_depth', 'load_intrinsics', 'load_rgb', 'map_pixel', 'read_exr', 'write_capture_bag']
