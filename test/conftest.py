"""Shared pytest set-up.

DDS traffic stays on this machine and away from other test runs: every ROS process a test
starts runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a ROS_DOMAIN_ID picked per run
(both overridable from the environment, e.g. on a real robot).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
# Test helpers (rosutil, synthetic_shapes) live beside the tests that use them; the test folders
# mirror the package layout (test/core, test/data, test/sim, test/ros, test/tools).
for _sub in ('core', 'ros'):
    if str(ROOT / 'test' / _sub) not in sys.path:
        sys.path.insert(0, str(ROOT / 'test' / _sub))

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
# Domain ids 0..101 are valid for Fast DDS on Linux; spread runs over 40..99 by process id.
os.environ.setdefault('ROS_DOMAIN_ID', str(40 + os.getpid() % 60))
