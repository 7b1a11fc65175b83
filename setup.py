"""ament_python package gpis_grasp_ros (the repository root)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'gpis_grasp_ros'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(include=[PACKAGE, PACKAGE + '.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml')),
        ('share/' + PACKAGE + '/launch', glob('launch/*.launch.py')),
        ('share/' + PACKAGE + '/rviz', glob('rviz/*.rviz')),
        ('share/' + PACKAGE, ['LICENSE', 'CITATION.cff']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='gpis_grasp_ros maintainers',
    maintainer_email='maintainers@gpis-grasp-ros.invalid',
    description='Grasp planning under shape uncertainty with GPIS (GP-GPIS-OPT).',
    license='BSD-3-Clause',
    entry_points={
        'console_scripts': [
            'gpis-grasp = gpis_grasp_ros.tools.cli:main',
            'segmentation_node = gpis_grasp_ros.ros.nodes.segmentation_node:main',
            'gpis_node = gpis_grasp_ros.ros.nodes.gpis_node:main',
            'planner_node = gpis_grasp_ros.ros.nodes.planner_node:main',
            'gripper_sim_node = gpis_grasp_ros.ros.nodes.gripper_sim_node:main',
            'bag_player = gpis_grasp_ros.ros.player:main',
        ],
    },
)
