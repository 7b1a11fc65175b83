"""The perception pipeline exactly as the nodes run it, callable without ROS.

segmentation_node publishes what :func:`publishable_grids` returns (an int8 occupancy grid with
-1 for missing cells and a float32 noise map with NaN for cells not used in training — the
precision of ``nav_msgs/OccupancyGrid`` and ``FloatGrid``), and gpis_node turns such a pair into a
posterior with :func:`posterior_from_grids`. The benchmark, the demo and the tests call the same
two functions, so offline results equal what the ROS graph computes (reading a bag into these
functions is :mod:`gpis_grasp_ros.data.bags`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gpis_grasp_ros.core.gpis import GpisParams, GpisPosterior, HyperparameterFit, fit_gpis
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.sdf import signed_distance
from gpis_grasp_ros.core.sensing import SensingResult


def message_geometry(geometry: GridGeometry) -> GridGeometry:
    """The geometry as it survives ``nav_msgs/MapMetaData`` (resolution is float32 there)."""
    return replace(geometry, resolution=float(np.float32(geometry.resolution)))


def publishable_grids(result: SensingResult) -> tuple[np.ndarray, np.ndarray, GridGeometry]:
    """Sensing result → (occupancy int8 0..100 with -1 = unknown, noise float32 m^2 with NaN = not trained).

    Unknown = every cell outside ``train_mask`` (missing, or uncertain: see the sensing module's Noise
    map): -1 (``nav_msgs/OccupancyGrid``'s "unknown"), counted as object in the SDF, not trained.
    """
    # floor, not round: a published value >= 50 exactly when the occupancy is >= 0.5, the object threshold of
    # core.sdf (0.498 would round to 50 and be object in the grid, free in the sensing result)
    occ = np.clip(np.floor(result.occupancy * 100.0), 0, 100).astype(np.int8)
    occ[~result.train_mask] = -1
    noise = np.where(result.train_mask, result.noise_variance, np.nan).astype(np.float32)
    return occ, noise, message_geometry(result.geometry)


def publishable_obstacles(result: SensingResult) -> np.ndarray:
    """The other objects in the target's grid as an int8 occupancy (100 = another object's cell, 0 = not), the
    ``object/obstacles`` grid segmentation_node publishes beside the target's."""
    obstacles = np.zeros(result.geometry.shape, bool) if result.obstacles is None else result.obstacles
    return np.where(obstacles, 100, 0).astype(np.int8)


def obstacle_distance(obstacles: np.ndarray | None, geometry: GridGeometry) -> np.ndarray | None:
    """Signed distance (m) to the obstacle cells of an occupancy (>= 50, ``object/obstacles``); None without any."""
    if obstacles is None:
        return None
    obstacles = np.asarray(obstacles)
    if obstacles.shape != geometry.shape:
        raise ValueError(f'the obstacle grid {obstacles.shape} must be {geometry.shape}, like the occupancy')
    cells = obstacles >= 50
    return signed_distance(cells, geometry.resolution) if cells.any() else None


def posterior_from_grids(occupancy: np.ndarray, noise: np.ndarray, geometry: GridGeometry,
                         params: GpisParams = GpisParams(), *,
                         warm_start: HyperparameterFit | None = None,
                         obstacles: np.ndarray | None = None) -> GpisPosterior:
    """Occupancy (0..100, -1 = missing) and noise map (m^2, NaN = excluded) → GPIS (section III-B).

    Missing cells count as object in the SDF but are not used for training, as in the paper.
    ``warm_start``: the previous frame's ``posterior.hyperparameter_fit`` of the same scene
    (see :func:`~gpis_grasp_ros.core.gpis.fit_gpis`). ``obstacles``: the other objects' cells (>= 50,
    :func:`publishable_obstacles`), which the jaws must keep out of (the posterior's ``obstacles``).
    """
    occupancy = np.asarray(occupancy)
    noise = np.asarray(noise, dtype=np.float64)
    if occupancy.shape != geometry.shape or noise.shape != geometry.shape:
        raise ValueError(f'occupancy {occupancy.shape} and noise map {noise.shape} must both be {geometry.shape}')
    missing = occupancy < 0
    occupied = (occupancy >= 50) | missing
    if not occupied.any():
        raise ValueError('the occupancy grid contains no object cell')
    train = ~missing & np.isfinite(noise)
    if not train.any():
        raise ValueError('no cell is usable for training (all missing or without noise estimate)')
    if np.any(noise[train] < 0):
        raise ValueError('the noise map has negative variances')
    distance = signed_distance(occupied, geometry.resolution)
    obstacle = obstacle_distance(obstacles, geometry)
    posterior = fit_gpis(distance, np.where(train, noise, 0.0), train, geometry, params, warm_start=warm_start)
    return posterior if obstacle is None else replace(posterior, obstacles=obstacle)
