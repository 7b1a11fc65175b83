"""The perception pipeline exactly as the nodes run it, callable without ROS.

segmentation_node publishes what :func:`publishable_grids` returns (an int8 occupancy grid with
-1 for missing cells and a float32 noise map with NaN for cells not used in training — the
precision of ``nav_msgs/OccupancyGrid`` and ``FloatGrid``), and gpis_node turns such a pair into a
posterior with :func:`posterior_from_grids`. The benchmark, the demo and the tests call the same
two functions, so offline results equal what the ROS graph computes.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from . import conversions
from .gpis import GpisParams, GpisPosterior, fit_gpis
from .grid import GridGeometry
from .sdf import signed_distance
from .sensing import CameraIntrinsics, SensingParams, SensingResult, frames_from_clouds, segment_frames

CLOUD_TOPIC = '/camera/depth/points'
RGB_TOPIC = '/camera/rgb/image_raw'
DEPTH_TOPIC = '/camera/depth/image_raw'
INFO_TOPIC = '/camera/rgb/camera_info'
TRUE_SDF_TOPIC = '/ground_truth/sdf'
TRUE_COM_TOPIC = '/ground_truth/center_of_mass'


def message_geometry(geometry: GridGeometry) -> GridGeometry:
    """The geometry as it survives ``nav_msgs/MapMetaData`` (resolution is float32 there)."""
    return replace(geometry, resolution=float(np.float32(geometry.resolution)))


def publishable_grids(result: SensingResult) -> tuple[np.ndarray, np.ndarray, GridGeometry]:
    """Sensing result → (occupancy int8 0..100 with -1 = missing, noise float32 m^2 with NaN = not trained)."""
    occ = np.clip(np.round(result.occupancy * 100.0), 0, 100).astype(np.int8)
    occ[result.missing] = -1
    noise = np.where(result.train_mask, result.noise_variance, np.nan).astype(np.float32)
    return occ, noise, message_geometry(result.geometry)


def posterior_from_grids(occupancy: np.ndarray, noise: np.ndarray, geometry: GridGeometry,
                         params: GpisParams = GpisParams()) -> GpisPosterior:
    """Occupancy (0..100, -1 = missing) and noise map (m^2, NaN = excluded) → GPIS (section III-B).

    Missing cells count as object in the SDF but are not used for training, as in the paper.
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
    return fit_gpis(distance, np.where(train, noise, 0.0), train, geometry, params)


@dataclass
class BagScene:
    """What a bag holds for offline use: camera frames and (evaluation only) the ground truth."""

    rgb_frames: np.ndarray  # (N, H, W, 3) uint8
    depth_frames: np.ndarray  # (N, H, W) m, NaN = no return
    intrinsics: CameraIntrinsics
    frame_id: str
    stamp_ns: int  # stamp of the last frame used
    true_sdf: np.ndarray | None = None  # m, positive outside
    true_geometry: GridGeometry | None = None
    true_center_of_mass: np.ndarray | None = None  # (x, y) m


def load_bag(path: str | os.PathLike[str], frames: int = 10, source: str = 'cloud') -> BagScene:
    """Read the first ``frames`` camera frames and the ground truth of a bag.

    ``source='cloud'`` uses ``camera/depth/points`` (as segmentation_node's default input mode),
    ``'images'`` the RGB + depth images and camera info.
    """
    from .bagio import read_messages

    path = Path(path)
    clouds: list[tuple[np.ndarray, np.ndarray]] = []
    rgbs: dict[int, np.ndarray] = {}
    depths: dict[int, np.ndarray] = {}
    info = None
    frame_id, stamp = '', 0
    scene_gt: dict = {}
    topics = [CLOUD_TOPIC, RGB_TOPIC, DEPTH_TOPIC, INFO_TOPIC, TRUE_SDF_TOPIC, TRUE_COM_TOPIC]
    for topic, _type, _t, msg in read_messages(path, topics):
        if topic == TRUE_SDF_TOPIC:
            scene_gt['sdf'], scene_gt['geometry'] = conversions.float_grid_to_numpy(msg)
        elif topic == TRUE_COM_TOPIC:
            scene_gt['com'] = conversions.point_stamped_to_numpy(msg)[:2]
        elif source == 'cloud' and topic == CLOUD_TOPIC and len(clouds) < frames:
            clouds.append(conversions.pointcloud2_to_xyz_rgb(msg))
            frame_id, stamp = msg.header.frame_id, conversions.stamp_to_ns(msg.header.stamp)
        elif source == 'images' and topic == INFO_TOPIC and info is None:
            info = CameraIntrinsics(*conversions.camera_info_to_intrinsics(msg))
        elif source == 'images' and topic == RGB_TOPIC and len(rgbs) < frames:
            rgbs[conversions.stamp_to_ns(msg.header.stamp)] = conversions.image_to_numpy(msg)
        elif source == 'images' and topic == DEPTH_TOPIC and len(depths) < frames:
            key = conversions.stamp_to_ns(msg.header.stamp)
            depths[key] = conversions.image_to_numpy(msg).astype(np.float64)
            frame_id, stamp = msg.header.frame_id, key
    if source == 'cloud':
        if not clouds:
            raise ValueError(f'{path}: no {CLOUD_TOPIC} messages')
        rgb, depth, intrinsics = frames_from_clouds(np.stack([c[0] for c in clouds]),
                                                    np.stack([c[1] for c in clouds]))
    elif source == 'images':
        keys = sorted(set(rgbs) & set(depths))
        if not keys or info is None:
            raise ValueError(f'{path}: no matching RGB/depth image pairs with camera info')
        rgb = np.stack([rgbs[k] for k in keys])
        depth = np.stack([depths[k] for k in keys])
        intrinsics = info
    else:
        raise ValueError(f"source must be 'cloud' or 'images', got '{source}'")
    return BagScene(rgb, depth, intrinsics, frame_id, stamp, scene_gt.get('sdf'), scene_gt.get('geometry'),
                    scene_gt.get('com'))


def posterior_from_scene(scene: BagScene, sensing_params: SensingParams = SensingParams(),
                         gpis_params: GpisParams = GpisParams()) -> tuple[GpisPosterior, SensingResult]:
    """Segmentation + GPIS of a loaded bag, through the same grids the nodes exchange."""
    result = segment_frames(scene.rgb_frames, scene.depth_frames, scene.intrinsics, sensing_params,
                            frame_id=scene.frame_id)
    occ, noise, geometry = publishable_grids(result)
    return posterior_from_grids(occ, noise, geometry, gpis_params), result
