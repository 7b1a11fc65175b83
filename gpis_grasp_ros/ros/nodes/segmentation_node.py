"""segmentation_node: camera frames of an object on a table → occupancy grid + noise map.

Subscribes either ``camera/depth/points`` (organized XYZRGB PointCloud2) or
``camera/rgb/image_raw`` + ``camera/depth/image_raw`` + ``camera/rgb/camera_info`` (parameter
``input_mode``), averages ``frames_to_average`` frames (paper section III-B) and publishes latched
``object/occupancy`` (nav_msgs/OccupancyGrid: 0..100, -1 = no depth return, counted as object but
not used for GPIS training) and ``object/noise_map`` (gpis_grasp_interfaces/FloatGrid, m^2 per
cell: variance of the cell's SDF value; NaN = not used for training), stamped with the newest
frame's stamp and the camera frame. The grids lie in the table plane: their ``info.origin`` /
geometry carry the full pose (position and orientation) in the camera frame.

Perception for a tilted head camera (:mod:`gpis_grasp_ros.core.sensing`): robust
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

import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from geometry_msgs.msg import PointStamped
from nav_msgs.msg import OccupancyGrid
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import String

from gpis_grasp_interfaces.msg import FloatGrid
from gpis_grasp_ros.core import noise_model, pipeline, sensing
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.ros import conversions, validation
from gpis_grasp_ros.ros.nodes.common import (
    LATCHED_QOS,
    GuardedNode,
    guarded,
    log_startup,
    run_node,
    sensor_qos,
)
from gpis_grasp_ros.ros.nodes.shared_params import GRIPPER
from gpis_grasp_ros.ros.params import ZEROS_ARE_NONE, Param, ParamTable

MAX_PENDING_IMAGES = 30


def _same_camera(a: sensing.CameraIntrinsics, b: sensing.CameraIntrinsics, tol_px: float = 0.5) -> bool:
    """Intrinsics equal up to ``tol_px`` (those recovered from each cloud differ by rounding)."""
    return (a.width, a.height) == (b.width, b.height) and bool(np.allclose(
        [a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], atol=tol_px))


def target_needs_point(target: str) -> bool:
    """Whether the target mode reads target_point."""
    return target in ('pixel', 'table')


def _window_note(window_px: tuple[int, int, int, int] | None) -> str:
    """Where the objects were counted: the target's window of the image, if it was not the whole image."""
    if window_px is None:
        return ''
    u0, v0, u1, v1 = window_px
    return f' in the target\'s {u1 - u0 + 1}x{v1 - v0 + 1} px window'


@dataclass(frozen=True)

class BurstConfig:
    """How frames are grouped into one estimate (see :class:`SegmentationNode`)."""

    frames_to_average: int = 10  # paper: 10
    min_frames: int = 3
    burst_timeout: float = 1.5  # s
    max_stamp_gap: float = 1.0  # s
    limits: validation.Limits = field(default_factory=validation.Limits)


@dataclass(frozen=True)
class InputConfig:
    """Camera inputs chosen at start-up (read-only parameters)."""

    input_mode: str = 'cloud'
    input_reliability: str = 'best_effort'


_SP = sensing.SensingParams
_SM = noise_model.SensorModel


def _custom_sensor(name: str, description: str, field_name: str, high: float = 1.0, **kw: Any) -> Param:
    return Param(name, float, 'custom sensor: ' + description, _SM, field_name, low=kw.pop('low', 0.0), high=high,
                 read_only=True, **kw)


PARAMETERS = ParamTable('segmentation_node', [
    Param('input_mode', str, "'cloud': camera/depth/points; 'images': rgb + depth images + camera_info",
          InputConfig, choices=('cloud', 'images'), read_only=True),
    Param('input_reliability', str, "QoS reliability of the camera subscriptions ('best_effort' = sensor data)",
          InputConfig, choices=('best_effort', 'reliable'), read_only=True),
    Param('frames_to_average', int, 'frames averaged per estimate (paper: 10)', BurstConfig, low=1, high=1000),
    Param('min_frames', int, 'fewest frames of a burst that make an estimate when the burst ends before '
          'frames_to_average frames arrived', BurstConfig, low=1, high=1000),
    Param('burst_timeout', float, 'a burst ends when no frame arrived for this long', BurstConfig, unit='s',
          low=0.05, high=60.0),
    Param('max_stamp_gap', float, 'frames whose header stamps are further apart than this, or go backwards, '
          'belong to different bursts', BurstConfig, unit='s', low=0.01, high=3600.0),
    Param('max_image_pixels', int, 'largest camera frame accepted; larger messages are rejected before anything '
          'is allocated', validation.Limits, unit='pixels', low=1, high=50_000_000),
    Param('grid_cell_size', float, 'planning-grid cell: M = the target footprint plus margins over this, within '
          '[min_grid_size, max_grid_size] (docs/planning.md, "Resolution and lambda")', _SP, 'cell_size_m', unit='m',
          low=0.0005, high=0.05),
    Param('min_grid_size', int, 'smallest M from grid_cell_size (a small object gets finer cells)', _SP,
          'min_grid_cells', unit='cells', low=4, high=100),
    Param('max_grid_size', int, 'largest M from grid_cell_size (a large object gets coarser cells)', _SP,
          'max_grid_cells', unit='cells', low=4, high=100),
    Param('grid_size', int, 'M: force M x M cells (the paper: 25); 0 = from grid_cell_size', _SP, unit='cells',
          low=0, high=100),
    Param('grid_min_pixels', float, 'a planning cell is at least this many pixel footprints on the table wide '
          '(2: two depth samples per cell); 0 = grid_cell_size alone', _SP, 'min_pixels_per_cell', unit='pixels',
          low=0.0, high=10.0),
    Param('grid_margin', float, 'margin around the object bounding box, as a fraction of its size', _SP, 'margin',
          low=0.0, high=5.0),
    Param('height_threshold', float, 'depth mask: minimum height above the table', _SP, unit='m', low=0.0, high=0.5),
    Param('color_threshold', float, "RGB mask: minimum distance from the table colour's shadow line (0-255 "
          'units); 0 = adaptive to the table texture seen on the fitted plane', _SP, low=0.0, high=442.0),
    Param('chroma_z_min', float, 'clear targets: grow the target over table-level pixels this many robust sigmas '
          "off the table's chromaticity, as colour-only evidence, and let a target pixel there select the clear "
          'object (0 = off)', _SP, low=0.0, high=100.0),
    Param('clear_body_height', float, 'known height of a clear target body, e.g. from a catalogue of the objects, '
          'instead of the priors (0 = the priors; they assume vertical walls and put a round body lying on the '
          'table, a bottle, too low)', _SP, 'clear_body_height_m', unit='m', low=0.0,
          high=float(_SP.max_object_height_m)),
    Param('sensor_model', str, "depth-noise model: 'carmine' (PrimeSense), 'realsense_d400' (stereo, sigma_z ~ "
          "z^2) or 'custom' (sensor_sigma_* / sensor_quantisation_* below)", default='carmine',
          choices=tuple(noise_model.SENSOR_MODELS), read_only=True),
    _custom_sensor('sensor_sigma_constant', 'c0 in sigma_z = c0 + c1 (z - z_ref)^2 + c2 z^2', 'sigma_constant_m',
                   unit='m'),
    _custom_sensor('sensor_sigma_quadratic', 'c1', 'sigma_quadratic_per_m', unit='1/m'),
    _custom_sensor('sensor_sigma_reference_depth', 'z_ref', 'sigma_reference_depth_m', high=10.0, unit='m'),
    _custom_sensor('sensor_sigma_stereo', 'c2', 'sigma_stereo_per_m', unit='1/m'),
    _custom_sensor('sensor_quantisation_quadratic', 'q2 in q = q2 z^2 + q0', 'quantisation_per_m', unit='1/m'),
    _custom_sensor('sensor_quantisation_constant', 'q0', 'quantisation_constant_m', unit='m'),
    _custom_sensor('sensor_occluder_x', 'x (camera frame) of its projector or second imager, whose shadow has no '
                   'return (0 = none; carmine 0.075, realsense_d400 0.050)', 'occluder_x_m', low=-1.0, unit='m',
                   default=0.0),
    _custom_sensor('sensor_occluder_y', 'y (camera frame) of it: a camera rolled about its optical axis (0 = none)',
                   'occluder_y_m', low=-1.0, unit='m', default=0.0),
    Param('table_plane', list, 'table plane a x + b y + c z + d = 0 in the camera frame; all 0 = fit it (robust '
          'MSAC over the whole cloud)', _SP, unit='m', size=4, rule=ZEROS_ARE_NONE),
    Param('roi_px', list, 'region of interest (u_min, v_min, u_max, v_max); all 0 = whole image', _SP, unit='px',
          size=4, rule=ZEROS_ARE_NONE),
    Param('roi_table', list, 'region of interest (x_min, y_min, x_max, y_max) in the table frame; all 0 = whole '
          'table', _SP, unit='m', size=4, rule=ZEROS_ARE_NONE),
    Param('target', str, "which object to model: 'largest', 'nearest_center' (of the image), 'pixel' or 'table' "
          '(the object containing target_point)', _SP, choices=tuple(sensing.TARGET_MODES)),
    Param('target_point', list, "target 'pixel': (u, v) px; target 'table': (x, y) m in the table frame", _SP,
          default=[0.0, 0.0], size=2),
    GRIPPER['max_opening'].replace(target=_SP, field='max_opening_m', low=0.0, description=(
        'w_g: maximum jaw opening; a target with no part narrower is refused (0 = no check)')),
    Param('max_tilt_deg', float, 'a table plane tilted more than this from the optical axis is refused (edge-on)',
          _SP, unit='deg', low=1.0, high=89.0),
])


def build_config(v: dict[str, Any]) -> tuple[sensing.SensingParams, BurstConfig]:
    """Parameter values → (SensingParams, BurstConfig); ValueError names the parameter."""
    model = str(v['sensor_model'])
    sensor = (_SM(name='custom', **PARAMETERS.kwargs(v, _SM)) if model == 'custom' else _SM.named(model))
    kwargs = PARAMETERS.kwargs(v, _SP)
    kwargs['target_point'] = tuple(kwargs['target_point']) if target_needs_point(kwargs['target']) else None
    params = sensing.SensingParams(sensor=sensor, **kwargs)
    burst = PARAMETERS.kwargs(v, BurstConfig)
    # min_frames above frames_to_average means: only complete bursts make an estimate
    burst['min_frames'] = min(burst['min_frames'], burst['frames_to_average'])
    return params, BurstConfig(limits=validation.Limits(**PARAMETERS.kwargs(v, validation.Limits)), **burst)


class SegmentationNode(GuardedNode):
    """Accumulates frames and runs :func:`gpis_grasp_ros.core.sensing.segment_frames`.

    **Bursts.** Frames are collected until ``frames_to_average`` arrived, or the burst ends (no
    frame for ``burst_timeout`` s): then an estimate is made from the frames collected if there
    are at least ``min_frames`` (the log line and ``segmentation/status`` say how many were used).
    Frames of two passes are never mixed: when header stamps go backwards (a replay restarting) or
    jump by more than ``max_stamp_gap`` s, the frames collected so far are finished as their own
    burst first. So a complete replay of a bag gives exactly the offline pipeline's grid, and a
    replay that lost a few best-effort frames still gives an estimate (from fewer frames).

    **A live camera.** A complete burst is estimated in a thread of its own while the next burst is
    collected, so frames do not wait in the input queue during an estimate (they would be stale when
    taken). When a burst is complete before the estimate of the previous one has finished, it waits; a
    newer complete burst replaces it (the newest wins; logged, counted in ``bursts_superseded``).

    **Camera input QoS.** ``input_reliability: best_effort`` (default, like camera drivers'
    sensor-data QoS) matches every publisher but may lose frames of large messages on a busy
    link; ``reliable`` matches only reliable publishers (e.g. ``gpis-grasp play --reliable``) and
    loses nothing on loopback.
    """

    def __init__(self, **kwargs) -> None:
        super().__init__('segmentation_node', **kwargs)
        self.params, self.burst = PARAMETERS.watch(self, build_config, self._apply_config)
        inputs = InputConfig(**PARAMETERS.kwargs(PARAMETERS.values(self), InputConfig))
        self.input_mode = inputs.input_mode
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
        # complete bursts are estimated in a thread of their own while the next one is collected (frames are
        # not left waiting in the input queue during an estimate): one waits at most, the newest
        self._estimates = threading.Condition()
        self._waiting: tuple | None = None
        self.bursts_superseded = 0
        self._estimator = threading.Thread(target=self._estimate_loop, name='segmentation-estimate', daemon=True)
        self._estimator.start()

        qos = sensor_qos(inputs.input_reliability)
        # frames and the burst timer one at a time, apart from the parameter services (answered during an
        # estimate)
        self._inputs = MutuallyExclusiveCallbackGroup()
        if self.input_mode == 'cloud':
            self.create_subscription(PointCloud2, 'camera/depth/points',
                                     guarded(self, 'camera/depth/points', self._on_cloud), qos,
                                     callback_group=self._inputs)
        else:
            self.create_subscription(Image, 'camera/rgb/image_raw',
                                     guarded(self, 'camera/rgb/image_raw', self._on_rgb), qos,
                                     callback_group=self._inputs)
            self.create_subscription(Image, 'camera/depth/image_raw',
                                     guarded(self, 'camera/depth/image_raw', self._on_depth), qos,
                                     callback_group=self._inputs)
            self.create_subscription(CameraInfo, 'camera/rgb/camera_info',
                                     guarded(self, 'camera/rgb/camera_info', self._on_info), qos,
                                     callback_group=self._inputs)
        self.occupancy_pub = self.create_publisher(OccupancyGrid, 'object/occupancy', LATCHED_QOS)
        self.noise_pub = self.create_publisher(FloatGrid, 'object/noise_map', LATCHED_QOS)
        self.obstacles_pub = self.create_publisher(OccupancyGrid, 'object/obstacles', LATCHED_QOS)
        #: the target's top: grid centre at the measured object height (published before the grids)
        self.top_pub = self.create_publisher(PointStamped, 'object/top', LATCHED_QOS)
        #: latched outcome of the last segmentation: 'ok: ...' or 'failed: <reason>' (nothing published then)
        self.status_pub = self.create_publisher(String, 'segmentation/status', LATCHED_QOS)
        self.create_timer(0.05, self._on_burst_timer, callback_group=self._inputs)
        topics = (['camera/depth/points'] if self.input_mode == 'cloud' else
                  ['camera/rgb/image_raw', 'camera/depth/image_raw', 'camera/rgb/camera_info'])
        log_startup(self, topics, ['object/occupancy', 'object/noise_map', 'object/obstacles', 'object/top',
                                   'segmentation/status'],
                    ['input_mode', 'input_reliability', 'frames_to_average', 'min_frames', 'burst_timeout',
                     'grid_size', 'target', 'sensor_model'])

    # ------------------------------------------------------------------ parameters
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
                self._hand_over(item)

    def _on_burst_timer(self) -> None:
        with self._lock:
            timeout = self.burst.burst_timeout
            if not self._frames or time.monotonic() - self._last_arrival < timeout:
                return
            item = self._take_burst(f'burst ended: no frame for {timeout:g} s')
        if item is not None:
            self._hand_over(item)

    def _take_burst(self, why: str) -> tuple | None:
        """Take the collected frames (caller holds the lock); None when fewer than min_frames."""
        frames, self._frames = self._frames, []
        if len(frames) < self.burst.min_frames:
            if frames:
                self.get_logger().warning(f'{why}: {len(frames)} frame(s) collected, fewer than min_frames='
                                          f'{self.burst.min_frames}; no estimate')
            return None
        return frames, self._intrinsics_used, self._stamp, self._frame_id, why

    def _hand_over(self, item: tuple) -> None:
        """Give a complete burst to the estimating thread; one it has not started yet is replaced (newest wins)."""
        with self._estimates:
            if self._waiting is not None:
                self.bursts_superseded += 1
                self.get_logger().info(f'a newer burst replaces one of {len(self._waiting[0])} frames not yet '
                                       f'estimated (the estimate before it still runs; {self.bursts_superseded} '
                                       'replaced so far)')
            self._waiting = item
            self._estimates.notify_all()

    def _estimate_loop(self) -> None:
        while True:
            with self._estimates:
                while self._waiting is None and not self.shutting_down.is_set():
                    self._estimates.wait()
                if self.shutting_down.is_set():
                    return
                item, self._waiting = self._waiting, None
                self.enter_callback()
            try:
                guarded(self, 'segmentation', lambda burst: self._estimate(*burst))(item)
            finally:
                self.exit_callback()

    def destroy_node(self) -> None:
        self.begin_shutdown()  # the estimating thread ends
        super().destroy_node()

    def begin_shutdown(self) -> None:
        estimates = getattr(self, '_estimates', None)  # None while __init__ has not made it yet
        if estimates is None:
            super().begin_shutdown()
            return
        with estimates:
            super().begin_shutdown()
            estimates.notify_all()

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
        # before the target's grids, so that gpis_node has the obstacles when it fits
        self.obstacles_pub.publish(messages.numpy_to_occupancy_grid(
            factory, pipeline.publishable_obstacles(result), geometry, header_msg))
        self.occupancy_pub.publish(messages.numpy_to_occupancy_grid(factory, occ, geometry, header_msg))
        self.noise_pub.publish(messages.numpy_to_float_grid(factory, noise, geometry, header_msg, 'm^2'))
        summary = (f'published {result.geometry.height}x{result.geometry.width} occupancy and noise map from '
                   f'{len(frames)} frames (worth {result.effective_frames:.1f} independent): '
                   f'{result.objects_seen} object(s) on the table{_window_note(result.window_px)}, target '
                   f'{result.geometry.size_m[0] * 1000:.0f} mm '
                   f'grid, table tilt {result.table.tilt_deg:.1f} deg, object height '
                   f'{result.object_height * 1000:.1f} mm, {int(result.missing.sum())} missing cells '
                   f'({why})')
        self.get_logger().info(summary)
        self.status_pub.publish(String(data=f'ok: {summary}'))


def main(args: list[str] | None = None) -> int:
    return run_node(SegmentationNode, args)


if __name__ == '__main__':
    sys.exit(main())
