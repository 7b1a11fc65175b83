"""ROS 2 nodes: thin wiring of topics, parameters and services around the ROS-free core.

When a node runs as a program (``ros2 run``/console script or ``python -m``), SIGINT and SIGTERM
are blocked here, before numpy, OSQP and DDS start their threads, so every thread inherits the
block and :func:`gpis_grasp_ros.ros.nodes.common.run_node` receives them with ``sigwait``. Otherwise
OSQP's solver, which installs its own SIGINT handler during each solve, would swallow a Ctrl-C
arriving mid-plan ("Solver interrupted") and the node would never shut down.
"""

import os
import signal
import sys

NODE_PROGRAMS = ('segmentation_node', 'gpis_node', 'planner_node', 'gripper_sim_node')


def _running_as_node_program() -> bool:
    argv = list(getattr(sys, 'orig_argv', []))
    if '-m' in argv:
        i = argv.index('-m')
        return i + 1 < len(argv) and argv[i + 1].startswith(__name__ + '.')
    return os.path.basename(sys.argv[0] if sys.argv else '') in NODE_PROGRAMS


#: True when this process is a node program whose signals are taken by run_node's sigwait thread.
SIGNALS_BLOCKED = False
if _running_as_node_program():
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    SIGNALS_BLOCKED = True
