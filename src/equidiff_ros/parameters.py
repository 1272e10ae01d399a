"""Node parameters that describe themselves.

Each node module lists its parameters once (``PARAMETERS``: name, default, description, unit and
range) and declares each through ``NodeParameters.declare``, which hands rclpy a
``ParameterDescriptor``: ``ros2 param describe`` (the DescribeParameters service) then says what a
parameter is, and rclpy refuses a value outside its range when it is declared (a ``-p`` override,
a parameter file) or set. The same list is the node's ``--help`` and the parameter tables of
docs/parameters.md (``parameters_markdown``; ``scripts/gen_parameters_doc.py`` writes them,
test/test_node_parameters.py fails when they differ).

Ranges are the project's ``config.Bounds``. A ROS range has inclusive ends only, so an exclusive
end (``gt=0``: positive) is given to ROS as the inclusive one plus ``additional_constraints``, and
checked here after the declaration, as an integer given to a float parameter (``number``) is.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from collections.abc import Iterator, Mapping
from typing import Any

from equidiff_core.config import Bounds, ConfigError, field_bounds, field_choices, field_description

_NOT_GIVEN = object()


class ParameterError(ConfigError):
    """A parameter's value the node cannot run with: out of range, of the wrong type, not a choice."""


@dataclasses.dataclass(frozen=True)
class NodeParameter:
    name: str
    default: Any  # its type is the parameter's type
    description: str  # what it is (the unit goes in ``bounds``)
    bounds: Bounds | None = None  # unit and range
    choices: tuple[str, ...] = ()  # the values a string parameter may take
    default_from: str = ""  # where a default computed at start comes from ("lab.yaml observation_hz")
    number: bool = False  # a float that also takes an integer (-p rate_hz:=5); ROS types 5 as an integer
    dynamic_typing: bool = False  # takes values of several types ("auto" or a number)

    @property
    def unit(self) -> str:
        return self.bounds.unit if self.bounds is not None else ""

    def range_text(self) -> str:
        """``0 < x <= 1``, or the choices, or "" when any value of the type goes."""
        if self.choices:
            return " | ".join(self.choices)
        if self.bounds is not None and self.bounds.describe() != "any":
            return self.bounds.describe()
        return ""

    def descriptor(self):
        from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

        unit = f" [{self.unit}]" if self.unit else ""
        default = f" Default: {self.default_from}." if self.default_from else ""
        descriptor = ParameterDescriptor(
            description=f"{self.description}{unit}.{default}",
            dynamic_typing=self.number or self.dynamic_typing,
        )
        constraints = []
        bounds = self.bounds
        if bounds is not None and bounds.describe() != "any":
            low = bounds.ge if bounds.ge is not None else bounds.gt
            high = bounds.le if bounds.le is not None else bounds.lt
            if isinstance(self.default, int) and not isinstance(self.default, bool) and not self.number:
                # integers: an exclusive end is the next integer, so ROS's range says it all
                low = -(2**63) if low is None else math.floor(low) + 1 if bounds.gt is not None else math.ceil(low)
                high = 2**63 - 1 if high is None else math.ceil(high) - 1 if bounds.lt is not None else math.floor(high)
                descriptor.integer_range = [IntegerRange(from_value=int(low), to_value=int(high), step=0)]
            else:
                low = -math.inf if low is None else float(low)
                high = math.inf if high is None else float(high)
                descriptor.floating_point_range = [FloatingPointRange(from_value=low, to_value=high, step=0.0)]
                if bounds.gt is not None or bounds.lt is not None:
                    constraints.append(f"{bounds.describe()} {self.unit}".strip())
        if isinstance(self.default, list) and descriptor.floating_point_range:
            constraints.append("the range is each item's")  # rclpy checks scalars only: the node checks items
        if self.choices:
            constraints.append("one of " + ", ".join(self.choices))
        if self.number:
            constraints.append("an integer is read as a float")
        descriptor.additional_constraints = "; ".join(constraints)
        return descriptor

    def check(self, value: Any, node_name: str) -> Any:
        """The declared value, or ParameterError saying why the node cannot run with it; rclpy has
        checked the type and the inclusive range already, not an exclusive end, an array's items or a
        number given as an integer."""
        if self.number:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise self.error(f"{self.name}: must be a number, got {value!r}", node_name)
            value = float(value)
        if self.choices and value not in self.choices:
            raise self.error(f"{self.name}: must be one of {', '.join(self.choices)}, got {value!r}", node_name)
        if hasattr(value, "tolist"):  # rclpy hands a numeric array parameter over as an array.array
            value = value.tolist()
        if self.bounds is not None and not isinstance(value, (str, bool)):
            try:
                self.bounds.check(value, self.name)
            except ConfigError as err:
                raise self.error(str(err), node_name) from None
        return value

    def error(self, what: str, node_name: str) -> ParameterError:
        """``parameter <name>: <what> (<node>); <what the parameter is>``: one line, all a reader needs."""
        return ParameterError(f"parameter {what} ({node_name}); {self.description}")


LAB_CONFIG = NodeParameter(
    "lab_config",
    "",
    "Path of lab.yaml: cameras, workspace, safety box, robot, observation rate",
    default_from="the installed config/lab.yaml",
)


class NodeParameters:
    """A node's parameters, in declaration order; ``declare`` declares one by name."""

    def __init__(self, *parameters: NodeParameter):
        self.by_name = {p.name: p for p in parameters}
        if len(self.by_name) != len(parameters):
            raise ValueError("a parameter is listed twice")
        for p in parameters:
            if not p.description.strip():
                raise ValueError(f"parameter {p.name} has no description")

    def __iter__(self) -> Iterator[NodeParameter]:
        return iter(self.by_name.values())

    def __add__(self, other: NodeParameters) -> NodeParameters:
        return NodeParameters(*self, *other)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.by_name)

    def declare(self, node, name: str, default: Any = _NOT_GIVEN) -> Any:
        """``declare`` the parameter called ``name``."""
        return declare(node, self.by_name[name], default)


def declare(node, parameter: NodeParameter, default: Any = _NOT_GIVEN) -> Any:
    """Declare ``parameter`` on ``node`` with its descriptor and return its value, checked.
    ``default``: the default computed at start, for a parameter whose ``default_from`` says where it
    comes from. A value out of range or of the wrong type is a ParameterError naming the parameter,
    the value and what it is, so the node exits with that one line (``runner.run_nodes``)."""
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException

    name = parameter.name
    if (default is _NOT_GIVEN) == bool(parameter.default_from):
        raise TypeError(f"parameter {name}: pass its default exactly when it is computed at start (default_from)")
    value = parameter.default if default is _NOT_GIVEN else default
    if parameter.number:
        value = float(value)
    try:
        declared = node.declare_parameter(name, value, parameter.descriptor()).value
    except (InvalidParameterValueException, InvalidParameterTypeException) as err:
        # rclpy's reason names the range or the type and the value given; add the unit and what it is
        reason = str(err).split("Reason: ", 1)[-1].removesuffix(f": {name}")
        unit = f", unit {parameter.unit}" if parameter.unit else ""
        raise parameter.error(f"{name}: {reason}{unit}", node.get_name()) from None
    return parameter.check(declared, node.get_name())


def bounds_of(cls: type, field_name: str) -> Bounds:
    """The unit and range declared on a config dataclass's field: a parameter that overrides that
    field (voxel_node's ``observation_hz``) has the same."""
    bounds = field_bounds(next(f for f in dataclasses.fields(cls) if f.name == field_name))
    if bounds is None:
        raise ValueError(f"{cls.__name__}.{field_name} declares no unit or range")
    return bounds


def config_parameters(cls: type) -> NodeParameters:
    """One parameter per field of config dataclass ``cls`` (``common.declare_config``), described by
    the field itself (``config.described`` / ``config.bounded``). Fields without a default, or
    holding a mapping, are not parameters."""
    hints = typing.get_type_hints(cls)
    parameters = []
    for f in dataclasses.fields(cls):
        default = f.default
        if default is dataclasses.MISSING or default is None or isinstance(default, dict):
            continue
        if isinstance(default, tuple):  # a ROS array parameter is typed by its items: (1, 1) of floats is [1.0, 1.0]
            default = [float(v) for v in default] if "float" in str(hints[f.name]) else list(default)
        parameters.append(NodeParameter(f.name, default, field_description(f), field_bounds(f), field_choices(f)))
    return NodeParameters(*parameters)


def _default_text(parameter: NodeParameter) -> str:
    if parameter.default_from:
        return parameter.default_from
    value = parameter.default
    if isinstance(value, str):
        return f'`"{value}"`' if value == "" else f"`{value}`"
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, list):
        return f"`[{', '.join(map(repr, value))}]`"
    return f"`{value!r}`"  # a float shows its point: 1.0, so the parameter's type is plain


def parameters_help(parameters: NodeParameters) -> str:
    """The parameters for ``--help``: one line each (``ros2 param describe`` says the same)."""
    lines = ["", "Parameters (-p name:=value):"]
    for p in parameters:
        unit = f" [{p.unit}]" if p.unit else ""
        allowed = f"; {p.range_text()}" if p.range_text() else ""
        lines.append(f"  {p.name} = {_default_text(p).strip('`')}{unit}{allowed}: {p.description}")
    return "\n".join(lines) + "\n"


def _cell(text: str) -> str:
    return text.replace("|", "\\|")  # a bar would end a markdown table cell


def parameter_table(parameters: NodeParameters) -> str:
    """The markdown table of a node's parameters (docs/parameters.md, ``--help``)."""
    lines = ["| parameter | default | unit | range | what it is |", "| --- | --- | --- | --- | --- |"]
    for p in parameters:
        lines.append(
            f"| `{p.name}` | {_default_text(p)} | {p.unit or '-'} | {_cell(p.range_text()) or '-'} | {_cell(p.description)} |"
        )
    return "\n".join(lines)


# every node executable (setup.py's NODES): the nodes whose parameters docs/parameters.md lists
NODES = ("camera_node", "voxel_node", "policy_node", "franka_node", "teleop_node", "recorder_node", "twin_node")
DOC_BEGIN = "<!-- parameters: generated by scripts/gen_parameters_doc.py from each node's PARAMETERS; do not edit -->"
DOC_END = "<!-- parameters: end -->"


def node_parameters() -> dict[str, NodeParameters]:
    """Each node's ``PARAMETERS`` (imports every node module: torch, MuJoCo)."""
    import importlib

    return {node: importlib.import_module(f"equidiff_ros.{node}").PARAMETERS for node in NODES}


def parameters_markdown(nodes: Mapping[str, NodeParameters]) -> str:
    """The generated part of docs/parameters.md, markers included: one table per node."""
    sections = [DOC_BEGIN]
    for node, parameters in nodes.items():
        sections.append(f"### {node}\n\n{parameter_table(parameters)}")
    sections.append(DOC_END)
    return "\n\n".join(sections)


def with_parameter_tables(document: str, nodes: Mapping[str, NodeParameters]) -> str:
    """``document`` (docs/parameters.md) with its generated part replaced by the tables of ``nodes``."""
    begin, end = document.index(DOC_BEGIN), document.index(DOC_END) + len(DOC_END)
    return document[:begin] + parameters_markdown(nodes) + document[end:]
