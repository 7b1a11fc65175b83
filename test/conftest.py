"""Shared pytest set-up.

Test helpers live in the ``support`` package (``test/support``; ``pytest.ini`` puts ``test`` and the
repository root on the path). Markers: ``ros`` (set here for every test under ``test/ros`` and for
modules that mark themselves) and ``slow`` (set by the slow modules and tests): ``make test-fast``
runs ``-m "not ros and not slow"``, ``make test`` runs everything.

DDS traffic stays on this machine and away from other test runs: every ROS process a test
starts runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a ROS_DOMAIN_ID picked per run
(both overridable from the environment, e.g. on a real robot).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
# Domain ids 0..101 are valid for Fast DDS on Linux; spread runs over 40..99 by process id.
os.environ.setdefault('ROS_DOMAIN_ID', str(40 + os.getpid() % 60))


#: Modules outside test/ros that start ROS entities (rclpy contexts, nodes, the demo).
ROS_MODULES = ('test/test_launch_files.py', 'test/tools/test_demo.py')
#: Modules whose tests run commands end to end or plan on every shipped bag (seconds to minutes each).
SLOW_MODULES = ('test/tools/', 'test/core/test_segmentation_real.py', 'test/core/test_contact_refinement.py',
                'test/core/test_sdf_bank.py', 'test/core/test_antipodal_guarantee.py', 'test/core/test_shadow.py',
                'test/ros/test_real_bags.py', 'test/ros/test_head_bag_pipeline.py', 'test/ros/test_nodes_pipeline.py')


def pytest_collection_modifyitems(config, items):
    """Mark ``ros`` every test under test/ros and in :data:`ROS_MODULES`, ``slow`` those in :data:`SLOW_MODULES`."""
    for item in items:
        rel = Path(str(item.path)).resolve().relative_to(ROOT).as_posix()
        if rel.startswith('test/ros/') or rel in ROS_MODULES:
            item.add_marker(pytest.mark.ros)
        if any(rel == m or (m.endswith('/') and rel.startswith(m)) for m in SLOW_MODULES):
            item.add_marker(pytest.mark.slow)
