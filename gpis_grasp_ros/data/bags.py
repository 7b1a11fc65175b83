"""A recorded scene for offline use: camera frames and ground truth read from a bag.

:func:`load_bag` reads what segmentation_node subscribes to (clouds, or RGB + depth images with
camera info) and the simulator's ground truth; :func:`posterior_from_scene` runs the perception
pipeline on it exactly as the nodes do (:mod:`gpis_grasp_ros.core.pipeline`).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gpis_grasp_ros.core.gpis import GpisParams, GpisPosterior
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.pipeline import posterior_from_grids, publishable_grids, publishable_obstacles
from gpis_grasp_ros.core.sensing import (
    CameraIntrinsics,
    SensingParams,
    SensingResult,
    frames_from_clouds,
    segment_frames,
)
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.data.bagio import read_messages
from gpis_grasp_ros.data.topics import TOPICS


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
    true_center_of_mass: np.ndarray | None = None  # (x, y) m in true_geometry's grid (table) frame
    true_obstacles: np.ndarray | None = None  # m on true_geometry: signed distance to the other objects (None: none)


#: The topics :func:`load_bag` reads.
SCENE_TOPICS = (TOPICS['points'], TOPICS['rgb'], TOPICS['depth'], TOPICS['rgb_info'], TOPICS['sdf'], TOPICS['com'],
                TOPICS['obstacles'])


def load_bag(path: str | os.PathLike[str], frames: int = 10, source: str = 'cloud') -> BagScene:
    """Read the first ``frames`` camera frames and the ground truth of a bag.

    ``source='cloud'`` uses ``camera/depth/points`` (as segmentation_node's default input mode),
    ``'images'`` the RGB + depth images and camera info.
    """
    path = Path(path)
    return scene_from_messages(read_messages(path, SCENE_TOPICS), frames, source, str(path))


def scene_from_messages(msgs: Iterable[tuple[str, str, int, Any]], frames: int = 10, source: str = 'cloud',
                        name: str = 'messages') -> BagScene:
    """:func:`load_bag` of ``(topic, msgtype, t_ns, msg)`` tuples in time order (e.g. a capture's messages
    before they are written: the scene is then exactly the one its bag would give); ``name`` for errors."""
    path = name
    clouds: list[tuple[np.ndarray, np.ndarray]] = []
    rgbs: dict[int, np.ndarray] = {}
    depths: dict[int, np.ndarray] = {}
    info = None
    frame_id, stamp = '', 0
    scene_gt: dict = {}
    for topic, _type, _t, msg in msgs:
        if topic == TOPICS['sdf']:
            scene_gt['sdf'], scene_gt['geometry'] = messages.float_grid_to_numpy(msg)
        elif topic == TOPICS['obstacles']:
            scene_gt['obstacles'], scene_gt['obstacles_geometry'] = messages.float_grid_to_numpy(msg)
        elif topic == TOPICS['com']:
            scene_gt['com'] = messages.point_stamped_to_numpy(msg)  # sensor frame, 3D
        elif source == 'cloud' and topic == TOPICS['points'] and len(clouds) < frames:
            clouds.append(messages.pointcloud2_to_xyz_rgb(msg))
            frame_id, stamp = msg.header.frame_id, messages.stamp_to_ns(msg.header.stamp)
        elif source == 'images' and topic == TOPICS['rgb_info'] and info is None:
            info = CameraIntrinsics(*messages.camera_info_to_intrinsics(msg))
        elif source == 'images' and topic == TOPICS['rgb'] and len(rgbs) < frames:
            rgbs[messages.stamp_to_ns(msg.header.stamp)] = messages.image_to_numpy(msg)
        elif source == 'images' and topic == TOPICS['depth'] and len(depths) < frames:
            key = messages.stamp_to_ns(msg.header.stamp)
            depths[key] = messages.image_to_numpy(msg).astype(np.float64)
            frame_id, stamp = msg.header.frame_id, key
    if source == 'cloud':
        if not clouds:
            raise ValueError(f"{path}: no {TOPICS['points']} messages")
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
    com = scene_gt.get('com')
    if com is not None and scene_gt.get('geometry') is not None:  # into the truth grid's (table) frame
        com = scene_gt['geometry'].from_sensor(com)[0]
    elif com is not None:
        com = com[:2]
    obstacles = scene_gt.get('obstacles')
    if obstacles is not None and (scene_gt.get('sdf') is None or obstacles.shape != scene_gt['sdf'].shape
                                  or scene_gt['obstacles_geometry'] != scene_gt['geometry']):
        raise ValueError(f"{path}: {TOPICS['obstacles']} is not on the grid of {TOPICS['sdf']}")
    return BagScene(rgb, depth, intrinsics, frame_id, stamp, scene_gt.get('sdf'), scene_gt.get('geometry'), com,
                    None if obstacles is None else obstacles.astype(np.float64))


def posterior_from_scene(scene: BagScene, sensing_params: SensingParams = SensingParams(),
                         gpis_params: GpisParams = GpisParams()) -> tuple[GpisPosterior, SensingResult]:
    """Segmentation + GPIS of a loaded bag, through the same grids the nodes exchange."""
    result = segment_frames(scene.rgb_frames, scene.depth_frames, scene.intrinsics, sensing_params,
                            frame_id=scene.frame_id)
    occ, noise, geometry = publishable_grids(result)
    return posterior_from_grids(occ, noise, geometry, gpis_params, obstacles=publishable_obstacles(result)), result
