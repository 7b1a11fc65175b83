"""Helpers shared by the tests: ROS harness (rosutil), synthetic posteriors (synthetic_shapes), tilted RGB-D scenes
(tilted_scene) and the shipped bags' posteriors (bag_posteriors)."""
