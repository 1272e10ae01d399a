"""Typed configuration: the lab set-up YAML (config/lab.yaml), the strict YAML loader every config
file goes through, and a small dict -> dataclass builder.

Every config object in the project is a frozen dataclass built with ``from_dict``: unknown
keys, missing required keys, wrong types and values outside a field's declared physical range
fail with the dotted path of the culprit ("lab.yaml.cameras[1].extrinsics.translation: expected
3 items, got 2"), never later as a silent wrong value. A field's unit and range are written once,
where it is declared (``bounded``); docs/limits.md is generated from those declarations
(``equidiff_core.limits_table``). We do not use pydantic: the builder is small, has no runtime
dependency and is shared by all configs (lab, model presets, control limits).

YAML is read with ``StrictLoader``: a duplicate key is an error naming both lines, and scalars
follow YAML 1.2's core schema (only ``true``/``false`` are booleans, only plain decimal or
``0x`` hex are integers), so ``serial: 0123456`` stays the string it was written as instead of
YAML 1.1's octal 42798, ``no`` is not ``False`` and ``1:30`` is not 90.
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import yaml

from . import geometry

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration file or dict that does not describe a valid configuration."""


# --- Strict YAML -------------------------------------------------------------------------------

# YAML 1.2 core schema scalars. PyYAML implements YAML 1.1, where 0123456 is octal, yes/no/on/off
# are booleans, 1:30 is a base-60 number and YYYY-MM-DD a date: none of that may reach a field.
_BOOL = re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$")
_INT = re.compile(r"^(?:[-+]?(?:0|[1-9][0-9]*)|[-+]?0x[0-9a-fA-F]+)$")
_FLOAT = re.compile(
    r"^(?:[-+]?(?:[0-9]+\.[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?"
    r"|[-+]?[0-9]+[eE][-+]?[0-9]+"
    r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"
)
_NULL = re.compile(r"^(?:~|null|Null|NULL|)$")
_IMPLICIT = (
    ("tag:yaml.org,2002:bool", _BOOL, list("tTfF")),
    ("tag:yaml.org,2002:int", _INT, list("-+0123456789")),
    ("tag:yaml.org,2002:float", _FLOAT, list("-+0123456789.")),
    ("tag:yaml.org,2002:null", _NULL, ["~", "n", "N", ""]),
)


class StrictLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` with YAML 1.2 core-schema scalars and no duplicate keys.

    Only null, booleans, integers, floats, strings, lists and mappings are built: YAML 1.1's
    timestamps, binary, sets, ordered maps and merge keys (``<<``) are refused or stay strings.
    """

    yaml_implicit_resolvers: typing.ClassVar[dict] = {}  # own tables: the SafeLoader's stay untouched
    yaml_constructors: typing.ClassVar[dict] = {}

    def construct_mapping(self, node, deep=False):
        if not isinstance(node, yaml.MappingNode):
            raise yaml.constructor.ConstructorError(None, None, f"expected a mapping, found {node.id}", node.start_mark)
        first_line: dict = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if not isinstance(key, typing.Hashable):
                raise yaml.constructor.ConstructorError(
                    "while reading a mapping", node.start_mark, "found an unhashable key", key_node.start_mark
                )
            line = key_node.start_mark.line + 1
            if key in first_line:
                raise ConfigError(
                    f"{key_node.start_mark.name}: duplicate key {key!r} at line {first_line[key]} and line {line}"
                )
            first_line[key] = line
        return yaml.constructor.BaseConstructor.construct_mapping(self, node, deep=deep)

    def construct_core_bool(self, node):
        value = self.construct_scalar(node)
        if not _BOOL.match(value):
            raise yaml.constructor.ConstructorError(None, None, f"not a boolean: {value!r}", node.start_mark)
        return value.lower() == "true"

    def construct_core_int(self, node):
        value = self.construct_scalar(node)
        if not _INT.match(value):
            raise yaml.constructor.ConstructorError(None, None, f"not an integer: {value!r}", node.start_mark)
        return int(value, 16) if "x" in value else int(value)

    def construct_core_float(self, node):
        value = self.construct_scalar(node)
        if not (_FLOAT.match(value) or _INT.match(value)):
            raise yaml.constructor.ConstructorError(None, None, f"not a number: {value!r}", node.start_mark)
        lowered = value.lower()
        if lowered.endswith(".inf"):
            return -math.inf if lowered.startswith("-") else math.inf
        if lowered == ".nan":
            return math.nan
        return float(int(value, 16)) if "x" in lowered else float(value)

    def construct_undefined(self, node):
        raise yaml.constructor.ConstructorError(
            None, None, f"tag {node.tag!r} is not allowed in a config file", node.start_mark
        )


for _tag, _regexp, _first in _IMPLICIT:
    StrictLoader.add_implicit_resolver(_tag, _regexp, _first)
StrictLoader.add_constructor("tag:yaml.org,2002:null", yaml.SafeLoader.construct_yaml_null)
StrictLoader.add_constructor("tag:yaml.org,2002:bool", StrictLoader.construct_core_bool)
StrictLoader.add_constructor("tag:yaml.org,2002:int", StrictLoader.construct_core_int)
StrictLoader.add_constructor("tag:yaml.org,2002:float", StrictLoader.construct_core_float)
StrictLoader.add_constructor("tag:yaml.org,2002:str", yaml.SafeLoader.construct_yaml_str)
StrictLoader.add_constructor("tag:yaml.org,2002:seq", yaml.SafeLoader.construct_yaml_seq)
StrictLoader.add_constructor("tag:yaml.org,2002:map", yaml.SafeLoader.construct_yaml_map)
StrictLoader.add_constructor(None, StrictLoader.construct_undefined)


class StrictDumper(yaml.SafeDumper):
    """``yaml.SafeDumper`` that also quotes every string ``StrictLoader`` would not read back as a
    string (``1e9``), so what it writes reloads as the same values."""


for _tag, _regexp, _first in _IMPLICIT:
    StrictDumper.add_implicit_resolver(_tag, _regexp, _first)


def parse_yaml(text: str, name: str = "<string>") -> Any:
    """YAML text -> plain data with ``StrictLoader``; any problem is a ConfigError naming ``name``."""
    loader = None
    try:
        loader = StrictLoader(text)  # reads the stream's first characters: may already fail
        loader.name = name  # marks (and so every error) name the file, not "<unicode string>"
        return loader.get_single_data()
    except ConfigError:
        raise
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        raise ConfigError(f"{name}: malformed YAML{where}: {err.problem or err.context}") from err
    except (yaml.YAMLError, ValueError) as err:  # ValueError: e.g. an integer longer than Python converts
        raise ConfigError(f"{name}: malformed YAML: {' '.join(str(err).split())}") from err
    finally:
        if loader is not None:
            loader.dispose()


def dump_yaml(data: Any, **kwargs) -> str:
    """Plain data -> YAML text that ``parse_yaml`` reads back as the same values."""
    return yaml.dump(data, Dumper=StrictDumper, **kwargs)


def load_yaml(path: str | Path) -> Any:
    """A YAML file -> plain data (``parse_yaml``): a missing or unreadable file is a ConfigError too."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such file")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"{path}: cannot read: {err}") from err
    return parse_yaml(text, str(path))


def load_mapping(path: str | Path) -> dict:
    """``load_yaml`` of a file that must hold a mapping (an empty file is an empty one)."""
    data = load_yaml(path)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    return data


# --- Declared units and ranges -----------------------------------------------------------------


@dataclass(frozen=True)
class Bounds:
    """A field's unit and physical range (each bound optional), checked by ``from_dict``: a number,
    or every number of a tuple, must lie inside."""

    unit: str
    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None
    doc: str = ""  # where the range comes from, when that is not obvious

    def allows(self, value: float) -> bool:
        return not (
            (self.gt is not None and not value > self.gt)
            or (self.ge is not None and not value >= self.ge)
            or (self.lt is not None and not value < self.lt)
            or (self.le is not None and not value <= self.le)
        )

    def describe(self) -> str:
        """``0 < x <= 1.7`` style, without the unit."""
        low = f"{_num(self.gt)} < " if self.gt is not None else f"{_num(self.ge)} <= " if self.ge is not None else ""
        high = f" < {_num(self.lt)}" if self.lt is not None else f" <= {_num(self.le)}" if self.le is not None else ""
        return f"{low}x{high}" if low or high else "any"

    def check(self, value: Any, where: str) -> None:
        items = value if isinstance(value, (tuple, list)) else (value,)
        for i, item in enumerate(items):
            if isinstance(item, (int, float)) and not isinstance(item, bool) and not self.allows(item):
                at = f"{where}[{i}]" if isinstance(value, (tuple, list)) else where
                why = f" ({self.doc})" if self.doc else ""
                unit = f" {self.unit}" if self.unit else ""
                raise ConfigError(f"{at}: {item!r}{unit} is out of range; allowed: {self.describe()}{unit}{why}")


def _num(value: float) -> str:
    return f"{value:g}"


def bounded(
    default: Any = dataclasses.MISSING, *, unit: str, doc: str = "", description: str = "", **limits: float
) -> Any:
    """A dataclass field with its unit and physical range (``gt``, ``ge``, ``lt``, ``le``; for a tuple,
    of each item), written once where it is declared: ``bounded(0.25, unit="m/s", gt=0, le=1.7)``.
    ``from_dict`` refuses a value outside, naming the dotted path, value, unit and range.
    ``description``: what the field is, where a node declares it as a ROS parameter (``described``)."""
    unknown = set(limits) - {"gt", "ge", "lt", "le"}
    if unknown:
        raise TypeError(f"bounded(): unknown limit(s) {sorted(unknown)}")
    metadata = {"bounds": Bounds(unit=unit, doc=doc, **limits), "description": description}
    return field(default=default, metadata=metadata)


def described(default: Any, description: str, choices: tuple[str, ...] = ()) -> Any:
    """A dataclass field that says what it is (and, for a string, the values it may take), for a field a
    node declares as a ROS parameter (``equidiff_ros.parameters.config_parameters``: its descriptor,
    ``--help``, docs/parameters.md). The dataclass still checks its values itself."""
    return field(default=default, metadata={"description": description, "choices": choices})


def field_bounds(f: dataclasses.Field) -> Bounds | None:
    return f.metadata.get("bounds")


def field_description(f: dataclasses.Field) -> str:
    return f.metadata.get("description", "")


def field_choices(f: dataclasses.Field) -> tuple[str, ...]:
    return f.metadata.get("choices", ())


UNIT_QUATERNION = "a unit quaternion: norm within 0.001 of 1"


def check_unit_quaternion(q: typing.Sequence[float], name: str, tol: float = 1e-3) -> None:
    """A rotation written as a quaternion must be one: |q| within ``tol`` of 1 (written rounded, not off)."""
    norm = math.sqrt(sum(v * v for v in q))
    if abs(norm - 1.0) > tol:
        raise ValueError(f"{name} must be a unit quaternion (|q| within {tol} of 1), got |q| = {norm:.6g}")


def from_dict(cls: type[T], data: Any, where: str = "") -> T:
    """Build dataclass ``cls`` from nested dicts/lists, checking keys and types on the way."""
    return _convert(cls, data, where or cls.__name__)


def _convert(tp: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in (a for a in args if a is not type(None)):
            try:
                return _convert(arg, value, where)
            except ConfigError as err:
                errors.append(str(err))
        raise ConfigError("; ".join(errors))
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping, got {type(value).__name__}")
        hints = typing.get_type_hints(tp)
        fields = {f.name: f for f in dataclasses.fields(tp) if f.init}
        unknown = sorted(map(str, set(value) - set(fields)))
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(fields)}")
        kwargs = {}
        for name, f in fields.items():
            if name in value:
                kwargs[name] = _convert(hints[name], value[name], f"{where}.{name}")
                if (bounds := field_bounds(f)) is not None and kwargs[name] is not None:
                    bounds.check(kwargs[name], f"{where}.{name}")
            elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"{where}: missing required key '{name}'")
        try:
            return tp(**kwargs)
        except (ValueError, TypeError, ArithmeticError) as err:
            raise ConfigError(f"{where}: {err}") from err
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {type(value).__name__}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f"{where}: expected {len(args)} items, got {len(value)}")
            return tuple(_convert(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
        item = args[0] if args else Any
        out = [_convert(item, v, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(out) if origin is tuple else out
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping, got {type(value).__name__}")
        key_t, val_t = args or (Any, Any)
        return {_convert(key_t, k, where): _convert(val_t, v, f"{where}.{k}") for k, v in value.items()}
    if tp is float:  # an int is a float; a bool is not a number
        try:
            number = float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else math.nan
        except OverflowError:
            number = math.nan
        if not math.isfinite(number):
            raise ConfigError(f"{where}: expected a finite number, got {value!r}")
        return number
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true/false, got {value!r}")
        return value
    if tp is str:  # no number becomes a string: quote serials ("0123456")
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string (quote it), got {type(value).__name__} {value!r}")
        return value
    raise ConfigError(f"{where}: unsupported config type {tp!r}")


def to_dict(obj: Any) -> Any:
    """Inverse of ``from_dict`` (tuples become lists), for saving configs in checkpoints and bags."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    return obj


# --- The lab set-up ----------------------------------------------------------------------

# Positions (TCP, boxes) stay within this of the base on every axis: the FR3 reaches 0.855 m from
# its shoulder, which is 0.333 m above the base.
REACH_M = 1.2


@dataclass(frozen=True)
class Workspace:
    """The cube the voxel grid covers, in the robot base frame."""

    center: tuple[float, float, float] = bounded((0.45, 0.0, 0.18), unit="m", ge=-REACH_M, le=REACH_M)
    edge: float = bounded(0.4, unit="m", gt=0, le=2 * REACH_M)
    resolution: int = bounded(64, unit="voxels per edge", ge=2, le=512)

    def __post_init__(self):
        if self.edge <= 0:
            raise ValueError(f"edge must be positive, got {self.edge}")
        if self.resolution < 2:
            raise ValueError(f"resolution must be >= 2, got {self.resolution}")

    @property
    def voxel_size(self) -> float:
        return self.edge / self.resolution

    @property
    def lower(self) -> np.ndarray:
        """Minimum corner: voxel (0, 0, 0) spans [lower, lower + voxel_size)."""
        return np.asarray(self.center) - self.edge / 2

    @property
    def upper(self) -> np.ndarray:
        return np.asarray(self.center) + self.edge / 2


@dataclass(frozen=True)
class SafetyBox:
    """Where franka_node lets the TCP go, in the robot base frame: separate from the voxel box
    (``Workspace``), which is where the cameras look. Every command is clipped into it.

    ``lower[2]`` is the floor the hand must not touch (the table top); the TCP stays
    ``floor_margin_m`` above it."""

    lower: tuple[float, float, float] = bounded((0.26, -0.19, 0.0), unit="m", ge=-REACH_M, le=REACH_M)  # z: table top
    upper: tuple[float, float, float] = bounded((0.64, 0.19, 0.37), unit="m", ge=-REACH_M, le=REACH_M)
    floor_margin_m: float = bounded(0.01, unit="m", ge=0, le=0.1)

    def __post_init__(self):
        if self.floor_margin_m < 0:
            raise ValueError(f"floor_margin_m must be >= 0, got {self.floor_margin_m}")
        if not np.all(self.min_corner < np.asarray(self.upper)):
            raise ValueError(
                f"safety box is empty: lower {list(self.lower)} (+ floor margin "
                f"{self.floor_margin_m}) must be below upper {list(self.upper)} on every axis"
            )

    @property
    def min_corner(self) -> np.ndarray:
        """The lowest corner the TCP may reach: ``lower`` raised by the floor margin."""
        return np.asarray(self.lower, dtype=np.float64) + [0.0, 0.0, self.floor_margin_m]

    @property
    def max_corner(self) -> np.ndarray:
        return np.asarray(self.upper, dtype=np.float64)


@dataclass(frozen=True)
class Extrinsics:
    """T_base_optical: pose of the camera's optical frame (x right, y down, z forward) in the base frame."""

    translation: tuple[float, float, float] = bounded(unit="m", ge=-5, le=5, doc="a camera in the room")
    quaternion_xyzw: tuple[float, float, float, float] = bounded(unit="", doc=UNIT_QUATERNION)

    def __post_init__(self):
        try:
            geometry.pose_from_pos_quat(self.translation, self.quaternion_xyzw)
        except geometry.GeometryError as err:
            raise ValueError(str(err)) from err

    def matrix(self) -> np.ndarray:
        return geometry.pose_from_pos_quat(self.translation, self.quaternion_xyzw)

    @classmethod
    def from_matrix(cls, T: np.ndarray) -> Extrinsics:
        p, q = geometry.pos_quat_from_pose(T)
        return cls(tuple(float(v) for v in p), tuple(float(v) for v in q))


@dataclass(frozen=True)
class CameraConfig:
    name: str
    serial: str  # quoted in YAML: a string, never a number
    extrinsics: Extrinsics
    width: int = bounded(848, unit="px", gt=0, le=4096)
    height: int = bounded(480, unit="px", gt=0, le=4096)
    fps: int = bounded(30, unit="Hz", gt=0, le=300)
    publish_hz: float = bounded(5.0, unit="Hz", gt=0, le=300, doc="and <= fps")
    # points nearer or farther are dropped by the camera node
    min_depth: float = bounded(0.1, unit="m", ge=0, le=20, doc="and < max_depth")
    max_depth: float = bounded(2.0, unit="m", gt=0, le=20)
    # Backend-specific options (realsense filters, exposure, ...): see each backend's config.
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        if not self.min_depth < self.max_depth:
            raise ValueError(f"min_depth ({self.min_depth} m) must be below max_depth ({self.max_depth} m)")
        if self.publish_hz > self.fps:
            raise ValueError(f"publish_hz ({self.publish_hz} Hz) cannot exceed the camera's fps ({self.fps})")

    @property
    def topic(self) -> str:
        return f"/cameras/{self.name}/points"

    @property
    def frame_id(self) -> str:
        return f"{self.name}_color_optical_frame"


@dataclass(frozen=True)
class RobotConfig:
    ip: str = "172.16.0.2"
    state_hz: float = bounded(100.0, unit="Hz", gt=0, le=1000, doc="the FR3's control rate")


@dataclass(frozen=True)
class LabConfig:
    cameras: tuple[CameraConfig, ...]
    workspace: Workspace = field(default_factory=Workspace)
    safety_box: SafetyBox = field(default_factory=SafetyBox)  # where franka_node lets the TCP go
    robot: RobotConfig = field(default_factory=RobotConfig)
    base_frame: str = "fr3_link0"
    observation_hz: float = bounded(5.0, unit="Hz", gt=0, le=100)

    def __post_init__(self):
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"camera names must be unique, got {names}")
        if not self.cameras:
            raise ValueError("at least one camera is required")

    def camera(self, name: str) -> CameraConfig:
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise ConfigError(f"no camera named {name!r}; configured: {[c.name for c in self.cameras]}")


def load_lab_config(path: str | Path) -> LabConfig:
    return from_dict(LabConfig, load_mapping(path), where=Path(path).name)


def default_config_dir() -> Path:
    """config/ of a source checkout, or share/equidiff_ros/config of an installed package."""
    here = Path(__file__).resolve()
    for candidate in (here.parents[2] / "config", here.parents[4] / "share" / "equidiff_ros" / "config"):
        if candidate.is_dir():
            return candidate
    import sys

    return Path(sys.prefix) / "share" / "equidiff_ros" / "config"
