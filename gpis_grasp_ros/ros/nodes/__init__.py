"""ROS 2 nodes: thin wiring of topics, parameters and services around the ROS-free core."""
