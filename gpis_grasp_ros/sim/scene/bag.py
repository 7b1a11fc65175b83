"""A simulated scene as ROS messages and as an MCAP bag (topics and QoS of :mod:`gpis_grasp_ros.data.topics`)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from gpis_grasp_ros.data.topics import CAMERA_TOPICS, GROUND_TRUTH_TOPICS, TOPIC_TYPES, TOPICS
from gpis_grasp_ros.sim.scene.simulator import Scene
from gpis_grasp_ros.sim.scene.spec import FRAME_ID, SceneSpec


def scene_messages(scene: Scene, f: Any) -> Iterator[tuple[str, str, int, Any]]:
    """``(topic, msgtype, t_ns, msg)`` of ``scene`` in bag order, built with the
    :mod:`~gpis_grasp_ros.data.messages` factory ``f``: latched ground truth at ``start_ns``, then per
    frame the two CameraInfos, the RGB image, the depth image and the point cloud."""
    from gpis_grasp_ros.data import messages as cv

    t0 = int(scene.spec.start_ns)
    gt = scene.ground_truth()
    hdr = cv.header(f, t0, FRAME_ID)
    yield TOPICS['occupancy'], TOPIC_TYPES[TOPICS['occupancy']], t0, \
        cv.numpy_to_occupancy_grid(f, gt.occupancy, gt.geometry, hdr)
    yield TOPICS['sdf'], TOPIC_TYPES[TOPICS['sdf']], t0, cv.numpy_to_float_grid(f, gt.sdf, gt.geometry, hdr, 'm')
    yield TOPICS['com'], TOPIC_TYPES[TOPICS['com']], t0, cv.point_stamped(f, gt.center_of_mass, hdr)
    if scene.spec.top_down:
        outline = cv.polygon_stamped(f, gt.outline, scene.table_depth, hdr)
    else:
        pts = [f.new('geometry_msgs/msg/Point32', x=float(x), y=float(y), z=float(z))
               for x, y, z in scene.pose.table_to_camera(gt.outline).astype(np.float32)]
        outline = f.new('geometry_msgs/msg/PolygonStamped', header=hdr,
                        polygon=f.new('geometry_msgs/msg/Polygon', points=pts))
    yield TOPICS['outline'], TOPIC_TYPES[TOPICS['outline']], t0, outline
    if gt.obstacles is not None:
        yield TOPICS['obstacles'], TOPIC_TYPES[TOPICS['obstacles']], t0, \
            cv.numpy_to_float_grid(f, gt.obstacles, gt.geometry, hdr, 'm')
    for frame in scene.frames():
        t = frame.stamp_ns
        h = cv.header(f, t, FRAME_ID)
        info = cv.intrinsics_to_camera_info(f, *scene.intrinsics, h)
        yield TOPICS['rgb_info'], TOPIC_TYPES[TOPICS['rgb_info']], t, info
        yield TOPICS['rgb'], TOPIC_TYPES[TOPICS['rgb']], t, cv.numpy_to_image(f, frame.rgb, 'rgb8', h)
        yield TOPICS['depth_info'], TOPIC_TYPES[TOPICS['depth_info']], t, info
        yield TOPICS['depth'], TOPIC_TYPES[TOPICS['depth']], t, cv.numpy_to_image(f, frame.depth, '32FC1', h)
        yield TOPICS['points'], TOPIC_TYPES[TOPICS['points']], t, \
            cv.xyz_rgb_to_pointcloud2(f, frame.xyz, frame.rgb, h)


def write_scene_bag(spec: SceneSpec, path: str | os.PathLike[str], overwrite: bool = False) -> Path:
    """Simulate ``spec`` and write it as an MCAP bag at ``path`` (``.mcap`` file or rosbag2 directory).

    Camera topics are recorded with sensor-data QoS, ground truth latched; the scene's
    :meth:`~Scene.describe` is the bag's metadata. All validation happens before anything is written;
    a failure while writing leaves no partial bag. Returns the path.
    """
    from gpis_grasp_ros.data import bagio
    from gpis_grasp_ros.data.messages import RosbagsFactory

    scene = Scene(spec)
    ts = bagio.get_typestore()
    meta = {'gpis_grasp_ros.sim.scene': json.dumps(scene.describe(), sort_keys=True)}
    with bagio.BagWriter(path, typestore=ts, custom_data=meta, overwrite=overwrite) as bag:
        for topic in GROUND_TRUTH_TOPICS + ((TOPICS['obstacles'],) if scene.distractors else ()):
            bag.add_topic(topic, TOPIC_TYPES[topic], bagio.LATCHED_QOS)
        for topic in CAMERA_TOPICS:
            bag.add_topic(topic, TOPIC_TYPES[topic], bagio.SENSOR_QOS)
        for topic, _msgtype, t_ns, msg in scene_messages(scene, RosbagsFactory(ts)):
            bag.write(topic, t_ns, msg)
    return Path(path)
