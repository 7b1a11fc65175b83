"""Declarative ROS parameters: one table per node, in the spirit of scikit-learn's ``_parameter_constraints``.

Each :class:`Param` gives a parameter's name, type, default, range or choices, unit, description,
whether it is read-only, and where its value goes in the library (a dataclass and its field, with
the rule that maps the ROS value onto the field, e.g. ``0 = None``). The default is the library
field's default unless the table says otherwise. A :class:`ParamTable` declares its parameters on a
node (``ParameterDescriptor`` with the description, the range and read-only), checks every value
at start-up and on every set (a rejected set fails with the reason and changes nothing), and
hands the node the keyword arguments of its library dataclasses: nothing is declared or copied
by hand.

The same tables generate ``config/default.yaml`` and the README's parameter tables::

    python -m gpis_grasp_ros.ros.params --yaml > config/default.yaml
    python -m gpis_grasp_ros.ros.params --markdown planner_node
    python -m gpis_grasp_ros.ros.params --update-readme README.md
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import math
import re
import sys
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: Each node's module and the name of its table (imported on demand by the generator).
NODE_TABLES = {
    'segmentation_node': 'gpis_grasp_ros.ros.nodes.segmentation_node',
    'gpis_node': 'gpis_grasp_ros.ros.nodes.gpis_node',
    'planner_node': 'gpis_grasp_ros.ros.nodes.planner_node',
    'gripper_sim_node': 'gpis_grasp_ros.ros.nodes.gripper_sim_node',
}

YAML_HEADER = ('# Default parameters of the gpis_grasp_ros nodes, generated from their parameter tables:\n'
               '#     python -m gpis_grasp_ros.ros.params --yaml > config/default.yaml\n'
               '# Use: ros2 run gpis_grasp_ros planner_node --ros-args --params-file config/default.yaml\n'
               '# Keys are /**/<node name>: they apply to the node in any namespace.\n')


# --------------------------------------------------------------------------- value rules
@dataclass(frozen=True)
class Rule:
    """How a ROS value maps onto a library field (and a library default back onto a ROS default)."""

    text: str  # shown in the docs, e.g. '0 = None'
    to_library: Callable[[Any], Any]
    from_library: Callable[[Any], Any]


AS_IS = Rule('', lambda v: v, lambda v: v)
#: 0 means "not set" (the library's None: a data-driven default or no bound).
ZERO_IS_NONE = Rule('0 = None', lambda v: float(v) or None, lambda v: 0.0 if v is None else float(v))
#: A negative value means "not set" (the library's None).
NEGATIVE_IS_NONE = Rule('negative = None', lambda v: None if float(v) < 0 else float(v),
                        lambda v: -1.0 if v is None else float(v))
#: A box or plane of numbers, all zero = not given (None).
ZEROS_ARE_NONE = Rule('all 0 = None', lambda v: None if not any(float(x) for x in v) else tuple(float(x) for x in v),
                      lambda v: [0.0, 0.0, 0.0, 0.0] if v is None else [float(x) for x in v])

_KINDS = {bool: 'bool', int: 'integer', float: 'double', str: 'string', list: 'double[]'}
_FROM_LIBRARY = object()


@dataclass(frozen=True)
class Param:
    """One ROS parameter: what ``ros2 param describe`` says about it and where it goes in the library.

    ``target``/``field`` name the dataclass (library or node configuration) and field the value
    sets (``field`` defaults to ``name``); ``rule`` maps the ROS value onto it. ``default`` defaults
    to that field's default (through ``rule.from_library``). ``low``/``high`` are inclusive.
    ``size`` is the required length of a ``list`` parameter.
    """

    name: str
    kind: type
    description: str
    target: type | None = None
    field: str | None = None
    default: Any = _FROM_LIBRARY
    unit: str = ''
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] = ()
    size: int | None = None
    read_only: bool = False
    rule: Rule = AS_IS

    @property
    def field_name(self) -> str:
        return self.field or self.name

    @property
    def maps_to(self) -> str:
        """'Dataclass.field' the value sets ('' when the node uses it itself)."""
        return f'{self.target.__name__}.{self.field_name}' if self.target is not None else ''

    def default_value(self) -> Any:
        """The ROS default: the table's, else the target field's default mapped back by the rule."""
        if self.default is not _FROM_LIBRARY:
            value = self.default
        else:
            if self.target is None:
                raise ValueError(f"parameter '{self.name}' has neither a default nor a target field")
            spec = {f.name: f for f in dataclasses.fields(self.target)}[self.field_name]
            if spec.default is not dataclasses.MISSING:
                library = spec.default
            elif spec.default_factory is not dataclasses.MISSING:
                library = spec.default_factory()
            else:
                raise ValueError(f'{self.maps_to} has no default: give parameter {self.name!r} one')
            value = self.rule.from_library(library)
        return [float(v) for v in value] if self.kind is list else self.kind(value)

    def replace(self, **changes: Any) -> Param:
        """A copy with some attributes changed (a node's variant of a shared parameter)."""
        return dataclasses.replace(self, **changes)

    def check(self, value: Any) -> None:
        """ValueError naming the parameter when ``value`` is outside its type, range, choices or size."""
        if self.kind is list:
            values = [float(v) for v in value]
            if self.size is not None and len(values) != self.size:
                raise ValueError(f"parameter '{self.name}' must have {self.size} numbers, got {values}")
            if not all(math.isfinite(v) for v in values):
                raise ValueError(f"parameter '{self.name}' must hold finite numbers, got {values}")
            return
        if self.kind is bool:
            if not isinstance(value, bool):
                raise ValueError(f"parameter '{self.name}' must be true or false, got {value!r}")
            return
        if self.choices and value not in self.choices:
            raise ValueError(f"parameter '{self.name}' must be one of {list(self.choices)}, got '{value}'")
        if self.kind in (int, float):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"parameter '{self.name}' must be a finite number, got {value!r}")
            if (self.low is not None and value < self.low) or (self.high is not None and value > self.high):
                raise ValueError(f"parameter '{self.name}'={value!r} is outside {self.constraints_text()}"
                                 + (f' {self.unit}' if self.unit else ''))

    def _number(self, x: float) -> str:
        return str(int(x)) if self.kind is int else f'{x:g}'

    def to_library(self, value: Any) -> Any:
        """The value for the target field."""
        if self.kind is list:
            value = [float(v) for v in value]
        elif self.kind is not str:
            value = self.kind(value)
        return self.rule.to_library(value)

    def descriptor_text(self) -> str:
        """Description with unit and rule, as ``ros2 param describe`` shows it."""
        text = self.description
        if self.unit:
            text += f' [{self.unit}]'
        return text

    def constraints_text(self) -> str:
        """Range or choices in words ('' when unconstrained)."""
        if self.choices:
            return 'one of: ' + ', '.join(self.choices)
        if self.low is not None and self.high is not None:
            return f'[{self._number(self.low)}, {self._number(self.high)}]'
        if self.size is not None:
            return f'{self.size} numbers'
        return ''


class ParamTable:
    """The parameters of one node; ``checks`` are cross-parameter rules raising ValueError."""

    def __init__(self, node: str, params: Iterable[Param],
                 checks: Sequence[Callable[[dict[str, Any]], None]] = ()) -> None:
        params = list(params)
        self.node = node
        self.params = {p.name: p for p in params}
        if len(self.params) != len(params):
            raise ValueError(f'{node}: duplicate parameter names')
        self.checks = tuple(checks)

    def __iter__(self):
        return iter(self.params.values())

    def __getitem__(self, name: str) -> Param:
        return self.params[name]

    def defaults(self) -> dict[str, Any]:
        return {p.name: p.default_value() for p in self}

    # ------------------------------------------------------------------ validation and mapping
    def validate(self, values: dict[str, Any]) -> None:
        """ValueError with the reason when any value or cross-parameter rule is violated."""
        for p in self:
            p.check(values[p.name])
        for check in self.checks:
            check(values)

    def kwargs(self, values: dict[str, Any], target: type) -> dict[str, Any]:
        """Keyword arguments of ``target`` from the parameters that map onto it."""
        return {p.field_name: p.to_library(values[p.name]) for p in self if p.target is target}

    # ------------------------------------------------------------------ rclpy
    def declare(self, node: Any) -> dict[str, Any]:
        """Declare every parameter on ``node`` with its descriptor; the start-up values (checked)."""
        from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

        for p in self:
            descriptor = ParameterDescriptor(description=p.descriptor_text(), read_only=p.read_only)
            if p.choices:
                descriptor.additional_constraints = p.constraints_text()
            if p.low is not None and p.high is not None:
                if p.kind is int:
                    descriptor.integer_range = [IntegerRange(from_value=int(p.low), to_value=int(p.high), step=0)]
                elif p.kind is float:
                    descriptor.floating_point_range = [
                        FloatingPointRange(from_value=float(p.low), to_value=float(p.high), step=0.0)]
            node.declare_parameter(p.name, p.default_value(), descriptor)
        values = self.values(node)
        self.validate(values)
        return values

    def values(self, node: Any) -> dict[str, Any]:
        """Current values of the table's parameters on ``node``."""
        return {p.name: node.get_parameter(p.name).value for p in self}

    def watch(self, node: Any, build: Callable[[dict[str, Any]], Any], apply: Callable[[Any], None]) -> Any:
        """Declare the parameters, build the configuration now and again after every accepted set.

        ``build(values)`` turns parameter values into the node's configuration (raising ValueError
        on invalid combinations, e.g. a library dataclass refusing a value); ``apply(config)``
        installs it. A set that :meth:`validate` or ``build`` rejects fails with the reason and
        changes nothing. Returns the start-up configuration.
        """
        from rcl_interfaces.msg import SetParametersResult

        values = self.declare(node)
        config = build(values)
        apply(config)

        def on_set(params: list) -> SetParametersResult:
            new = self.values(node)
            new.update({p.name: p.value for p in params if p.name in self.params})
            try:
                self.validate(new)
                build(new)
            except (ValueError, TypeError) as exc:
                return SetParametersResult(successful=False, reason=str(exc))
            return SetParametersResult(successful=True)

        def post_set(params: list) -> None:
            if not any(p.name in self.params for p in params):
                return
            apply(build(self.values(node)))
            changed = ', '.join(f'{p.name}={p.value!r}' for p in params)
            node.get_logger().info(f'parameters applied: {changed}')

        node.add_on_set_parameters_callback(on_set)
        node.add_post_set_parameters_callback(post_set)
        return config


# --------------------------------------------------------------------------- generators
def node_tables() -> dict[str, ParamTable]:
    """Every node's table (node name → table), in launch order."""
    return {node: importlib.import_module(module).PARAMETERS for node, module in NODE_TABLES.items()}


def _yaml_value(value: Any) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, str):
        return f"'{value}'"
    return repr(value)


def render_yaml(tables: dict[str, ParamTable] | None = None) -> str:
    """config/default.yaml: every node's parameters (sorted) with their defaults and descriptions."""
    lines = [YAML_HEADER]
    for node, table in (tables or node_tables()).items():
        lines += [f'/**/{node}:', '  ros__parameters:']
        for p in sorted(table, key=lambda p: p.name):
            notes = [t for t in (p.constraints_text(), 'read-only: set at start-up' if p.read_only else '') if t]
            lines.append(f'    # {p.descriptor_text()}' + (f' ({"; ".join(notes)})' if notes else ''))
            lines.append(f'    {p.name}: {_yaml_value(p.default_value())}')
        lines.append('')
    return '\n'.join(lines)


def _md(text: str) -> str:
    return text.replace('|', '\\|')


def render_markdown(node: str, table: ParamTable | None = None) -> str:
    """The README's parameter table of ``node``."""
    table = table or node_tables()[node]
    rows = ['| parameter | type | default | range | unit | description | sets |', '|---|---|---|---|---|---|---|']
    for p in sorted(table, key=lambda p: p.name):
        constraint = p.constraints_text() + (' (read-only)' if p.read_only else '')
        rows.append(f'| `{p.name}` | {_KINDS[p.kind]} | `{_yaml_value(p.default_value())}` | {_md(constraint)} | '
                    f'{_md(p.unit)} | {_md(p.description)} | {f"`{p.maps_to}`" if p.maps_to else "node"} |')
    return '\n'.join(rows) + '\n'


def _markers(node: str) -> tuple[str, str]:
    return f'<!-- params:{node} -->', f'<!-- /params:{node} -->'


def readme_nodes(text: str) -> list[str]:
    """Nodes whose table markers are present in ``text``."""
    return [node for node in NODE_TABLES if all(m in text for m in _markers(node))]


def update_readme(text: str, tables: dict[str, ParamTable] | None = None) -> str:
    """``text`` with each node's table between its ``<!-- params:NODE -->`` markers regenerated.

    ValueError naming the missing markers when a node has none (or only one of the pair).
    """
    tables = tables or node_tables()
    missing = [f'{a} ... {b}' for a, b in (_markers(n) for n in tables) if a not in text or b not in text]
    if missing:
        raise ValueError('README has no parameter table markers for: ' + ', '.join(missing))
    for node, table in tables.items():
        start, end = _markers(node)
        pattern = re.compile(re.escape(start) + r'.*?' + re.escape(end), re.S)
        block = f'{start}\n{render_markdown(node, table)}{end}'
        text = pattern.sub(lambda _m, b=block: b, text, count=1)
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m gpis_grasp_ros.ros.params',
                                     description='Generate config/default.yaml and the README parameter tables.')
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument('--yaml', action='store_true', help='print config/default.yaml')
    group.add_argument('--markdown', metavar='NODE', choices=list(NODE_TABLES), help="print NODE's table")
    group.add_argument('--update-readme', metavar='README', type=Path,
                       help='rewrite the tables between <!-- params:NODE --> ... <!-- /params:NODE --> markers')
    args = parser.parse_args(argv)
    if args.yaml:
        sys.stdout.write(render_yaml())
    elif args.markdown:
        sys.stdout.write(render_markdown(args.markdown))
    else:
        try:
            text = args.update_readme.read_text()
            args.update_readme.write_text(update_readme(text))
        except (OSError, ValueError) as exc:
            print(f'error: {exc}', file=sys.stderr)
            return 1
    return 0


__all__ = ['AS_IS', 'NEGATIVE_IS_NONE', 'ZEROS_ARE_NONE', 'ZERO_IS_NONE', 'Param', 'ParamTable', 'Rule',
           'render_markdown', 'render_yaml', 'update_readme']


if __name__ == '__main__':
    sys.exit(main())
