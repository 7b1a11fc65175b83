"""gpis_grasp_ros: grasp planning under shape uncertainty with Gaussian process implicit surfaces.

The folder a module sits in tells what it may import (checked by ``test/test_layout.py``):

* :mod:`gpis_grasp_ros.core` — the paper, no ROS and no I/O;
* :mod:`gpis_grasp_ros.data` — bags and message layouts, ROS-free;
* :mod:`gpis_grasp_ros.sim` — the scene simulator and object catalogue;
* :mod:`gpis_grasp_ros.viz` — images of grids and grasps;
* :mod:`gpis_grasp_ros.ros` — nodes, rclpy conversions, bag player (the only rclpy user);
* :mod:`gpis_grasp_ros.tools` — the ``gpis-grasp`` command line, demo and benchmarks.

``gpis_grasp_ros.cli`` and ``gpis_grasp_ros.bench`` are entry shims for ``python -m``.
"""

__version__ = '0.1.0'
