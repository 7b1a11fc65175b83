"""The paper's numerics (Mahler et al., ICRA 2015): sensing, SDF, GPIS, GPIS-Blur, contacts,
quality, SCP, planners and the perception pipeline. No ROS, no I/O: imports only ``core``."""
