"""The whole gpis_grasp_ros pipeline: segmentation_node → gpis_node → planner_node (+ gripper_sim_node).

    ros2 launch gpis_grasp_ros gpis_grasp.launch.py                       # nodes only, camera on camera/...
    ros2 launch gpis_grasp_ros gpis_grasp.launch.py bag:=/path/A_tape_dispenser.mcap gripper_sim:=true rviz:=true
    ros2 launch gpis_grasp_ros gpis_grasp.launch.py input_mode:=images sensor_model:=realsense_d400 \\
        target:=pixel target_point:='[320.0, 240.0]' rgb_topic:=/my/rgb depth_topic:=/my/depth \\
        camera_info_topic:=/my/camera_info
    ros2 launch gpis_grasp_ros gpis_grasp.launch.py bag:=capture.mcap frames_to_average:=1 \\
        sensor_model:=realsense_d400 target:=pixel target_point:='[160.0, 120.0]'   # a one-frame imported capture

Every node reads ``params_file`` (default: the installed config/default.yaml, keys ``/**/<node>`` so it
applies in any namespace); the arguments below override single parameters. ``bag:=FILE`` replays one bag
with the package's ``bag_player`` (latched topics kept alive after the replay): its topics are published as
recorded (absolute ``/camera/...``, ``/ground_truth/...``), so use it without a ``namespace``.
Only plain launch constructs are used (see test/test_launch_files.py, which checks this file statically).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, NotEqualsSubstitution
from launch_ros.actions import Node

from launch import LaunchDescription

PACKAGE = 'gpis_grasp_ros'


def generate_launch_description():
    share = get_package_share_directory(PACKAGE)
    namespace = LaunchConfiguration('namespace')
    params_file = LaunchConfiguration('params_file')
    use_sim_time = LaunchConfiguration('use_sim_time')
    bag = LaunchConfiguration('bag')
    common = [params_file, {'use_sim_time': use_sim_time}]

    arguments = [
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of the nodes, their topics and services (empty = none)'),
        DeclareLaunchArgument('params_file', default_value=os.path.join(share, 'config', 'default.yaml'),
                              description='parameter file of all nodes (/**/<node> keys)'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='nodes take their time from /clock'),
        DeclareLaunchArgument('input_mode', default_value='cloud',
                              description="segmentation input: 'cloud' (organized XYZRGB PointCloud2) or 'images' "
                                          '(registered rgb + depth images + camera_info)'),
        DeclareLaunchArgument('sensor_model', default_value='carmine',
                              description="depth-noise model: 'carmine', 'realsense_d400' or 'custom'"),
        DeclareLaunchArgument('frames_to_average', default_value='10',
                              description='camera frames averaged per estimate (1 for a one-frame bag)'),
        DeclareLaunchArgument('target', default_value='largest',
                              description="object to model: 'largest', 'nearest_center', 'pixel' or 'table'"),
        DeclareLaunchArgument('target_point', default_value='[0.0, 0.0]',
                              description="target 'pixel': (u, v) px; target 'table': (x, y) m in the table frame"),
        DeclareLaunchArgument('cloud_topic', default_value='camera/depth/points',
                              description="input_mode 'cloud': the organized XYZRGB point cloud"),
        DeclareLaunchArgument('rgb_topic', default_value='camera/rgb/image_raw',
                              description="input_mode 'images': the colour image"),
        DeclareLaunchArgument('depth_topic', default_value='camera/depth/image_raw',
                              description="input_mode 'images': the depth image registered to the colour image "
                                          '(32FC1 m or 16UC1 mm, same header stamp as the colour image)'),
        DeclareLaunchArgument('camera_info_topic', default_value='camera/rgb/camera_info',
                              description="input_mode 'images': the colour camera's CameraInfo"),
        DeclareLaunchArgument('gripper_sim', default_value='false',
                              description='also start gripper_sim_node (executes grasps on a bag\'s ground truth)'),
        DeclareLaunchArgument('bag', default_value='',
                              description='replay this bag (.mcap file or rosbag2 directory) with bag_player'),
        DeclareLaunchArgument('bag_rate', default_value='1.0',
                              description='bag replay speed factor (0 = as fast as the subscribers allow)'),
        DeclareLaunchArgument('rviz', default_value='false',
                              description='open RViz2 with the installed rviz/gpis_grasp.rviz'),
        DeclareLaunchArgument('rviz_config', default_value=os.path.join(share, 'rviz', 'gpis_grasp.rviz'),
                              description='RViz2 configuration file'),
        DeclareLaunchArgument('fixed_frame', default_value='camera_rgb_optical_frame',
                              description="RViz2 fixed frame: the camera's optical frame (the frame_id of the "
                                          'camera messages; the shipped bags use camera_rgb_optical_frame)'),
    ]

    segmentation = Node(
        package=PACKAGE, executable='segmentation_node', namespace=namespace, output='screen',
        parameters=[*common, {'input_mode': LaunchConfiguration('input_mode'),
                              'sensor_model': LaunchConfiguration('sensor_model'),
                              'frames_to_average': LaunchConfiguration('frames_to_average'),
                              'target': LaunchConfiguration('target'),
                              'target_point': LaunchConfiguration('target_point')}],
        remappings=[('camera/depth/points', LaunchConfiguration('cloud_topic')),
                    ('camera/rgb/image_raw', LaunchConfiguration('rgb_topic')),
                    ('camera/depth/image_raw', LaunchConfiguration('depth_topic')),
                    ('camera/rgb/camera_info', LaunchConfiguration('camera_info_topic'))])
    gpis = Node(package=PACKAGE, executable='gpis_node', namespace=namespace, output='screen', parameters=common)
    planner = Node(package=PACKAGE, executable='planner_node', namespace=namespace, output='screen',
                   parameters=common)
    gripper = Node(package=PACKAGE, executable='gripper_sim_node', namespace=namespace, output='screen',
                   parameters=common, condition=IfCondition(LaunchConfiguration('gripper_sim')))
    player = Node(package=PACKAGE, executable='bag_player', output='screen',
                  arguments=[bag, '--rate', LaunchConfiguration('bag_rate'), '--keep-alive'],
                  condition=IfCondition(NotEqualsSubstitution(bag, '')))
    rviz = Node(package='rviz2', executable='rviz2', output='screen',
                arguments=['-d', LaunchConfiguration('rviz_config'), '-f', LaunchConfiguration('fixed_frame')],
                parameters=[{'use_sim_time': use_sim_time}], condition=IfCondition(LaunchConfiguration('rviz')))
    return LaunchDescription([*arguments, segmentation, gpis, planner, gripper, player, rviz])
