"""gpis_grasp.launch.py on an Intel RealSense D400 driven by realsense-ros (realsense2_camera 4.x).

    ros2 launch realsense2_camera rs_launch.py align_depth.enable:=true enable_sync:=true
    ros2 launch gpis_grasp_ros realsense.launch.py target:=nearest_center rviz:=true

Segmentation reads images (``input_mode:=images``): the colour image, the depth aligned to it (16UC1,
mm) and the colour CameraInfo under realsense-ros's default names (camera namespace ``camera``, camera
name ``camera``); ``sensor_model:=realsense_d400``. segmentation_node pairs colour and depth by exact
header stamp, hence ``enable_sync:=true`` on the camera. A camera started with another
``camera_namespace``/``camera_name`` is used by overriding ``rgb_topic``, ``depth_topic`` and
``camera_info_topic``. Every other argument is passed on to gpis_grasp.launch.py.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, IncludeLaunchDescription
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch.substitutions import LaunchConfiguration

from launch import LaunchDescription

PACKAGE = 'gpis_grasp_ros'

#: realsense-ros 4.x default topics (namespace 'camera', node 'camera', align_depth.enable:=true).
REALSENSE_TOPICS = {
    'rgb_topic': '/camera/camera/color/image_raw',
    'depth_topic': '/camera/camera/aligned_depth_to_color/image_raw',
    'camera_info_topic': '/camera/camera/color/camera_info',
}


def generate_launch_description():
    share = get_package_share_directory(PACKAGE)
    arguments = [
        DeclareLaunchArgument('rgb_topic', default_value=REALSENSE_TOPICS['rgb_topic'],
                              description='colour image of the RealSense'),
        DeclareLaunchArgument('depth_topic', default_value=REALSENSE_TOPICS['depth_topic'],
                              description='depth aligned to the colour image'),
        DeclareLaunchArgument('camera_info_topic', default_value=REALSENSE_TOPICS['camera_info_topic'],
                              description='CameraInfo of the colour image'),
        DeclareLaunchArgument('fixed_frame', default_value='camera_color_optical_frame',
                              description="RViz2 fixed frame: realsense-ros's colour optical frame"),
        DeclareLaunchArgument('namespace', default_value='', description='namespace of the gpis_grasp_ros nodes'),
        DeclareLaunchArgument('target', default_value='largest',
                              description="object to model: 'largest', 'nearest_center', 'pixel' or 'table'"),
        DeclareLaunchArgument('target_point', default_value='[0.0, 0.0]',
                              description="target 'pixel': (u, v) px; target 'table': (x, y) m in the table frame"),
        DeclareLaunchArgument('params_file', default_value=os.path.join(share, 'config', 'default.yaml'),
                              description='parameter file of all nodes (/**/<node> keys)'),
        DeclareLaunchArgument('use_sim_time', default_value='false', description='nodes take their time from /clock'),
        DeclareLaunchArgument('rviz', default_value='false', description='open RViz2 with rviz/gpis_grasp.rviz'),
    ]
    pipeline = IncludeLaunchDescription(
        PythonLaunchDescriptionSource(os.path.join(share, 'launch', 'gpis_grasp.launch.py')),
        launch_arguments={
            'input_mode': 'images',
            'sensor_model': 'realsense_d400',
            'rgb_topic': LaunchConfiguration('rgb_topic'),
            'depth_topic': LaunchConfiguration('depth_topic'),
            'camera_info_topic': LaunchConfiguration('camera_info_topic'),
            'fixed_frame': LaunchConfiguration('fixed_frame'),
            'namespace': LaunchConfiguration('namespace'),
            'target': LaunchConfiguration('target'),
            'target_point': LaunchConfiguration('target_point'),
            'params_file': LaunchConfiguration('params_file'),
            'use_sim_time': LaunchConfiguration('use_sim_time'),
            'rviz': LaunchConfiguration('rviz'),
        }.items())
    return LaunchDescription([*arguments, pipeline])
