"""One way to build and read ROS 2 messages, live (rclpy) or in bags (rosbags), without ROS in core.

This module is the message codec: the factories, time stamps, and the robot-state messages
(``/franka/ee_pose`` and ``/franka/executed_target`` PoseStamped, ``/franka/joint_states``
JointState: 7 arm joints + two finger joints each at width/2, ``/tf_static`` TFMessage, the
``/diagnostics`` entries). Nodes, commands and loggers read and write those only through it.
The wire formats with a module of their own are the point clouds (``pointcloud``), the pose
chunks (``chunk``) and the camera images (``cameras.color``).

rclpy's generated classes and rosbags' typestore classes share field names, so every
encoder in core is written once against a ``MsgFactory`` and works for both:

* ``RclpyFactory`` (used by the nodes) imports ``sensor_msgs.msg`` etc. lazily;
* ``RosbagsFactory`` (used by the recorder, dataset, viz and tests) uses the Jazzy typestore.

Readers only use attribute access, so they take either kind of message directly. The
factories differ in what array fields want (rclpy: ``array.array``/bytes, rosbags: numpy),
which ``uint8_array`` / ``float64_array`` hide.
"""

from __future__ import annotations

import array
import functools
import importlib
import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from . import geometry
from .robots.base import ARM_JOINT_NAMES, FINGER_JOINT_NAMES, RobotState

NS_PER_S = 1_000_000_000


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time (either flavour) -> integer nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def header_stamp_ns_from_cdr(data: bytes) -> int:
    """The ``header.stamp`` of a serialised (CDR) message that starts with a std_msgs/Header
    (PointCloud2, MultiDOFJointTrajectory, ...), without deserialising the rest: a listener
    that needs only the stamp of a 1 MiB voxel grid reads 8 bytes."""
    little = len(data) > 1 and data[1] & 1  # encapsulation id: 0x0001 = CDR little endian
    sec, nanosec = struct.unpack_from("<iI" if little else ">iI", data, 4)
    return sec * NS_PER_S + nanosec


def split_ns(ns: int) -> tuple[int, int]:
    sec, nanosec = divmod(int(ns), NS_PER_S)
    return sec, nanosec


def uint8_buffer(data: Any) -> np.ndarray:
    """A message's uint8[] field (bytes, array.array or numpy) as a read-only numpy view, no copy."""
    if isinstance(data, np.ndarray):
        return data.view(np.uint8).reshape(-1)
    return np.frombuffer(memoryview(data).cast("B"), dtype=np.uint8)


class MsgFactory:
    """Builds messages by ROS type name ('sensor_msgs/msg/PointCloud2')."""

    def cls(self, type_name: str) -> type:
        raise NotImplementedError

    def make(self, type_name: str, **fields: Any) -> Any:
        return self.cls(type_name)(**fields)

    def uint8_array(self, data: bytes | np.ndarray) -> Any:
        raise NotImplementedError

    def float64_array(self, values: Any) -> Any:
        raise NotImplementedError

    def time(self, ns: int) -> Any:
        sec, nanosec = split_ns(ns)
        return self.make("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)

    def duration(self, ns: int) -> Any:
        sec, nanosec = split_ns(ns)
        return self.make("builtin_interfaces/msg/Duration", sec=sec, nanosec=nanosec)

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        return self.make("std_msgs/msg/Header", stamp=self.time(stamp_ns), frame_id=frame_id)


class RclpyFactory(MsgFactory):
    def __init__(self):
        self._cache: dict[str, type] = {}

    def cls(self, type_name: str) -> type:
        if type_name not in self._cache:
            pkg, kind, name = type_name.split("/")
            self._cache[type_name] = getattr(importlib.import_module(f"{pkg}.{kind}"), name)
        return self._cache[type_name]

    def uint8_array(self, data: bytes | np.ndarray) -> Any:
        buf = data.tobytes() if isinstance(data, np.ndarray) else bytes(data)
        return array.array("B", buf)

    def float64_array(self, values: Any) -> Any:
        return array.array("d", np.asarray(values, dtype=np.float64).tobytes())


class RosbagsFactory(MsgFactory):
    def __init__(self, typestore: Any = None):
        if typestore is None:
            typestore = jazzy_typestore()
        self.typestore = typestore

    def cls(self, type_name: str) -> type:
        try:
            return self.typestore.types[type_name]
        except KeyError:
            raise KeyError(f"message type {type_name} is not in the rosbags typestore") from None

    def uint8_array(self, data: bytes | np.ndarray) -> Any:
        if isinstance(data, np.ndarray):
            return data.view(np.uint8).reshape(-1)
        return np.frombuffer(bytes(data), dtype=np.uint8)

    def float64_array(self, values: Any) -> Any:
        return np.asarray(values, dtype=np.float64)


def jazzy_typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


@functools.cache
def rosbags_factory() -> RosbagsFactory:
    """A shared RosbagsFactory (building the typestore takes ~0.1 s)."""
    return RosbagsFactory()


# --- robot state, transforms and diagnostics ---------------------------------------------------

TCP_FRAME = "fr3_hand_tcp"  # franka_ros2's name for the TCP frame (also the chunk's joint name)

# diagnostic_msgs/DiagnosticStatus levels
OK, WARN, ERROR, STALE = 0, 1, 2, 3


def _point(factory: MsgFactory, type_name: str, p: np.ndarray) -> Any:
    return factory.make(type_name, x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _quaternion(factory: MsgFactory, q: np.ndarray) -> Any:
    return factory.make("geometry_msgs/msg/Quaternion", x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))


def transform_msg(factory: MsgFactory, pose: np.ndarray) -> Any:
    """(4, 4) pose -> ``geometry_msgs/Transform``."""
    p, q = geometry.pos_quat_from_pose(pose)
    return transform_msg_from_pos_quat(factory, p, q)


def transform_msg_from_pos_quat(factory: MsgFactory, position: Any, quat_xyzw: Any) -> Any:
    """Position (3,) and scalar-last quaternion (4,) -> ``geometry_msgs/Transform``, values as given."""
    return factory.make(
        "geometry_msgs/msg/Transform",
        translation=_point(factory, "geometry_msgs/msg/Vector3", position),
        rotation=_quaternion(factory, quat_xyzw),
    )


def pose_stamped(factory: MsgFactory, pose: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    p, q = geometry.pos_quat_from_pose(pose)
    mk = factory.make
    return mk(
        "geometry_msgs/msg/PoseStamped",
        header=factory.header(stamp_ns, frame_id),
        pose=mk(
            "geometry_msgs/msg/Pose",
            position=_point(factory, "geometry_msgs/msg/Point", p),
            orientation=_quaternion(factory, q),
        ),
    )


def position_from_msg(msg: Any) -> np.ndarray:
    """PoseStamped or Pose (either flavour) -> position (3,), unchecked."""
    p = getattr(msg, "pose", msg).position
    return np.array([p.x, p.y, p.z], dtype=np.float64)


def _pos_quat(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    pose = getattr(msg, "pose", msg)
    o = pose.orientation
    return position_from_msg(pose), np.array([o.x, o.y, o.z, o.w], dtype=np.float64)


def pose_from_msg(msg: Any) -> np.ndarray:
    """PoseStamped or Pose (either flavour) -> (4, 4); raises GeometryError on NaN / non-unit quaternions."""
    return geometry.pose_from_pos_quat(*_pos_quat(msg))


def pos_quat_from_msg(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """PoseStamped or Pose -> (position (3,), quaternion xyzw (4,)) as sent; raises GeometryError
    on a NaN / inf position or a NaN / non-unit quaternion."""
    pos, quat = _pos_quat(msg)
    if not np.all(np.isfinite(pos)):
        raise geometry.GeometryError("pose position contains NaN or inf")
    geometry.pose_from_pos_quat(pos, quat)  # validates the quaternion
    return pos, quat


def pose_from_transform(msg: Any) -> np.ndarray:
    """Transform or TransformStamped (either flavour) -> (4, 4); raises GeometryError on NaN / non-unit quaternions."""
    transform = getattr(msg, "transform", msg)
    t, r = transform.translation, transform.rotation
    return geometry.pose_from_pos_quat([t.x, t.y, t.z], [r.x, r.y, r.z, r.w])


def tf_message(factory: MsgFactory, transforms: list[tuple[str, str, np.ndarray]], stamp_ns: int) -> Any:
    """``tf2_msgs/TFMessage`` of (parent frame, child frame, 4x4 pose of the child in the parent)."""
    mk = factory.make
    out = [
        mk(
            "geometry_msgs/msg/TransformStamped",
            header=factory.header(stamp_ns, parent),
            child_frame_id=child,
            transform=transform_msg(factory, pose),
        )
        for parent, child, pose in transforms
    ]
    return mk("tf2_msgs/msg/TFMessage", transforms=out)


def joint_state(factory: MsgFactory, state: RobotState, stamp_ns: int) -> Any:
    width = float(state.gripper_width) if np.isfinite(state.gripper_width) else 0.0
    positions = [*map(float, state.joint_positions), width / 2, width / 2]
    velocities = [*map(float, state.joint_velocities), 0.0, 0.0]
    return factory.make(
        "sensor_msgs/msg/JointState",
        header=factory.header(stamp_ns, ""),
        name=[*ARM_JOINT_NAMES, *FINGER_JOINT_NAMES],
        position=factory.float64_array(positions),
        velocity=factory.float64_array(velocities),
        effort=factory.float64_array([]),
    )


def _named_positions(msg: Any, names: tuple[str, ...]) -> list[float] | None:
    order = list(msg.name)
    try:
        return [float(msg.position[order.index(n)]) for n in names]
    except (ValueError, IndexError):
        return None


def has_gripper_joints(msg: Any) -> bool:
    """Whether a JointState names both finger joints (an arm-only publisher does not)."""
    names = list(msg.name)
    return all(j in names for j in FINGER_JOINT_NAMES)


def gripper_width_from_joint_state(msg: Any) -> float | None:
    """Gripper width = sum of the two finger joints; None if the message carries no gripper state
    (no finger joints, e.g. an arm-only publisher, or fewer positions than names: malformed).
    The value may be NaN/inf if the publisher sent that: callers check ``isfinite``."""
    fingers = _named_positions(msg, FINGER_JOINT_NAMES)
    return None if fingers is None else float(sum(fingers))


def arm_joint_positions(msg: Any) -> np.ndarray | None:
    """The 7 arm joints' positions (rad, joint 1 first) of a JointState, by name; None if any is missing."""
    positions = _named_positions(msg, ARM_JOINT_NAMES)
    return None if positions is None else np.array(positions, dtype=np.float64)


def diagnostic_array(
    factory: MsgFactory, stamp_ns: int, name: str, hardware_id: str, level: int, message: str, values: Mapping[str, Any]
) -> Any:
    mk = factory.make
    # DiagnosticStatus.level is a ROS `byte`: rclpy wants bytes (an int serialises as garbage),
    # rosbags an int.
    level = bytes([int(level)]) if isinstance(factory, RclpyFactory) else int(level)
    status = mk(
        "diagnostic_msgs/msg/DiagnosticStatus",
        level=level,
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=[mk("diagnostic_msgs/msg/KeyValue", key=str(k), value=_fmt(v)) for k, v in values.items()],
    )
    return mk("diagnostic_msgs/msg/DiagnosticArray", header=factory.header(stamp_ns, ""), status=[status])


@dataclass(frozen=True)
class DiagnosticEntry:
    """One ``diagnostic_msgs/DiagnosticStatus`` as read back: the level as an int (OK .. STALE)."""

    name: str
    level: int
    message: str
    hardware_id: str
    values: dict[str, str]

    def quote(self, keys: tuple[str, ...]) -> str:
        """The message and the values under ``keys``, for an error message: "'holding' (state holding, …)"."""
        counts = ", ".join(f"{k} {self.values.get(k, '?')}" for k in keys)
        return f"'{self.message}' ({counts})"

    def number(self, key: str) -> float | None:
        """The value under ``key`` as a finite float; None when absent, text ("ok") or NaN (no figure yet)."""
        try:
            value = float(self.values[key])
        except (KeyError, TypeError, ValueError):
            return None
        return value if math.isfinite(value) else None


def diagnostic_entries(msg: Any) -> list[DiagnosticEntry]:
    """DiagnosticArray (either flavour) -> its entries, values as the strings they were sent as."""
    return [
        DiagnosticEntry(
            str(status.name),
            status.level[0] if isinstance(status.level, bytes) else int(status.level),
            str(status.message),
            str(status.hardware_id),
            {str(kv.key): kv.value for kv in status.values},
        )
        for status in msg.status
    ]


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.3f}"
    return str(v)
