"""config/default.yaml documents exactly the parameters the nodes declare, with their defaults."""

from __future__ import annotations

import sys
from pathlib import Path

import rclpy
import yaml
from rclpy.context import Context

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / 'scripts'))

from gen_default_config import node_parameters  # noqa: E402


def test_default_yaml_matches_declared_parameters():
    context = Context()
    rclpy.init(context=context)
    try:
        declared = node_parameters(context)
    finally:
        rclpy.try_shutdown(context=context)
    documented = yaml.safe_load((ROOT / 'config' / 'default.yaml').read_text())
    # '/**/node:' keys: the file applies to the nodes under any namespace
    assert set(documented) == {f'/**/{node}' for node in declared}
    for node, rows in declared.items():
        values = documented[f'/**/{node}']['ros__parameters']
        assert set(values) == {name for name, _, _ in rows}, node
        for name, default, description in rows:
            assert values[name] == default, f'{node}.{name}'
            assert description, f'{node}.{name} has no description'
