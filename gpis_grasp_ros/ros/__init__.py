"""The ROS 2 layer: nodes, rclpy message conversions, the bag player. The only folder that imports
rclpy and message packages; may import ``core``, ``data``, ``viz`` and ``ros``."""
