"""The bag and ROS topic names of the camera streams and the simulator's ground truth, and their message types.

One table for every writer and reader of bags (the simulator, the RGB-D importer, the bag reader):
``TOPICS`` maps a short key to the topic name, ``TOPIC_TYPES`` a topic name to its ROS 2 message type.
"""

from __future__ import annotations

TOPICS: dict[str, str] = {
    'points': '/camera/depth/points',
    'rgb': '/camera/rgb/image_raw',
    'depth': '/camera/depth/image_raw',
    'rgb_info': '/camera/rgb/camera_info',
    'depth_info': '/camera/depth/camera_info',
    'occupancy': '/ground_truth/occupancy',
    'sdf': '/ground_truth/sdf',
    'com': '/ground_truth/center_of_mass',
    'outline': '/ground_truth/outline',
    'obstacles': '/ground_truth/obstacles',
}
TOPIC_TYPES: dict[str, str] = {
    TOPICS['points']: 'sensor_msgs/msg/PointCloud2',
    TOPICS['rgb']: 'sensor_msgs/msg/Image',
    TOPICS['depth']: 'sensor_msgs/msg/Image',
    TOPICS['rgb_info']: 'sensor_msgs/msg/CameraInfo',
    TOPICS['depth_info']: 'sensor_msgs/msg/CameraInfo',
    TOPICS['occupancy']: 'nav_msgs/msg/OccupancyGrid',
    TOPICS['sdf']: 'gpis_grasp_interfaces/msg/FloatGrid',
    TOPICS['com']: 'geometry_msgs/msg/PointStamped',
    TOPICS['outline']: 'geometry_msgs/msg/PolygonStamped',
    TOPICS['obstacles']: 'gpis_grasp_interfaces/msg/FloatGrid',
}
#: The simulator's ground truth (a real capture's truth may add ``obstacles``, the other labelled objects).
GROUND_TRUTH_TOPICS: tuple[str, ...] = (TOPICS['occupancy'], TOPICS['sdf'], TOPICS['com'], TOPICS['outline'])
CAMERA_TOPICS: tuple[str, ...] = (TOPICS['rgb_info'], TOPICS['rgb'], TOPICS['depth_info'], TOPICS['depth'],
                                  TOPICS['points'])
