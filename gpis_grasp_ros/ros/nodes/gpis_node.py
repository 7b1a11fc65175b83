"""gpis_node: occupancy grid + noise map → GPIS (paper sections III and IV).

Subscribes latched ``object/occupancy`` and ``object/noise_map``, combines only a pair with the
same stamp and the same grid, computes the SDF by Euclidean distance transform, fits the GPIS
(squared-exponential kernel, ML hyperparameters, constant negative prior mean, per-cell noise)
and publishes latched ``gpis/model`` (GpisModel), ``gpis/mean`` and ``gpis/variance``
(FloatGrid, m and m^2), ``gpis/blur`` (mono8 GPIS-Blur image) and OccupancyGrid renderings
``gpis/mean_map`` and ``gpis/variance_map`` for RViz, and latched ``gpis/status`` (std_msgs/String,
``'ok: <summary>'`` naming how the hyperparameters were found, ``'failed: <reason>'`` when a pair was not fitted).

Warm start: the last fit of every ``frame_id`` (at most :data:`WARM_STARTS` frames) is the next fit's
``warm_start`` (docs/gpis-model.md, Warm start): its C and l are kept when the score test accepts them on the
new frame, else the search starts from them alone. A change of any GPIS parameter forgets every stored fit, so
the next frame is searched cold. The log line and ``gpis/status`` say which: ``warm (kept ...)``,
``warm, re-searched ...``, ``cold search ...`` or ``fixed``.

``GpisModel.object_height`` is the height above the grid's table plane of the latched
``object/top`` point (geometry_msgs/PointStamped from segmentation_node) with the occupancy's stamp
and frame; 0 (unknown) when none matches (an older or another publisher of the grids). Topics are not
ordered with each other: when the matching ``object/top`` arrives after the model was published with
height 0, ``gpis/model`` is published again with the height (same fit, no refit).
"""

from __future__ import annotations

import math
import sys
import threading
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from geometry_msgs.msg import PointStamped
from nav_msgs.msg import OccupancyGrid
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from sensor_msgs.msg import Image
from std_msgs.msg import String

from gpis_grasp_interfaces.msg import FloatGrid, GpisModel
from gpis_grasp_ros.core import gpis, pipeline
from gpis_grasp_ros.core.blur import gpis_blur
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.ros import conversions, validation
from gpis_grasp_ros.ros.nodes.common import (
    LATCHED_QOS,
    GuardedNode,
    guarded,
    log_startup,
    run_node,
)
from gpis_grasp_ros.ros.nodes.shared_params import check_resolutions, grid_limits
from gpis_grasp_ros.ros.params import ZERO_IS_NONE, Param, ParamTable

#: Largest per-cell noise variance accepted on object/noise_map (m^2; a 1 m standard deviation).
MAX_NOISE_VARIANCE = 1.0
#: Frames (header.frame_id) whose last hyperparameter fit is kept as the next fit's warm start.
WARM_STARTS = 8


@dataclass(frozen=True)
class GpisNodeConfig:
    """gpis_node parameters in effect."""

    params: gpis.GpisParams = field(default_factory=gpis.GpisParams)
    blur_samples: int = 1000  # GPIS-Blur shape samples (paper: 1000)
    blur_upsample: int = 8  # GPIS-Blur image pixels per grid cell
    stamp_tolerance: float = 0.0  # s between the stamps of a paired occupancy and noise map
    limits: validation.Limits = field(default_factory=validation.Limits)


_GP = gpis.GpisParams
PARAMETERS = ParamTable('gpis_node', [
    Param('prior_mean', float, 'constant prior mean of the SDF; negative biases unobserved cells to object', _GP,
          unit='m', low=-1.0, high=0.0),
    Param('optimize_hyperparameters', bool, 'fit C and l by maximum marginal likelihood', _GP),
    Param('signal_variance', float, 'kernel scale C used when not optimising (0 = data-driven default)', _GP,
          unit='m^2', low=0.0, high=1.0, rule=ZERO_IS_NONE),
    Param('length_scale', float, 'kernel bandwidth l used when not optimising (0 = data-driven default)', _GP,
          unit='m', low=0.0, high=10.0, rule=ZERO_IS_NONE),
    Param('gradient_observations', bool, 'also train on the SDF gradient (derivative observations, paper '
          'section III)', _GP),
    Param('gradient_noise_variance', float, 'noise variance g0 of one central-difference SDF gradient component',
          _GP, low=0.0, high=10.0),
    Param('search_band_cells', float, 'hyperparameter search on training cells with |SDF| <= this many cells '
          '(0 = all cells)', _GP, unit='cells', low=0.0, high=1000.0, rule=ZERO_IS_NONE),
    Param('length_scale_min_cells', float, 'lower bound of the ML length scale l', _GP, unit='cells',
          low=0.1, high=100.0),
    Param('length_scale_max_extent', float, 'upper bound of l as a fraction of the grid extent', _GP,
          low=0.01, high=10.0),
    Param('length_scale_max_thickness', float, "upper bound of l as a multiple of the object's largest inscribed "
          'radius (0 = no bound)', _GP, low=0.0, high=100.0, rule=ZERO_IS_NONE),
    Param('blur_samples', int, 'GPIS-Blur: number of shape samples (paper: 1000)', GpisNodeConfig,
          low=1, high=100000),
    Param('blur_upsample', int, 'GPIS-Blur: image pixels per grid cell', GpisNodeConfig, low=1, high=64),
    Param('stamp_tolerance', float, 'max stamp difference between occupancy and noise map to pair them',
          GpisNodeConfig, unit='s', low=0.0, high=10.0),
    *grid_limits('input', 40000, '; the GP fit needs about 8 n^2 bytes for n training cells'),
], checks=[check_resolutions])


def build_config(v: dict[str, Any]) -> GpisNodeConfig:
    """Parameter values → :class:`GpisNodeConfig` (ValueError names the parameter)."""
    return GpisNodeConfig(params=gpis.GpisParams(**PARAMETERS.kwargs(v, gpis.GpisParams)),
                          limits=validation.Limits(**PARAMETERS.kwargs(v, validation.Limits)),
                          **PARAMETERS.kwargs(v, GpisNodeConfig))


def grid_mismatch(a, b) -> str | None:
    """Name the first field in which two grid geometries differ (None when they describe the same grid)."""
    for name in ('width', 'height'):
        if getattr(a, name) != getattr(b, name):
            return f'info.{name} ({getattr(a, name)} vs {getattr(b, name)})'
    for name in ('resolution', 'origin_x', 'origin_y', 'z'):
        va, vb = float(getattr(a, name)), float(getattr(b, name))
        if abs(va - vb) > 1e-9:
            field = 'info.resolution' if name == 'resolution' else \
                f"info.origin.position.{ {'origin_x': 'x', 'origin_y': 'y', 'z': 'z'}[name]}"
            return f'{field} ({va:g} vs {vb:g} m)'
    if not np.allclose(a.rotation, b.rotation, atol=1e-9):
        return 'info.origin.orientation'
    return None


def hyperparameter_summary(fit: gpis.HyperparameterFit | None) -> str:
    """How a fit's C and l were found, for the log and ``gpis/status``."""
    if fit is None:
        return 'hyperparameters fixed'
    test = f'score {fit.drift_statistic:.2f}'
    if math.isfinite(fit.drift_ratio):
        test += f', likelihood ratio of a step {fit.drift_ratio:.2f}'
    if fit.warm_started and not fit.searched:
        evaluations = 'evaluation' if fit.n_evaluations == 1 else 'evaluations'
        return f'hyperparameters warm: previous C, l kept ({test}, {fit.n_evaluations} likelihood {evaluations})'
    if fit.warm_started:
        return (f'hyperparameters warm: re-searched from the previous C, l ({test}, '
                f'{fit.n_evaluations} likelihood evaluations)')
    return f'hyperparameters cold search ({fit.n_evaluations} likelihood evaluations, {fit.n_starts} starts)'


class GpisNode(GuardedNode):
    """Thin ROS wrapper around :func:`gpis_grasp_ros.core.gpis.fit_gpis`."""

    def __init__(self, **kwargs) -> None:
        super().__init__('gpis_node', **kwargs)
        self._lock = threading.Lock()
        #: frame_id -> the last fit there (most recent last), the next fit's warm start
        self._warm: OrderedDict[str, gpis.HyperparameterFit] = OrderedDict()
        self.config: GpisNodeConfig | None = None
        self.config = PARAMETERS.watch(self, build_config, self._apply_config)
        self._occupancy: OccupancyGrid | None = None
        self._noise: FloatGrid | None = None
        self._last_pair = None
        self._top: PointStamped | None = None
        self._obstacles: OccupancyGrid | None = None
        self._published: tuple[gpis.GpisPosterior, Any, float] | None = None  # last model, its header, its height
        #: the last published posterior's hyperparameter fit (None: hyperparameters fixed)
        self.last_fit: gpis.HyperparameterFit | None = None
        # the inputs one at a time, apart from the parameter services (answered while a fit runs)
        inputs = MutuallyExclusiveCallbackGroup()
        self.create_subscription(PointStamped, 'object/top', guarded(self, 'object/top', self._on_top), LATCHED_QOS,
                                 callback_group=inputs)
        self.create_subscription(OccupancyGrid, 'object/occupancy',
                                 guarded(self, 'object/occupancy', self._on_occupancy), LATCHED_QOS,
                                 callback_group=inputs)
        self.create_subscription(FloatGrid, 'object/noise_map', guarded(self, 'object/noise_map', self._on_noise),
                                 LATCHED_QOS, callback_group=inputs)
        self.create_subscription(OccupancyGrid, 'object/obstacles',
                                 guarded(self, 'object/obstacles', self._on_obstacles), LATCHED_QOS,
                                 callback_group=inputs)
        self.model_pub = self.create_publisher(GpisModel, 'gpis/model', LATCHED_QOS)
        self.mean_pub = self.create_publisher(FloatGrid, 'gpis/mean', LATCHED_QOS)
        self.var_pub = self.create_publisher(FloatGrid, 'gpis/variance', LATCHED_QOS)
        self.blur_pub = self.create_publisher(Image, 'gpis/blur', LATCHED_QOS)
        self.mean_map_pub = self.create_publisher(OccupancyGrid, 'gpis/mean_map', LATCHED_QOS)
        self.var_map_pub = self.create_publisher(OccupancyGrid, 'gpis/variance_map', LATCHED_QOS)
        self.status_pub = self.create_publisher(String, 'gpis/status', LATCHED_QOS)
        log_startup(self, ['object/occupancy', 'object/noise_map', 'object/obstacles', 'object/top'],
                    ['gpis/model', 'gpis/mean', 'gpis/variance', 'gpis/blur', 'gpis/mean_map', 'gpis/variance_map',
                     'gpis/status'],
                    ['optimize_hyperparameters', 'prior_mean', 'blur_samples', 'stamp_tolerance', 'max_grid_cells'])

    @property
    def params(self) -> gpis.GpisParams:
        """GPIS parameters in effect."""
        return self.config.params

    def _apply_config(self, config: GpisNodeConfig) -> None:
        with self._lock:
            if self.config is not None and config.params != self.config.params and self._warm:
                self._warm.clear()  # other GPIS settings: the stored fits are not fits of this model
                self.get_logger().info('GPIS parameters changed: the next fit of every frame is searched cold')
            self.config = config

    def warm_start(self, frame_id: str) -> gpis.HyperparameterFit | None:
        """The stored fit that warm-starts the next fit of ``frame_id`` (None: a cold search)."""
        with self._lock:
            return self._warm.get(frame_id)

    def _remember(self, frame_id: str, params: gpis.GpisParams, fit: gpis.HyperparameterFit | None) -> None:
        with self._lock:
            if fit is None or not fit.ok or params != self.config.params:
                return  # no search, a failed one, or parameters changed while fitting: nothing to warm-start from
            self._warm[frame_id] = fit
            self._warm.move_to_end(frame_id)
            while len(self._warm) > WARM_STARTS:
                self._warm.popitem(last=False)

    def _on_occupancy(self, msg: OccupancyGrid) -> None:
        try:
            validation.check_occupancy_grid(msg, self.config.limits)
        except ValueError as exc:
            self.reject(f'ignoring object/occupancy: {exc}')
            return
        with self._lock:
            self._occupancy = msg
        self._try_fit()

    def _on_top(self, msg: PointStamped) -> None:
        try:
            validation.check_stamp(msg.header, 'PointStamped object/top')
            validation.check_point(msg, 'PointStamped object/top.point', self.config.limits)
        except ValueError as exc:
            self.reject(f'ignoring object/top: {exc}')
            return
        with self._lock:
            self._top = msg
        self._complete_model()

    def _complete_model(self) -> None:
        """Re-publish the last model when it went out without what arrived since for its frame: the object height
        (it went out as unknown, 0, and the matching ``object/top`` is here now) or the obstacles (none went out
        and the matching ``object/obstacles`` holds some) - they arrived after the fit, or while it was
        published."""
        with self._lock:
            last = self._published
        if last is None:
            return
        posterior, header, height = last
        tolerance = self.config.stamp_tolerance
        new_height = height if height > 0.0 else self.object_height(header, posterior.geometry, tolerance)
        obstacles = None if posterior.obstacles is not None else self.obstacles(header, posterior.geometry,
                                                                                  tolerance)
        if new_height == height and obstacles is None:
            return
        if obstacles is not None:
            posterior = replace(posterior, obstacles=obstacles)
        with self._lock:
            if self._published is not last:  # a newer model went out meanwhile: it carries its own
                return
            self._published = (posterior, header, new_height)
        self.model_pub.publish(messages.posterior_to_gpis_model(posterior, header, conversions.RclpyFactory(),
                                                                object_height=new_height))
        what = ([f'object height {new_height * 1000:.1f} mm'] if new_height != height else []) + (
            [f'{int((obstacles < 0).sum())} obstacle cells'] if obstacles is not None else [])
        self.get_logger().info(f'inputs arrived after the fit: gpis/model re-published with {" and ".join(what)}')

    def object_height(self, header, geometry, tolerance_s: float) -> float:
        """Height (m) above the grid's table plane of the ``object/top`` point matching ``header`` (stamp within
        ``tolerance_s``, same frame); 0 (unknown) without one, or when the point is off the grid or higher than
        :data:`~gpis_grasp_ros.ros.validation.MAX_OBJECT_HEIGHT` (logged)."""
        with self._lock:
            top = self._top
        if top is None or top.header.frame_id != header.frame_id or abs(
                messages.stamp_to_ns(top.header.stamp) - messages.stamp_to_ns(header.stamp)) > tolerance_s * 1e9:
            return 0.0
        try:
            return validation.object_height_of(messages.point_stamped_to_numpy(top), geometry)
        except ValueError as exc:
            self.reject(f'ignoring object/top: {exc}; object height unknown')
            return 0.0

    def _on_obstacles(self, msg: OccupancyGrid) -> None:
        try:
            validation.check_occupancy_grid(msg, self.config.limits)
        except ValueError as exc:
            self.reject(f'ignoring object/obstacles: {exc}')
            return
        with self._lock:
            self._obstacles = msg
        self._complete_model()

    def obstacles(self, header, geometry, tolerance_s: float) -> np.ndarray | None:
        """Signed distance (m) to the other objects of the ``object/obstacles`` grid matching ``header`` (stamp
        within ``tolerance_s``, same frame and grid); None without one (or without any obstacle cell)."""
        with self._lock:
            msg = self._obstacles
        if msg is None or msg.header.frame_id != header.frame_id or abs(
                messages.stamp_to_ns(msg.header.stamp) - messages.stamp_to_ns(header.stamp)) > tolerance_s * 1e9:
            return None
        grid, obstacle_geometry = messages.occupancy_grid_to_numpy(msg)
        differs = grid_mismatch(geometry, obstacle_geometry)
        if differs is not None:
            self.reject(f'ignoring object/obstacles: its grid differs from the occupancy\'s ({differs})')
            return None
        return pipeline.obstacle_distance(grid, geometry)

    def _on_noise(self, msg: FloatGrid) -> None:
        try:
            validation.check_float_grid(msg, self.config.limits, 'FloatGrid object/noise_map', allow_nan=True,
                                        low=0.0, high=MAX_NOISE_VARIANCE)
        except ValueError as exc:
            self.reject(f'ignoring object/noise_map: {exc}')
            return
        with self._lock:
            self._noise = msg
        self._try_fit()

    def _try_fit(self) -> None:
        config = self.config
        with self._lock:
            occ_msg, noise_msg = self._occupancy, self._noise
            if occ_msg is None or noise_msg is None:
                return
            t_occ = messages.stamp_to_ns(occ_msg.header.stamp)
            t_noise = messages.stamp_to_ns(noise_msg.header.stamp)
            if abs(t_occ - t_noise) > config.stamp_tolerance * 1e9:
                return  # stale or mismatched pair: wait for the partner
            if self._last_pair is not None and (self._last_pair[0] is occ_msg or self._last_pair[1] is noise_msg):
                # each message is used once: a replayed bag repeats its stamps, so the previous
                # pass's partner has the same stamp; wait for this pass's partner
                return
        try:
            occ, geometry = messages.occupancy_grid_to_numpy(occ_msg)
            noise, noise_geometry = messages.float_grid_to_numpy(noise_msg)
            differs = grid_mismatch(geometry, noise_geometry)
            if differs is not None:
                raise ValueError(f'object/occupancy and object/noise_map describe different grids: {differs} differs')
            if occ_msg.header.frame_id != noise_msg.header.frame_id:
                raise ValueError(f"frames differ: header.frame_id '{occ_msg.header.frame_id}' vs "
                                 f"'{noise_msg.header.frame_id}'")
            frame_id = occ_msg.header.frame_id
            warm = self.warm_start(frame_id) if config.params.optimize_hyperparameters else None
            posterior = self.fit(occ, noise, geometry, config.params, warm_start=warm)
            validation.check_posterior(posterior)
        except (ValueError, np.linalg.LinAlgError) as exc:
            self.get_logger().warning(f'GPIS not updated: {exc}')
            self.status_pub.publish(String(data=f'failed: {exc}'))
            return
        self._remember(frame_id, config.params, posterior.hyperparameter_fit)
        with self._lock:
            self._last_pair = (occ_msg, noise_msg)
        self._publish(posterior, occ_msg.header, config)

    def fit(self, occ: np.ndarray, noise: np.ndarray, geometry, params: gpis.GpisParams | None = None, *,
            warm_start: gpis.HyperparameterFit | None = None) -> gpis.GpisPosterior:
        """Occupancy (0..100; -1 = unknown: missing or uncertain, not trained, object in the SDF) and noise
        (m^2, NaN = untrained) → GPIS posterior; ``warm_start`` a previous fit of the same scene."""
        return pipeline.posterior_from_grids(occ, noise, geometry, params or self.config.params,
                                             warm_start=warm_start)

    def _publish(self, posterior: gpis.GpisPosterior, header, config: GpisNodeConfig) -> None:
        factory = conversions.RclpyFactory()
        g = posterior.geometry
        height = self.object_height(header, g, config.stamp_tolerance)
        obstacles = self.obstacles(header, g, config.stamp_tolerance)
        if obstacles is not None:
            posterior = replace(posterior, obstacles=obstacles)
        self.model_pub.publish(messages.posterior_to_gpis_model(posterior, header, factory, object_height=height))
        self.mean_pub.publish(messages.numpy_to_float_grid(factory, posterior.mean, g, header, 'm'))
        self.var_pub.publish(messages.numpy_to_float_grid(factory, posterior.variance, g, header, 'm^2'))
        blur = gpis_blur(posterior, n_samples=config.blur_samples, rng=np.random.default_rng(0),
                         upsample=config.blur_upsample)
        self.blur_pub.publish(messages.numpy_to_image(factory, blur, 'mono8', header))
        # RViz renderings: mean as occupancy-like (inside = 100), variance normalised to 0..100.
        scale = max(float(np.abs(posterior.mean).max()), 1e-9)
        mean_map = np.clip(np.round(50 - 50 * posterior.mean / scale), 0, 100).astype(np.int8)
        var_map = np.clip(np.round(100 * posterior.variance / max(float(posterior.variance.max()), 1e-18)),
                          0, 100).astype(np.int8)
        self.mean_map_pub.publish(messages.numpy_to_occupancy_grid(factory, mean_map, g, header))
        self.var_map_pub.publish(messages.numpy_to_occupancy_grid(factory, var_map, g, header))
        p = posterior.params
        summary = (f'GPIS {g.height}x{g.width}: C={p.signal_variance:.3g} m^2, l={p.length_scale * 1000:.1f} mm, '
                   f'prior mean={p.prior_mean * 1000:.1f} mm, {hyperparameter_summary(posterior.hyperparameter_fit)}')
        self.get_logger().info(f'published {summary}, object height {height * 1000:.1f} mm'
                               + ('' if height > 0 else ' (unknown)'))
        with self._lock:
            self._published = (posterior, header, height)
            self.last_fit = posterior.hyperparameter_fit
        self.status_pub.publish(String(data=f'ok: {summary}'))
        self._complete_model()


def main(args: list[str] | None = None) -> int:
    return run_node(GpisNode, args)


if __name__ == '__main__':
    sys.exit(main())
