"""segmentation_node: camera frames of an object on a table → occupancy grid + noise map.

Subscribes either ``camera/depth/points`` (organized XYZRGB PointCloud2) or
``camera/rgb/image_raw`` + ``camera/depth/image_raw`` + ``camera/rgb/camera_info`` (parameter
``input_mode``), averages ``frames_to_average`` frames (paper section III-B) and publishes latched
``object/occupancy`` (nav_msgs/OccupancyGrid: 0..100, -1 = no depth return, counted as object but
not used for GPIS training) and ``object/noise_map`` (gpis_grasp_interfaces/FloatGrid, m^2 per
cell: variance of the cell's SDF value; NaN = not used for training), stamped with the newest
frame's stamp and the camera frame. The grids lie in the table plane: their ``info.origin`` /
geometry carry the full pose (position and orientation) in the camera frame.

Perception for a tilted head camera (issue 12, :mod:`gpis_grasp_ros.core.sensing`): robust
table-plane fit (or ``table_plane``), region of interest (``roi_px`` / ``roi_table``), one
``target`` object isolated in the table plane, ``sensor_model`` noise. When no grid can be made
(no plane, plane edge-on, empty table, target point on no object, target cut by the image border
or too wide for ``max_opening``) nothing is published; the reason is logged and published on the
latched ``segmentation/status`` (std_msgs/String, ``'failed: <reason>'``; ``'ok: <summary>'``
after each publication). With the grids it publishes latched ``object/top``
(geometry_msgs/PointStamped, same stamp and frame): the centre of the grid lifted to the target's
measured height above the table along the normal (camera frame, m; on the plane = height unknown);
gpis_node puts that height into ``GpisModel.object_height`` for the planner's ``grasp_height``.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from geometry_msgs.msg import PointStamped
from nav_msgs.msg import OccupancyGrid
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import String

from gpis_grasp_interfaces.msg import FloatGrid
from gpis_grasp_ros.core import noise_model, pipeline, sensing
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.ros import conversions, validation
from gpis_grasp_ros.ros.nodes.common import (
    LATCHED_QOS,
    GuardedNode,
    declare,
    guarded,
    log_startup,
    run_node,
    sensor_qos,
    watch_parameters,
)

MAX_PENDING_IMAGES = 30


def _same_camera(a: sensing.CameraIntrinsics, b: sensing.CameraIntrinsics, tol_px: float = 0.5) -> bool:
    """Intrinsics equal up to ``tol_px`` (those recovered from each cloud differ by rounding)."""
    return (a.width, a.height) == (b.width, b.height) and bool(np.allclose(
        [a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], atol=tol_px))


def _optional_box(values: list[float], name: str) -> tuple[float, ...] | None:
    """A 4-number parameter where all zeros means 'not given'."""
    values = [float(v) for v in values]
    if len(values) != 4:
        raise ValueError(f"parameter '{name}' must have 4 numbers (all 0 = not given), got {values}")
    return None if not any(values) else tuple(values)


def perception_parameters(node: Node, defaults: sensing.SensingParams) -> dict:
    """Declare the table / target / sensor parameters (issue 12) and return them as SensingParams fields."""
    model = declare(node, 'sensor_model', 'carmine',
                    "depth-noise model: 'carmine' (PrimeSense), 'realsense_d400' (stereo, sigma_z ~ z^2) or "
                    "'custom' (sensor_sigma_* / sensor_quantisation_* below)",
                    choices=list(noise_model.SENSOR_MODELS), read_only=True)
    custom = noise_model.SensorModel(
        'custom',
        declare(node, 'sensor_sigma_constant', 0.0012, "custom sensor: c0 (m) in sigma_z = c0 + c1 (z - z_ref)^2 + "
                'c2 z^2', low=0.0, high=1.0, read_only=True),
        declare(node, 'sensor_sigma_quadratic', 0.0019, 'custom sensor: c1 (1/m)', low=0.0, high=1.0, read_only=True),
        declare(node, 'sensor_sigma_reference_depth', 0.4, 'custom sensor: z_ref (m)', low=0.0, high=10.0,
                read_only=True),
        declare(node, 'sensor_sigma_stereo', 0.0, 'custom sensor: c2 (1/m)', low=0.0, high=1.0, read_only=True),
        declare(node, 'sensor_quantisation_quadratic', 0.00285, 'custom sensor: q2 (1/m) in q = q2 z^2 + q0',
                low=0.0, high=1.0, read_only=True),
        declare(node, 'sensor_quantisation_constant', 0.0, 'custom sensor: q0 (m)', low=0.0, high=1.0,
                read_only=True),
        declare(node, 'sensor_occluder_x', 0.0, 'custom sensor: x (m, camera frame) of its projector or second '
                'imager, whose shadow has no return (0 = none; carmine 0.075, realsense_d400 0.050)',
                low=-1.0, high=1.0, read_only=True))
    plane = _optional_box(declare(node, 'table_plane', [0.0, 0.0, 0.0, 0.0],
                                  'table plane a x + b y + c z + d = 0 in the camera frame (m); all 0 = fit it '
                                  '(robust MSAC over the whole cloud)'), 'table_plane')
    target = declare(node, 'target', defaults.target,
                     "which object to model: 'largest', 'nearest_center' (of the image), 'pixel' or 'table' "
                     '(the object containing target_point)', choices=list(sensing.TARGET_MODES))
    point = [float(v) for v in declare(node, 'target_point', [0.0, 0.0],
                                       "target 'pixel': (u, v) px; target 'table': (x, y) m in the table frame")]
    return dict(
        sensor=custom if model == 'custom' else noise_model.SensorModel.named(model),
        table_plane=plane,
        roi_px=_optional_box(declare(node, 'roi_px', [0.0, 0.0, 0.0, 0.0],
                                     'region of interest (u_min, v_min, u_max, v_max) px; all 0 = whole image'),
                             'roi_px'),
        roi_table=_optional_box(declare(node, 'roi_table', [0.0, 0.0, 0.0, 0.0],
                                        'region of interest (x_min, y_min, x_max, y_max) m in the table frame; '
                                        'all 0 = whole table'), 'roi_table'),
        target=target,
        target_point=tuple(point) if target in ('pixel', 'table') else None,
        max_opening_m=declare(node, 'max_opening', float(defaults.max_opening_m),
                              'gripper opening (m): a target with no part narrower is refused (0 = no check)',
                              low=0.0, high=2.0),
        max_tilt_deg=declare(node, 'max_tilt_deg', float(defaults.max_tilt_deg),
                             'a table plane tilted more than this from the optical axis is refused (edge-on)',
                             low=1.0, high=89.0),
    )


def target_needs_point(target: str) -> bool:
    """Whether the target mode reads target_point."""
    return target in ('pixel', 'table')


@dataclass(frozen=True)
class BurstConfig:
    """How frames are grouped into one estimate (see :class:`SegmentationNode`)."""

    frames_to_average: int
    min_frames: int
    burst_timeout: float
    max_stamp_gap: float
    limits: validation.Limits


class SegmentationNode(GuardedNode):
    """Accumulates frames and runs :func:`gpis_grasp_ros.core.sensing.segment_frames`.

    **Bursts.** Frames are collected until ``frames_to_average`` arrived, or the burst ends (no
    frame for ``burst_timeout`` s): then an estimate is made from the frames collected if there
    are at least ``min_frames`` (the log line and ``segmentation/status`` say how many were used).
    Frames of two passes are never mixed: when header stamps go backwards (a replay restarting) or
    jump by more than ``max_stamp_gap`` s, the frames collected so far are finished as their own
    burst first. So a complete replay of a bag gives exactly the offline pipeline's grid, and a
    replay that lost a few best-effort frames still gives an estimate (from fewer frames).

    **Camera input QoS.** ``input_reliability: best_effort`` (default, like camera drivers'
    sensor-data QoS) matches every publisher but may lose frames of large messages on a busy
    link; ``reliable`` matches only reliable publishers (e.g. ``gpis-grasp play --reliable``) and
    loses nothing on loopback.
    """

    def __init__(self, **kwargs) -> None:
        super().__init__('segmentation_node', **kwargs)
        lim = validation.Limits()
        self.input_mode = declare(self, 'input_mode', 'cloud',
                                  "'cloud': camera/depth/points; 'images': rgb + depth images + camera_info",
                                  choices=['cloud', 'images'], read_only=True)
        self.frames_to_average = declare(self, 'frames_to_average', 10, 'frames averaged per estimate (paper: 10)',
                                         low=1, high=1000)
        reliability = declare(self, 'input_reliability', 'best_effort',
                              "QoS reliability of the camera subscriptions ('best_effort' = sensor data)",
                              choices=['best_effort', 'reliable'], read_only=True)
        defaults = sensing.SensingParams()
        self.params = sensing.SensingParams(
            grid_size=declare(self, 'grid_size', defaults.grid_size, 'M: cells per side of the M x M grid (paper: 25)',
                              low=4, high=100),
            margin=declare(self, 'grid_margin', float(defaults.margin),
                           'margin around the object bounding box, as a fraction of its size', low=0.0, high=5.0),
            height_threshold=declare(self, 'height_threshold', float(defaults.height_threshold),
                                     'depth mask: minimum height above the table (m)', low=0.0, high=0.5),
            color_threshold=declare(self, 'color_threshold', float(defaults.color_threshold),
                                    'RGB mask: minimum distance from the table colour\'s shadow line (0-255 units); '
                                    '0 = adaptive to the table texture seen on the fitted plane',
                                    low=0.0, high=442.0),
            chroma_z_min=declare(self, 'chroma_z_min', float(defaults.chroma_z_min),
                                 'clear targets: grow the target over table-level pixels this many robust sigmas '
                                 'off the table\'s chromaticity, as colour-only evidence (0 = off)',
                                 low=0.0, high=100.0),
            see_through_test=declare(self, 'see_through_test', bool(defaults.see_through_test),
                                     'a return behind the solid under a point seen above the table (a clear part '
                                     'seen through) is moved to where its ray enters that solid; false: kept '
                                     'where the sensor put it'),
            shadow_test=declare(self, 'shadow_test', bool(defaults.shadow_test),
                                'no-return, table-coloured pixels on table the sensor\'s projector or second imager '
                                'cannot see beside an object (sensor_model\'s occluder), where the visual hull cannot '
                                'tell them from the object (a near top-down view), are unmeasured table; false: '
                                'missing = object'),
            clear_body_prism=declare(self, 'clear_body_prism', bool(defaults.clear_body_prism),
                                     'a clear target (under a quarter of it seen in depth) is the prism under its '
                                     'silhouette, of the height at which it is as narrow as high or as deep as wide '
                                     '(the lower); false: the table '
                                     'seen through it stays where its rays meet the table'),
            clear_body_height_m=declare(self, 'clear_body_height', float(defaults.clear_body_height_m),
                                        'known height (m) of a clear target body, e.g. from a catalogue of the '
                                        'objects, instead of the priors (0 = the priors; they assume vertical walls '
                                        'and put a round body lying on the table, a bottle, too low)',
                                        low=0.0, high=float(defaults.max_object_height_m)),
            train_clear_body=declare(self, 'train_clear_body', bool(defaults.train_clear_body),
                                     'the clear body\'s prism cells are GPIS training points (object, SDF variance '
                                     'of full disagreement); false: unknown cells, the prior governs them'),
            **perception_parameters(self, defaults),
        )
        declare(self, 'min_frames', 3, 'fewest frames of a burst that make an estimate when the burst ends '
                'before frames_to_average frames arrived', low=1, high=1000)
        declare(self, 'burst_timeout', 1.5, 'a burst ends when no frame arrived for this long (s)', low=0.05, high=60.0)
        declare(self, 'max_stamp_gap', 1.0, 'frames whose header stamps are further apart than this (s), or go '
                'backwards, belong to different bursts', low=0.01, high=3600.0)
        declare(self, 'max_image_pixels', lim.max_image_pixels, 'largest camera frame accepted (pixels); larger '
                'messages are rejected before anything is allocated', low=1, high=50_000_000)
        self._base_params = self.params
        self.burst: BurstConfig = watch_parameters(self, self._build_config, self._apply_config)[1]
        self._frames: list[tuple[np.ndarray, np.ndarray]] = []
        self._last_stamp_ns = 0
        self._last_arrival = 0.0
        self._stamp = None
        self._frame_id = ''
        self._intrinsics = None
        self._intrinsics_used = None
        self._pending_rgb: dict[int, Image] = {}
        self._pending_depth: dict[int, Image] = {}
        self._lock = threading.Lock()

        qos = sensor_qos(reliability)
        if self.input_mode == 'cloud':
            self.create_subscription(PointCloud2, 'camera/depth/points',
                                     guarded(self, 'camera/depth/points', self._on_cloud), qos)
        else:
            self.create_subscription(Image, 'camera/rgb/image_raw',
                                     guarded(self, 'camera/rgb/image_raw', self._on_rgb), qos)
            self.create_subscription(Image, 'camera/depth/image_raw',
                                     guarded(self, 'camera/depth/image_raw', self._on_depth), qos)
            self.create_subscription(CameraInfo, 'camera/rgb/camera_info',
                                     guarded(self, 'camera/rgb/camera_info', self._on_info), qos)
        self.occupancy_pub = self.create_publisher(OccupancyGrid, 'object/occupancy', LATCHED_QOS)
        self.noise_pub = self.create_publisher(FloatGrid, 'object/noise_map', LATCHED_QOS)
        #: the target's top: grid centre at the measured object height (published before the grids)
        self.top_pub = self.create_publisher(PointStamped, 'object/top', LATCHED_QOS)
        #: latched outcome of the last segmentation: 'ok: ...' or 'failed: <reason>' (nothing published then)
        self.status_pub = self.create_publisher(String, 'segmentation/status', LATCHED_QOS)
        self.create_timer(0.05, self._on_burst_timer)
        inputs = (['camera/depth/points'] if self.input_mode == 'cloud' else
                  ['camera/rgb/image_raw', 'camera/depth/image_raw', 'camera/rgb/camera_info'])
        log_startup(self, inputs, ['object/occupancy', 'object/noise_map', 'object/top', 'segmentation/status'],
                    ['input_mode', 'input_reliability', 'frames_to_average', 'min_frames', 'burst_timeout',
                     'grid_size', 'target', 'sensor_model'])

    # ------------------------------------------------------------------ parameters
    def _build_config(self, v: dict[str, Any]) -> tuple[sensing.SensingParams, BurstConfig]:
        """Parameter values → (SensingParams, BurstConfig); ValueError names the parameter."""
        target = str(v['target'])
        params = replace(self._base_params, grid_size=int(v['grid_size']), margin=float(v['grid_margin']),
                         height_threshold=float(v['height_threshold']), color_threshold=float(v['color_threshold']),
                         table_plane=_optional_box(v['table_plane'], 'table_plane'),
                         roi_px=_optional_box(v['roi_px'], 'roi_px'),
                         roi_table=_optional_box(v['roi_table'], 'roi_table'), target=target,
                         target_point=(tuple(float(x) for x in v['target_point'])
                                       if target in ('pixel', 'table') else None),
                         max_opening_m=float(v['max_opening']), max_tilt_deg=float(v['max_tilt_deg']),
                         chroma_z_min=float(v['chroma_z_min']),
                         clear_body_prism=bool(v['clear_body_prism']), train_clear_body=bool(v['train_clear_body']),
                         clear_body_height_m=float(v['clear_body_height']),
                         see_through_test=bool(v['see_through_test']), shadow_test=bool(v['shadow_test']))
        if target_needs_point(target) and len(v['target_point']) != 2:
            raise ValueError(f"target '{target}' needs target_point with 2 numbers")
        # min_frames above frames_to_average means: only complete bursts make an estimate
        burst = BurstConfig(frames_to_average=int(v['frames_to_average']),
                            min_frames=min(int(v['min_frames']), int(v['frames_to_average'])),
                            burst_timeout=float(v['burst_timeout']), max_stamp_gap=float(v['max_stamp_gap']),
                            limits=validation.Limits(max_image_pixels=int(v['max_image_pixels'])))
        return params, burst

    def _apply_config(self, config: tuple[sensing.SensingParams, BurstConfig]) -> None:
        self.params, self.burst = config
        self.frames_to_average = self.burst.frames_to_average

    # ------------------------------------------------------------------ inputs
    def _on_cloud(self, msg: PointCloud2) -> None:
        try:
            validation.check_pointcloud(msg, self.burst.limits)
            xyz, rgb = messages.pointcloud2_to_xyz_rgb(msg)
            rgb_f, depth_f, intrinsics = sensing.frames_from_clouds(xyz[None], rgb[None])
            lim = self.burst.limits
            if not all(np.isfinite(f) and lim.min_focal_px <= f <= lim.max_focal_px
                       for f in (intrinsics.fx, intrinsics.fy)):
                raise ValueError(f'the points give implausible focal lengths fx={intrinsics.fx:.3g}, '
                                 f'fy={intrinsics.fy:.3g} px (x, y, z are not an organized camera cloud)')
        except ValueError as exc:
            self.reject(f'ignoring PointCloud2 on camera/depth/points: {exc}')
            return
        self._add_frame(rgb_f[0], depth_f[0], intrinsics, msg.header)

    def _on_info(self, msg: CameraInfo) -> None:
        try:
            self._intrinsics = sensing.CameraIntrinsics(*validation.check_camera_info(msg, self.burst.limits))
        except (ValueError, TypeError) as exc:
            self.reject(f'ignoring CameraInfo: {exc}')

    def _on_rgb(self, msg: Image) -> None:
        try:
            validation.check_image(msg, self.burst.limits, 'Image camera/rgb/image_raw')
        except ValueError as exc:
            self.reject(f'ignoring {exc}')
            return
        self._pair(msg, self._pending_rgb, self._pending_depth, rgb_first=True)

    def _on_depth(self, msg: Image) -> None:
        try:
            validation.check_image(msg, self.burst.limits, 'Image camera/depth/image_raw')
        except ValueError as exc:
            self.reject(f'ignoring {exc}')
            return
        self._pair(msg, self._pending_depth, self._pending_rgb, rgb_first=False)

    def _pair(self, msg: Image, mine: dict, other: dict, rgb_first: bool) -> None:
        """Match RGB and depth images by exact stamp (registered depth: same stamp per frame)."""
        key = messages.stamp_to_ns(msg.header.stamp)
        with self._lock:
            partner = other.pop(key, None)
            if partner is None:
                mine[key] = msg
                for stale in sorted(mine)[:-MAX_PENDING_IMAGES]:
                    del mine[stale]
                return
        rgb_msg, depth_msg = (msg, partner) if rgb_first else (partner, msg)
        if self._intrinsics is None:
            self.get_logger().warning('no CameraInfo received yet on camera/rgb/camera_info; frame skipped',
                                      throttle_duration_sec=5.0)
            return
        try:
            rgb = messages.image_to_numpy(rgb_msg)
            depth = messages.image_to_numpy(depth_msg)
            if rgb.ndim != 3 or depth.ndim != 2:
                raise ValueError(f'expected a colour image and a single-channel depth image, got shapes '
                                 f'{rgb.shape} and {depth.shape}')
            if rgb.shape[:2] != depth.shape:
                raise ValueError(f'RGB {rgb.shape[:2]} and depth {depth.shape} sizes differ')
            if rgb_msg.encoding == 'bgr8':
                rgb = rgb[..., ::-1]
        except ValueError as exc:
            self.reject(f'ignoring image pair: {exc}')
            return
        self._add_frame(rgb, depth.astype(np.float64), self._intrinsics, depth_msg.header)

    # ------------------------------------------------------------------ processing
    def _add_frame(self, rgb: np.ndarray, depth: np.ndarray, intrinsics, header) -> None:
        stamp_ns = messages.stamp_to_ns(header.stamp)
        finished = []
        with self._lock:
            burst = self.burst
            if self._frames:
                gap = (stamp_ns - self._last_stamp_ns) * 1e-9
                if gap < 0 or gap > burst.max_stamp_gap:
                    why = 'stamps went backwards' if gap < 0 else f'stamps jumped by {gap:.2f} s'
                    finished.append(self._take_burst(f'burst ended: {why}'))
                elif self._frames[0][0].shape != rgb.shape or not _same_camera(self._intrinsics_used, intrinsics):
                    self.get_logger().warning(f'camera geometry changed; dropping {len(self._frames)} frame(s) of '
                                              'the other geometry')
                    self._frames = []
            self._frames.append((rgb, depth))
            self._intrinsics_used = intrinsics
            self._last_stamp_ns, self._last_arrival = stamp_ns, time.monotonic()
            self._stamp, self._frame_id = header.stamp, header.frame_id
            if len(self._frames) >= burst.frames_to_average:
                finished.append(self._take_burst('frames_to_average reached'))
        for item in finished:
            if item is not None:
                self._estimate(*item)

    def _on_burst_timer(self) -> None:
        with self._lock:
            timeout = self.burst.burst_timeout
            if not self._frames or time.monotonic() - self._last_arrival < timeout:
                return
            item = self._take_burst(f'burst ended: no frame for {timeout:g} s')
        if item is not None:
            self._estimate(*item)

    def _take_burst(self, why: str) -> tuple | None:
        """Take the collected frames (caller holds the lock); None when fewer than min_frames."""
        frames, self._frames = self._frames, []
        if len(frames) < self.burst.min_frames:
            if frames:
                self.get_logger().warning(f'{why}: {len(frames)} frame(s) collected, fewer than min_frames='
                                          f'{self.burst.min_frames}; no estimate')
            return None
        return frames, self._intrinsics_used, self._stamp, self._frame_id, why

    def _estimate(self, frames: list, intrinsics, stamp, frame_id: str, why: str) -> None:
        """Segment one burst of frames and publish the grids."""
        rgb_frames = np.stack([f[0] for f in frames])
        depth_frames = np.stack([f[1] for f in frames])
        try:
            result = sensing.segment_frames(rgb_frames, depth_frames, intrinsics, self.params,
                                            frame_id=frame_id)
        except ValueError as exc:
            self.get_logger().warning(f'segmentation failed, nothing published: {exc}')
            self.status_pub.publish(String(data=f'failed: {exc}'))
            return
        factory = conversions.RclpyFactory()
        header_msg = messages.header(factory, messages.stamp_to_ns(stamp), frame_id)
        occ, noise, geometry = pipeline.publishable_grids(result)
        centre = np.array([geometry.origin_x, geometry.origin_y]) + 0.5 * np.array(geometry.size_m)
        self.top_pub.publish(messages.point_stamped(factory, geometry.to_sensor(centre, result.object_height),
                                                    header_msg))
        self.occupancy_pub.publish(messages.numpy_to_occupancy_grid(factory, occ, geometry, header_msg))
        self.noise_pub.publish(messages.numpy_to_float_grid(factory, noise, geometry, header_msg, 'm^2'))
        summary = (f'published {result.geometry.height}x{result.geometry.width} occupancy and noise map from '
                   f'{len(frames)} frames (worth {result.effective_frames:.1f} independent): '
                   f'{result.objects_seen} object(s) on the table, target {result.geometry.size_m[0] * 1000:.0f} mm '
                   f'grid, table tilt {result.table.tilt_deg:.1f} deg, object height '
                   f'{result.object_height * 1000:.1f} mm, {int(result.missing.sum())} missing cells '
                   f'({why})')
        self.get_logger().info(summary)
        self.status_pub.publish(String(data=f'ok: {summary}'))


def main(args: list[str] | None = None) -> int:
    return run_node(SegmentationNode, args)


if __name__ == '__main__':
    main()
