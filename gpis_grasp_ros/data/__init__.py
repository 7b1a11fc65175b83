"""Data in and out, ROS-free: MCAP bags (rosbags), message layouts ↔ numpy, recorded scenes.
May import ``core`` and ``data``."""
