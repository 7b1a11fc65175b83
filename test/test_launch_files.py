"""The launch files, the RViz configuration and package.xml, checked without the launch packages.

The ``launch`` / ``launch_ros`` packages are not installed here (nor on PyPI), so the launch files are
parsed with ``ast`` and never imported. What they name is checked against the real nodes: each node
class is instantiated in-process with rclpy and its declared parameters, publishers and subscriptions
are read with the public rclpy API.
"""

from __future__ import annotations

import ast
import re
import runpy
import shlex
import sys
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import pytest
import rclpy
import setuptools
import yaml
from rclpy.context import Context
from rclpy.parameter import Parameter

ROOT = Path(__file__).resolve().parents[1]
LAUNCH = ROOT / 'launch'
PIPELINE = LAUNCH / 'gpis_grasp.launch.py'
REALSENSE = LAUNCH / 'realsense.launch.py'
RVIZ = ROOT / 'rviz' / 'gpis_grasp.rviz'
PACKAGE = 'gpis_grasp_ros'
#: Launch constructs the launch files may use (plain launch / launch_ros, nothing package-specific).
PLAIN = {'LaunchDescription', 'DeclareLaunchArgument', 'LaunchConfiguration', 'IncludeLaunchDescription',
         'PythonLaunchDescriptionSource', 'IfCondition', 'NotEqualsSubstitution', 'Node', 'PushRosNamespace',
         'GroupAction', 'get_package_share_directory'}


# ------------------------------------------------------------------------------------------ setup.py
def _setup_kwargs() -> dict[str, Any]:
    captured: dict[str, Any] = {}
    original = setuptools.setup
    setuptools.setup = lambda **kw: captured.update(kw)
    try:
        runpy.run_path(str(ROOT / 'setup.py'), run_name='__main__')
    finally:
        setuptools.setup = original
    return captured


SETUP = _setup_kwargs()
CONSOLE_SCRIPTS = {line.split('=')[0].strip(): line.split('=')[1].strip()
                   for line in SETUP['entry_points']['console_scripts']}


# ------------------------------------------------------------------------------------------ the nodes
def _node_classes() -> dict[str, Any]:
    from gpis_grasp_ros.ros.nodes.gpis_node import GpisNode
    from gpis_grasp_ros.ros.nodes.gripper_sim_node import GripperSimNode
    from gpis_grasp_ros.ros.nodes.planner_node import PlannerNode
    from gpis_grasp_ros.ros.nodes.segmentation_node import SegmentationNode
    return {'segmentation_node': SegmentationNode, 'gpis_node': GpisNode, 'planner_node': PlannerNode,
            'gripper_sim_node': GripperSimNode}


def _interface(cls: Any, overrides: list[Parameter] = ()) -> dict[str, Any]:
    """Declared parameters and the (type, fully qualified topic) of the publishers and subscriptions."""
    context = Context()
    rclpy.init(context=context)
    node = cls(context=context, parameter_overrides=list(overrides))
    try:
        names = set(node.list_parameters([], 0).names)
        pubs = {(p.msg_type, p.topic_name) for p in node.publishers}
        subs = {(s.msg_type, s.topic_name) for s in node.subscriptions}
        return {'parameters': names, 'publishes': pubs, 'subscribes': subs}
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.fixture(scope='module')
def nodes() -> dict[str, dict[str, Any]]:
    """Interface of every node; segmentation_node's is the union of both input modes."""
    out = {name: _interface(cls) for name, cls in _node_classes().items()}
    images = _interface(_node_classes()['segmentation_node'], [Parameter('input_mode', value='images')])
    for key in ('parameters', 'publishes', 'subscribes'):
        out['segmentation_node'][key] |= images[key]
    return out


def _topics(iface: dict[str, Any], key: str) -> set[str]:
    return {topic for _type, topic in iface[key]}


# ------------------------------------------------------------------------------------------ launch parsing
class LaunchFile:
    """The statically known content of a launch file: arguments, nodes, includes."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.tree = ast.parse(path.read_text())
        self.names: dict[str, ast.AST] = {}
        for node in ast.walk(self.tree):
            if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
                self.names[node.targets[0].id] = node.value
        self.calls = [n for n in ast.walk(self.tree) if isinstance(n, ast.Call)]

    def resolve(self, node: ast.AST) -> ast.AST:
        while isinstance(node, ast.Name) and node.id in self.names:
            node = self.names[node.id]
        return node

    def literal(self, node: ast.AST) -> Any:
        node = self.resolve(node)
        if isinstance(node, ast.Subscript):  # NAME['key'] of a module-level dict
            return self.literal(node.value)[self.literal(node.slice)]
        if isinstance(node, ast.Dict):
            return {self.literal(k): self.literal(v) for k, v in zip(node.keys, node.values, strict=True)}
        return ast.literal_eval(node)

    def calls_of(self, name: str) -> list[ast.Call]:
        return [c for c in self.calls if isinstance(c.func, ast.Name) and c.func.id == name]

    @staticmethod
    def keyword(call: ast.Call, name: str) -> ast.AST | None:
        return next((k.value for k in call.keywords if k.arg == name), None)

    def arguments(self) -> dict[str, Any]:
        """DeclareLaunchArgument name → default (a literal, or None when computed, e.g. an installed path)."""
        out = {}
        for call in self.calls_of('DeclareLaunchArgument'):
            default = self.keyword(call, 'default_value')
            try:
                value = self.literal(default)
            except ValueError:
                value = None
            out[self.literal(call.args[0])] = value
        return out

    def configurations(self) -> set[str]:
        return {self.literal(c.args[0]) for c in self.calls_of('LaunchConfiguration')}

    def elements(self, node: ast.AST | None) -> list[ast.AST]:
        """Items of a list expression, following names and expanding ``*name``."""
        node = self.resolve(node) if node is not None else None
        if node is None:
            return []
        if not isinstance(node, ast.List):
            return [node]
        out = []
        for item in node.elts:
            if isinstance(item, ast.Starred):
                out += self.elements(item.value)
            else:
                out.append(self.resolve(item))
        return out

    def nodes(self) -> list[dict[str, Any]]:
        out = []
        for call in self.calls_of('Node'):
            params: dict[str, ast.AST] = {}
            for item in self.elements(self.keyword(call, 'parameters')):
                if isinstance(item, ast.Dict):
                    params.update({self.literal(k): v for k, v in zip(item.keys, item.values, strict=True)})
            remaps = [self.literal(t.elts[0]) for t in self.elements(self.keyword(call, 'remappings'))]
            out.append({'package': self.literal(self.keyword(call, 'package')),
                        'executable': self.literal(self.keyword(call, 'executable')),
                        'parameters': params, 'remappings': remaps})
        return out

    def config_name(self, node: ast.AST) -> str | None:
        """The launch argument a value is (``LaunchConfiguration('x')`` → 'x'), else None."""
        node = self.resolve(node)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == 'LaunchConfiguration':
            return self.literal(node.args[0])
        return None


def _launch_files() -> list[Path]:
    return sorted(LAUNCH.glob('*.launch.py'))


def test_launch_files_exist_and_are_installed():
    assert {p.name for p in _launch_files()} == {'gpis_grasp.launch.py', 'realsense.launch.py'}
    installed = {dest: files for dest, files in SETUP['data_files']}
    assert sorted(installed[f'share/{PACKAGE}/launch']) == sorted(str(p.relative_to(ROOT)) for p in _launch_files())
    assert installed[f'share/{PACKAGE}/rviz'] == ['rviz/gpis_grasp.rviz']


@pytest.mark.parametrize('path', _launch_files(), ids=lambda p: p.name)
def test_launch_file_uses_plain_constructs_and_declares_what_it_reads(path):
    lf = LaunchFile(path)
    imported = set()
    for node in ast.walk(lf.tree):
        if isinstance(node, ast.ImportFrom):
            assert node.module.split('.')[0] in ('launch', 'launch_ros', 'ament_index_python'), node.module
            imported |= {a.name for a in node.names}
    assert imported <= PLAIN, imported - PLAIN
    assert 'generate_launch_description' in {f.name for f in lf.tree.body if isinstance(f, ast.FunctionDef)}
    missing = lf.configurations() - set(lf.arguments())
    assert not missing, f'{path.name} reads undeclared launch arguments {missing}'


@pytest.mark.parametrize('path', _launch_files(), ids=lambda p: p.name)
def test_launch_nodes_match_the_real_nodes(path, nodes):
    lf = LaunchFile(path)
    for entry in lf.nodes():
        if entry['package'] != PACKAGE:
            assert (entry['package'], entry['executable']) == ('rviz2', 'rviz2')
            continue
        exe = entry['executable']
        assert exe in CONSOLE_SCRIPTS, f'{path.name}: {exe} is not a console script of setup.py'
        if exe == 'bag_player':
            assert not entry['parameters'] and not entry['remappings']
            continue
        iface = nodes[exe]
        unknown = set(entry['parameters']) - iface['parameters']
        assert not unknown, f'{path.name}: {exe} has no parameter(s) {unknown}'
        topics = _topics(iface, 'publishes') | _topics(iface, 'subscribes')
        for source in entry['remappings']:
            assert '/' + source in topics, f'{path.name}: {exe} neither publishes nor subscribes {source}'


def test_pipeline_starts_every_node_once():
    executables = sorted(n['executable'] for n in LaunchFile(PIPELINE).nodes())
    assert executables == sorted(['segmentation_node', 'gpis_node', 'planner_node', 'gripper_sim_node',
                                  'bag_player', 'rviz2'])
    declared = LaunchFile(PIPELINE).arguments()
    for name in ('input_mode', 'sensor_model', 'target', 'target_point', 'params_file', 'namespace',
                 'use_sim_time', 'rviz', 'bag', 'gripper_sim'):
        assert name in declared, name


def _segmentation_overrides(lf: LaunchFile, values: dict[str, Any]) -> list[Parameter]:
    """segmentation_node's parameters as the launch file sets them, with the launch arguments ``values``
    (yaml-parsed like launch_ros parses parameter strings)."""
    seg = next(n for n in lf.nodes() if n['executable'] == 'segmentation_node')
    out = []
    for name, value in seg['parameters'].items():
        arg = lf.config_name(value)
        if arg is None or name == 'use_sim_time':
            continue
        out.append(Parameter(name, value=yaml.safe_load(str(values[arg]))))
    return out


def test_pipeline_defaults_are_accepted_by_segmentation_node():
    lf = LaunchFile(PIPELINE)
    overrides = _segmentation_overrides(lf, lf.arguments())
    assert {p.name for p in overrides} == {'input_mode', 'sensor_model', 'frames_to_average', 'target',
                                           'target_point'}
    iface = _interface(_node_classes()['segmentation_node'], overrides)
    assert '/camera/depth/points' in _topics(iface, 'subscribes')


def test_realsense_includes_the_pipeline_with_realsense_topics():
    rs, pipe = LaunchFile(REALSENSE), LaunchFile(PIPELINE)
    include = rs.calls_of('IncludeLaunchDescription')
    assert len(include) == 1
    source = rs.calls_of('PythonLaunchDescriptionSource')[0]
    assert 'gpis_grasp.launch.py' in ast.unparse(source)
    arguments = rs.keyword(include[0], 'launch_arguments')  # {...}.items()
    mapping = arguments.func.value
    given = {rs.literal(k): v for k, v in zip(mapping.keys, mapping.values, strict=True)}
    assert set(given) <= set(pipe.arguments()), set(given) - set(pipe.arguments())
    values = {k: (rs.literal(v) if rs.config_name(v) is None else rs.arguments()[rs.config_name(v)])
              for k, v in given.items()}
    assert values['input_mode'] == 'images' and values['sensor_model'] == 'realsense_d400'
    assert (values['rgb_topic'], values['depth_topic'], values['camera_info_topic']) == (
        '/camera/camera/color/image_raw', '/camera/camera/aligned_depth_to_color/image_raw',
        '/camera/camera/color/camera_info')
    from gpis_grasp_ros.data.rgbd_import import FRAME_ID
    assert values['fixed_frame'] == FRAME_ID  # realsense-ros's colour optical frame
    # the pipeline remaps the image-mode inputs to exactly these arguments
    seg = next(n for n in pipe.nodes() if n['executable'] == 'segmentation_node')
    assert {'camera/rgb/image_raw', 'camera/depth/image_raw', 'camera/rgb/camera_info'} <= set(seg['remappings'])
    merged = {**pipe.arguments(), **values}
    iface = _interface(_node_classes()['segmentation_node'], _segmentation_overrides(pipe, merged))
    assert {'/camera/rgb/image_raw', '/camera/depth/image_raw', '/camera/rgb/camera_info'} <= _topics(
        iface, 'subscribes')


# ------------------------------------------------------------------------------------------ rviz
def _rviz_topics(tree: Any) -> list[tuple[str, str]]:
    """(display class, topic) of every display naming a topic."""
    out = []
    if isinstance(tree, dict):
        if 'Class' in tree and isinstance(tree.get('Topic'), dict):
            out.append((tree['Class'], tree['Topic']['Value']))
        for value in tree.values():
            out += _rviz_topics(value)
    elif isinstance(tree, list):
        for value in tree:
            out += _rviz_topics(value)
    return out


def test_rviz_config_shows_what_the_nodes_publish(nodes):
    config = yaml.safe_load(RVIZ.read_text())
    from gpis_grasp_ros.sim.scene import FRAME_ID
    assert config['Visualization Manager']['Global Options']['Fixed Frame'] == FRAME_ID
    assert LaunchFile(PIPELINE).arguments()['fixed_frame'] == FRAME_ID
    published = {topic: msg_type for iface in nodes.values() for msg_type, topic in iface['publishes']}
    expected_type = {'rviz_default_plugins/Map': 'OccupancyGrid', 'rviz_default_plugins/Image': 'Image',
                     'rviz_default_plugins/MarkerArray': 'MarkerArray'}
    shown = _rviz_topics(config)
    assert {t for _c, t in shown} == {'/object/occupancy', '/gpis/mean_map', '/gpis/variance_map', '/grasp/markers',
                                      '/gpis/blur', '/grasp/image'}
    for cls, topic in shown:
        assert topic in published, f'no node publishes {topic}'
        assert published[topic].__name__ == expected_type[cls], (topic, cls)
    assert 'Update Topic' not in RVIZ.read_text()  # no map-update topics: no node publishes them


# ------------------------------------------------------------------------------------------ package.xml
ROSDEP_KEYS = {'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'cv2': 'python3-opencv', 'yaml': 'python3-yaml',
               'matplotlib': 'python3-matplotlib', 'tqdm': 'python3-tqdm', 'sklearn': 'python3-sklearn'}
PIP_ONLY = {'osqp': 'osqp', 'numba': 'numba', 'rosbags': 'rosbags', 'threadpoolctl': 'threadpoolctl',
            'distributed': 'distributed', 'OpenEXR': 'openexr'}


def _top_level_imports(paths: list[Path]) -> set[str]:
    names = set()
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names |= {a.name.split('.')[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                names.add(node.module.split('.')[0])
    return names


def test_package_xml_declares_every_imported_library():
    root = ET.parse(ROOT / 'package.xml').getroot()
    assert root.get('format') == '3'
    assert root.findtext('name') == PACKAGE and root.findtext('license') == 'BSD-3-Clause'
    depends = {e.text for tag in ('depend', 'exec_depend') for e in root.iter(tag)}
    code = sorted((ROOT / PACKAGE).rglob('*.py')) + sorted((ROOT / 'examples').rglob('*.py'))
    imported = _top_level_imports(code)
    stdlib = set(sys.stdlib_module_names) | {PACKAGE}
    third_party = imported - stdlib
    requirements = {re.split('[=<>\\[]', line)[0].strip().lower()
                    for line in (ROOT / 'requirements.txt').read_text().splitlines()
                    if line.strip() and not line.startswith('#')}
    for name in sorted(third_party):
        if name in ROSDEP_KEYS:
            assert ROSDEP_KEYS[name] in depends, name
        elif name in PIP_ONLY:
            assert PIP_ONLY[name] in requirements, name
        else:  # a ROS package
            assert name in depends, f'{name} is imported but not declared in package.xml'
    assert _top_level_imports(_launch_files()) - stdlib <= depends
    assert 'rviz2' in depends


def test_license_and_citation():
    text = (ROOT / 'LICENSE').read_text()
    assert text.startswith('BSD 3-Clause License') and 'gpis_grasp_ros contributors' in text
    cff = yaml.safe_load((ROOT / 'CITATION.cff').read_text())
    paper = cff['preferred-citation']
    assert cff['license'] == 'BSD-3-Clause'
    assert ' '.join(paper['title'].split()) == ('GP-GPIS-OPT: Grasp Planning With Shape Uncertainty Using Gaussian '
                                                'Process Implicit Surfaces and Sequential Convex Programming')
    assert [a['family-names'] for a in paper['authors']] == ['Mahler', 'Patil', 'Kehoe', 'van den Berg',
                                                             'Ciocarlie', 'Abbeel', 'Goldberg']
    assert paper['year'] == 2015


# ------------------------------------------------------------------------------------------ the README's commands
def _readme_launch_commands() -> list[tuple[str, dict[str, str]]]:
    """(launch file, {argument: value}) of every ``ros2 launch gpis_grasp_ros ...`` in the READMEs, shell variables
    of the README ($U, $V: a pixel; $PWD) given example values."""
    text = '\n'.join((ROOT / p).read_text() for p in ('README.md', 'bags/real/README.md')).replace('\\\n', ' ')
    text = text.replace('$U', '412.0').replace('$V', '230.0').replace('$PWD', '/tmp')
    out = []
    for line in text.splitlines():
        line = line.strip().strip('`')
        if not line.startswith(f'ros2 launch {PACKAGE} '):
            continue
        words = shlex.split(line.split(' #')[0])
        out.append((words[3], dict(w.split(':=', 1) for w in words[4:])))
    return out


def test_readme_launch_commands_name_declared_arguments_nodes_accept():
    commands = _readme_launch_commands()
    assert {name for name, _ in commands} == {'gpis_grasp.launch.py', 'realsense.launch.py'}
    assert any('frames_to_average' in args for _, args in commands)  # the one-frame replay
    pipe = LaunchFile(PIPELINE)
    for name, args in commands:
        lf = LaunchFile(LAUNCH / name)
        declared = lf.arguments()
        assert set(args) <= set(declared), (name, set(args) - set(declared))
        if lf.path == PIPELINE:
            values = {**declared, **args}
        else:  # realsense.launch.py: its values, passed on to the pipeline
            rs_values = {**declared, **args}
            include = lf.keyword(lf.calls_of('IncludeLaunchDescription')[0], 'launch_arguments').func.value
            given = {lf.literal(k): v for k, v in zip(include.keys, include.values, strict=True)}
            values = {**pipe.arguments(), **{k: (lf.literal(v) if lf.config_name(v) is None
                                                 else rs_values[lf.config_name(v)]) for k, v in given.items()}}
        overrides = _segmentation_overrides(pipe, {k: v for k, v in values.items() if v is not None})
        _interface(_node_classes()['segmentation_node'], overrides)  # raises on a value the node refuses
