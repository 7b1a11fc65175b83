"""The package layout is the architecture: the folder a module sits in tells what it may import.

* ``core``  — the paper (no ROS, no I/O): may import only ``core``.
* ``data``  — bags and message layouts, ROS-free: ``core``, ``data``.
* ``sim``   — the scene simulator and object catalogue: ``core``, ``data``, ``sim``.
* ``viz``   — images of grids and grasps: ``core``, ``viz``.
* ``ros``   — nodes, rclpy conversions, bag player (the only place for rclpy and messages):
  ``core``, ``data``, ``sim``, ``viz``, ``ros`` (the gripper simulator node executes grasps with ``sim``).
* ``tools`` — command line, demo, benchmarks: anything.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / 'gpis_grasp_ros'

ALLOWED: dict[str, set[str]] = {
    'core': {'core'},
    'data': {'core', 'data'},
    'sim': {'core', 'data', 'sim'},
    'viz': {'core', 'viz'},
    'ros': {'core', 'data', 'sim', 'viz', 'ros'},
    'tools': {'core', 'data', 'sim', 'viz', 'ros', 'tools'},
}
ROS_FREE = ('core', 'data', 'sim', 'viz')
ROS_PREFIXES = ('rclpy', 'rosidl', 'rmw', 'gpis_grasp_interfaces', 'builtin_interfaces', 'action_msgs')


def _is_ros_module(name: str) -> bool:
    top = name.split('.')[0]
    return top.startswith(ROS_PREFIXES) or top.endswith('_msgs') or top.endswith('_srvs')


def _imports(path: Path) -> list[str]:
    """Every module a file imports (absolute names; relative imports resolved), at any depth."""
    rel = path.relative_to(ROOT).with_suffix('').parts
    names = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = list(rel[:-node.level])
                names.append('.'.join(base + ([node.module] if node.module else [])))
            else:
                names.append(node.module or '')
    return names


def _modules(folder: str) -> list[Path]:
    return sorted((PKG / folder).rglob('*.py'))


@pytest.mark.parametrize('folder', sorted(ALLOWED))
def test_folder_imports_only_what_its_layer_allows(folder):
    assert _modules(folder), f'no modules under {folder}/'
    bad = []
    for path in _modules(folder):
        for name in _imports(path):
            parts = name.split('.')
            if parts[0] == 'gpis_grasp_ros' and len(parts) > 1 and parts[1] in ALLOWED:
                if parts[1] not in ALLOWED[folder]:
                    bad.append(f'{path.relative_to(ROOT)} imports {name}')
            if folder in ROS_FREE and _is_ros_module(name):
                bad.append(f'{path.relative_to(ROOT)} imports ROS module {name}')
    assert not bad, '\n'.join(bad)


def test_checker_catches_a_forbidden_import(tmp_path):
    """The AST walk sees lazy imports inside functions and relative imports (guards the test)."""
    fake = ROOT / 'gpis_grasp_ros' / 'core' / '_layout_probe.py'
    src = 'def f():\n    import rclpy\n    from ..ros import conversions\n    return rclpy, conversions\n'
    try:
        fake.write_text(src)
        names = _imports(fake)
    finally:
        fake.unlink()
    assert 'rclpy' in names and 'gpis_grasp_ros.ros' in names


def test_importing_the_ros_free_layers_loads_no_ros_module():
    """Import every module under core/, data/, sim/, viz/ in a fresh interpreter: no rclpy, no messages."""
    modules = ['gpis_grasp_ros.' + '.'.join(p.relative_to(PKG).with_suffix('').parts).removesuffix('.__init__')
               for folder in ROS_FREE for p in _modules(folder)]
    code = ('import importlib, json, sys\n'
            f'for m in {modules!r}: importlib.import_module(m)\n'
            'print(json.dumps(sorted(sys.modules)))\n')
    out = subprocess.run([sys.executable, '-c', code], cwd=ROOT, capture_output=True, text=True, check=True)
    loaded = json.loads(out.stdout.strip().splitlines()[-1])
    assert len(modules) >= 15
    ros = [m for m in loaded if _is_ros_module(m)]
    assert not ros, f'ROS modules loaded by the ROS-free layers: {ros[:10]}'


def test_no_module_left_at_the_top_but_the_entry_shims():
    top = sorted(p.name for p in PKG.glob('*.py'))
    assert top == ['__init__.py', 'bench.py', 'cli.py']
