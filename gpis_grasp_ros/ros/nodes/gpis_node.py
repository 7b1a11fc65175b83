"""gpis_node: occupancy grid + noise map → GPIS (paper sections III and IV).

Subscribes latched ``object/occupancy`` and ``object/noise_map``, combines only a pair with the
same stamp and the same grid, computes the SDF by Euclidean distance transform, fits the GPIS
(squared-exponential kernel, ML hyperparameters, constant negative prior mean, per-cell noise)
and publishes latched ``gpis/model`` (GpisModel), ``gpis/mean`` and ``gpis/variance``
(FloatGrid, m and m^2), ``gpis/blur`` (mono8 GPIS-Blur image) and OccupancyGrid renderings
``gpis/mean_map`` and ``gpis/variance_map`` for RViz.
"""

from __future__ import annotations

import threading

import numpy as np
from nav_msgs.msg import OccupancyGrid
from rclpy.node import Node
from sensor_msgs.msg import Image

from gpis_grasp_interfaces.msg import FloatGrid, GpisModel
from gpis_grasp_ros.core import gpis, pipeline
from gpis_grasp_ros.core.blur import gpis_blur
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.ros import conversions
from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS, declare, guarded, run_node


class GpisNode(Node):
    """Thin ROS wrapper around :func:`gpis_grasp_ros.core.gpis.fit_gpis`."""

    def __init__(self, **kwargs) -> None:
        super().__init__('gpis_node', **kwargs)
        d = gpis.GpisParams()
        self.params = gpis.GpisParams(
            prior_mean=declare(self, 'prior_mean', float(d.prior_mean),
                               'constant prior mean of the SDF (m); negative biases unobserved cells to object',
                               low=-1.0, high=0.0),
            optimize_hyperparameters=declare(self, 'optimize_hyperparameters', bool(d.optimize_hyperparameters),
                                             'fit C and l by maximum marginal likelihood'),
            signal_variance=declare(self, 'signal_variance', float(d.signal_variance or 0.0),
                                    'kernel scale C (m^2) used when not optimising (0 = data-driven default)',
                                    low=0.0, high=1.0) or None,
            length_scale=declare(self, 'length_scale', float(d.length_scale or 0.0),
                                 'kernel bandwidth l (m) used when not optimising (0 = data-driven default)',
                                 low=0.0, high=10.0) or None,
        )
        self.blur_samples = declare(self, 'blur_samples', 1000, 'GPIS-Blur: number of shape samples (paper: 1000)',
                                    low=1, high=100000)
        self.blur_upsample = declare(self, 'blur_upsample', 8, 'GPIS-Blur: image pixels per grid cell', low=1, high=64)
        self.stamp_tolerance = declare(self, 'stamp_tolerance', 0.0,
                                       'max stamp difference (s) between occupancy and noise map to pair them',
                                       low=0.0, high=10.0)
        self._occupancy: OccupancyGrid | None = None
        self._noise: FloatGrid | None = None
        self._last_pair = None
        self._lock = threading.Lock()
        self.create_subscription(OccupancyGrid, 'object/occupancy',
                                 guarded(self, 'object/occupancy', self._on_occupancy), LATCHED_QOS)
        self.create_subscription(FloatGrid, 'object/noise_map', guarded(self, 'object/noise_map', self._on_noise),
                                 LATCHED_QOS)
        self.model_pub = self.create_publisher(GpisModel, 'gpis/model', LATCHED_QOS)
        self.mean_pub = self.create_publisher(FloatGrid, 'gpis/mean', LATCHED_QOS)
        self.var_pub = self.create_publisher(FloatGrid, 'gpis/variance', LATCHED_QOS)
        self.blur_pub = self.create_publisher(Image, 'gpis/blur', LATCHED_QOS)
        self.mean_map_pub = self.create_publisher(OccupancyGrid, 'gpis/mean_map', LATCHED_QOS)
        self.var_map_pub = self.create_publisher(OccupancyGrid, 'gpis/variance_map', LATCHED_QOS)

    def _on_occupancy(self, msg: OccupancyGrid) -> None:
        with self._lock:
            self._occupancy = msg
        self._try_fit()

    def _on_noise(self, msg: FloatGrid) -> None:
        with self._lock:
            self._noise = msg
        self._try_fit()

    def _try_fit(self) -> None:
        with self._lock:
            occ_msg, noise_msg = self._occupancy, self._noise
            if occ_msg is None or noise_msg is None:
                return
            t_occ = messages.stamp_to_ns(occ_msg.header.stamp)
            t_noise = messages.stamp_to_ns(noise_msg.header.stamp)
            if abs(t_occ - t_noise) > self.stamp_tolerance * 1e9:
                return  # stale or mismatched pair: wait for the partner
            if self._last_pair is not None and self._last_pair[0] is occ_msg and self._last_pair[1] is noise_msg:
                return  # this exact pair was already used (a replayed bag may repeat stamps)
            self._last_pair = (occ_msg, noise_msg)
        try:
            occ, geometry = messages.occupancy_grid_to_numpy(occ_msg)
            noise, noise_geometry = messages.float_grid_to_numpy(noise_msg)
            if occ.shape != noise.shape or not np.allclose(
                    [geometry.origin_x, geometry.origin_y, geometry.resolution],
                    [noise_geometry.origin_x, noise_geometry.origin_y, noise_geometry.resolution], atol=1e-9):
                raise ValueError(f'occupancy {occ.shape} and noise map {noise.shape} describe different grids')
            if occ_msg.header.frame_id != noise_msg.header.frame_id:
                raise ValueError(f"frames differ: '{occ_msg.header.frame_id}' vs '{noise_msg.header.frame_id}'")
            posterior = self.fit(occ, noise, geometry)
        except ValueError as exc:
            self.get_logger().warning(f'GPIS not updated: {exc}')
            return
        self._publish(posterior, occ_msg.header)

    def fit(self, occ: np.ndarray, noise: np.ndarray, geometry) -> gpis.GpisPosterior:
        """Occupancy (0..100, -1 = missing) and noise (m^2, NaN = untrained) → GPIS posterior."""
        return pipeline.posterior_from_grids(occ, noise, geometry, self.params)

    def _publish(self, posterior: gpis.GpisPosterior, header) -> None:
        factory = conversions.RclpyFactory()
        g = posterior.geometry
        self.model_pub.publish(messages.posterior_to_gpis_model(posterior, header, factory))
        self.mean_pub.publish(messages.numpy_to_float_grid(factory, posterior.mean, g, header, 'm'))
        self.var_pub.publish(messages.numpy_to_float_grid(factory, posterior.variance, g, header, 'm^2'))
        blur = gpis_blur(posterior, n_samples=self.blur_samples, rng=np.random.default_rng(0),
                         upsample=self.blur_upsample)
        self.blur_pub.publish(messages.numpy_to_image(factory, blur, 'mono8', header))
        # RViz renderings: mean as occupancy-like (inside = 100), variance normalised to 0..100.
        scale = max(float(np.abs(posterior.mean).max()), 1e-9)
        mean_map = np.clip(np.round(50 - 50 * posterior.mean / scale), 0, 100).astype(np.int8)
        var_map = np.clip(np.round(100 * posterior.variance / max(float(posterior.variance.max()), 1e-18)),
                          0, 100).astype(np.int8)
        self.mean_map_pub.publish(messages.numpy_to_occupancy_grid(factory, mean_map, g, header))
        self.var_map_pub.publish(messages.numpy_to_occupancy_grid(factory, var_map, g, header))
        p = posterior.params
        self.get_logger().info(f'published GPIS {g.height}x{g.width}: C={p.signal_variance:.3g} m^2, '
                               f'l={p.length_scale * 1000:.1f} mm, prior mean={p.prior_mean * 1000:.1f} mm')


def main(args: list[str] | None = None) -> int:
    return run_node(GpisNode, args)


if __name__ == '__main__':
    main()
