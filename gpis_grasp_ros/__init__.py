"""gpis_grasp_ros: grasp planning under shape uncertainty with Gaussian process implicit surfaces.

The numeric core (sensing, sdf, gpis, blur, contacts, quality, planners, scene) imports no ROS;
the ROS 2 nodes live in :mod:`gpis_grasp_ros.nodes` and message conversion in
:mod:`gpis_grasp_ros.conversions`.
"""

__version__ = '0.1.0'
