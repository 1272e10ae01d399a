"""Typed configuration: the lab set-up YAML (config/lab.yaml) and a small dict -> dataclass builder.

Every config object in the project is a frozen dataclass built with ``from_dict``: unknown
keys, missing required keys and wrong types fail with the dotted path of the culprit
("lab.yaml: cameras[1].extrinsics.translation: expected 3 numbers, got 2"), never later as
a silent wrong value. We do not use pydantic: the builder is ~60 lines, has no runtime
dependency and is shared by all configs (lab, model presets, control limits).
"""

from __future__ import annotations

import dataclasses
import math
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
        unknown = sorted(set(value) - set(fields))
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(fields)}")
        kwargs = {}
        for name, f in fields.items():
            if name in value:
                kwargs[name] = _convert(hints[name], value[name], f"{where}.{name}")
            elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"{where}: missing required key '{name}'")
        try:
            return tp(**kwargs)
        except (ValueError, TypeError) as err:
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
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(f"{where}: expected a finite number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true/false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, (str, int)) or isinstance(value, bool):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return str(value)
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


def load_yaml(path: str | Path) -> Any:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such file")
    try:
        return yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: malformed YAML: {err}") from err


# --- The lab set-up ----------------------------------------------------------------------


@dataclass(frozen=True)
class Workspace:
    """The cube the voxel grid covers, in the robot base frame."""

    center: tuple[float, float, float] = (0.45, 0.0, 0.18)
    edge: float = 0.4  # m
    resolution: int = 64  # voxels per edge

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

    lower: tuple[float, float, float] = (0.26, -0.19, 0.0)  # m; z: the table top
    upper: tuple[float, float, float] = (0.64, 0.19, 0.37)
    floor_margin_m: float = 0.01

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

    translation: tuple[float, float, float]
    quaternion_xyzw: tuple[float, float, float, float]

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
    serial: str
    extrinsics: Extrinsics
    width: int = 848
    height: int = 480
    fps: int = 30
    publish_hz: float = 5.0
    min_depth: float = 0.1  # m; points nearer or farther are dropped by the camera node
    max_depth: float = 2.0
    # Backend-specific options (realsense filters, exposure, ...): see each backend's config.
    options: dict[str, Any] = field(default_factory=dict)

    @property
    def topic(self) -> str:
        return f"/cameras/{self.name}/points"

    @property
    def frame_id(self) -> str:
        return f"{self.name}_color_optical_frame"


@dataclass(frozen=True)
class RobotConfig:
    ip: str = "172.16.0.2"
    state_hz: float = 100.0


@dataclass(frozen=True)
class LabConfig:
    cameras: tuple[CameraConfig, ...]
    workspace: Workspace = field(default_factory=Workspace)
    safety_box: SafetyBox = field(default_factory=SafetyBox)  # where franka_node lets the TCP go
    robot: RobotConfig = field(default_factory=RobotConfig)
    base_frame: str = "fr3_link0"
    observation_hz: float = 5.0

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
    data = load_yaml(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    return from_dict(LabConfig, data, where=Path(path).name)


def default_config_dir() -> Path:
    """config/ of a source checkout, or share/equidiff_ros/config of an installed package."""
    here = Path(__file__).resolve()
    for candidate in (here.parents[2] / "config", here.parents[4] / "share" / "equidiff_ros" / "config"):
        if candidate.is_dir():
            return candidate
    import sys

    return Path(sys.prefix) / "share" / "equidiff_ros" / "config"
