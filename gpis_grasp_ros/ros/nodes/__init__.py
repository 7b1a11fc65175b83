"""ROS 2 nodes: thin wiring of topics, parameters and services around the ROS-free core.

Each node's parameters are one declarative table (``PARAMETERS`` in its module, built with
:mod:`gpis_grasp_ros.ros.params`); its ``main`` is the rclpy idiom (:func:`.common.run_node`).
"""
