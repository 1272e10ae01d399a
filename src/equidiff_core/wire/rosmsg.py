"""One way to build and read ROS 2 messages, live (rclpy) or in bags (rosbags), without ROS in core.

This module is the message codec: the factories, time stamps, and the robot-state messages
(``/franka/ee_pose`` and ``/franka/executed_target`` PoseStamped, ``/franka/joint_states``
JointState: 7 arm joints + two finger joints each at width/2, ``/tf_static`` TFMessage, the
``/diagnostics`` entries). Nodes, commands and loggers read and write those only through it.
The wire formats with a module of their own are the point clouds (``wire.pointcloud``), the pose
chunks (``chunk``) and the camera images (``cameras.color``).

rclpy's generated classes and rosbags' typestore classes share field names, so every
encoder in core is written once against a ``MsgFactory`` and works for both:

* ``RclpyFactory`` (used by the nodes) imports ``sensor_msgs.msg`` etc. lazily;
* ``RosbagsFactory`` (used by the recorder, dataset, viz and tests) uses the Jazzy typestore.

Readers only use attribute access, so they take either kind of message directly. The
factories differ in what array fields want (rclpy: ``array.array``/bytes, rosbags: numpy),
which ``uint8_array`` / ``float64_array`` hide.

Decoders check what they receive against what the receiver expects (the frame where the caller
knows it; finite values; unit quaternions within ``geometry``'s tolerance, refused rather than
normalised beyond it; joint states whose names and positions agree; a gripper width the hand
can have; well-formed diagnostics) and raise ``MessageError`` with a ``MessageReason`` on
anything else, never another exception and never a repaired value.
"""

from __future__ import annotations

import array
import enum
import functools
import importlib
import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from .. import geometry
from ..policy.doubt import SIGNALS, ChunkDoubt
from ..robots.base import ARM_JOINT_NAMES, FINGER_JOINT_NAMES, RobotState

NS_PER_S = 1_000_000_000


class MessageReason(enum.StrEnum):
    """Why a robot-state, transform or diagnostics message was refused: nodes count each on
    /diagnostics (``dropped_<topic>_<reason>``)."""

    MALFORMED = "malformed"  # arrays that disagree, repeated names, truncated bytes, a field out of its range
    NAN = "nan"  # NaN / inf values
    QUATERNION = "quaternion"  # not unit length within geometry's tolerance
    FRAME = "frame"  # header.frame_id (or child_frame_id) is not the one the receiver expects
    RANGE = "range"  # a value the hardware cannot have: a gripper width outside its stroke
    FUTURE = "future"  # stamped further ahead of the receiver's clock than allowed


class MessageError(ValueError):
    """A message that cannot be used (and must be dropped, not guessed at); ``reason`` a ``MessageReason``."""

    def __init__(self, message: str, reason: MessageReason = MessageReason.MALFORMED):
        super().__init__(message)
        self.reason = MessageReason(reason)


def check_not_future(stamp_ns: int, now_ns: int, max_future_ns: int, what: str) -> None:
    """MessageError (FUTURE) when ``stamp_ns`` is more than ``max_future_ns`` ahead of ``now_ns``:
    a clock is wrong, and a state from the future would pass every age check."""
    ahead = int(stamp_ns) - int(now_ns)
    if ahead > max_future_ns:
        raise MessageError(
            f"{what} stamped {ahead / 1e6:.0f} ms ahead of this node's clock (limit {max_future_ns / 1e6:.0f} ms)",
            MessageReason.FUTURE,
        )


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time (either flavour) -> integer nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def header_stamp_ns_from_cdr(data: bytes) -> int:
    """The ``header.stamp`` of a serialised (CDR) message that starts with a std_msgs/Header
    (PointCloud2, MultiDOFJointTrajectory, ...), without deserialising the rest: a listener
    that needs only the stamp of a 1 MiB voxel grid reads 8 bytes. MessageError when the bytes
    end before the stamp or its nanoseconds are not below one second (not a Header)."""
    data = bytes(data[:12])
    if len(data) < 12:
        raise MessageError(f"a serialised message of {len(data)} bytes ends before its header stamp (bytes 4..12)")
    little = data[1] & 1  # encapsulation id: 0x0001 = CDR little endian
    sec, nanosec = struct.unpack_from("<iI" if little else ">iI", data, 4)
    if nanosec >= NS_PER_S:
        raise MessageError(f"header stamp nanosec {nanosec} is not below one second: not a std_msgs/Header")
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


def _check_frame(msg: Any, frame_id: str | None, what: str) -> None:
    """MessageError (FRAME) unless ``frame_id`` is None or ``msg``'s header frame; a bare (unstamped)
    message cannot show a frame the caller asked for."""
    if frame_id is None:
        return
    header = getattr(msg, "header", None)
    if header is None:
        raise MessageError(f"a bare {what} has no header: it cannot show the expected frame {frame_id!r}")
    if str(header.frame_id) != frame_id:
        raise MessageError(f"{what} frame_id {str(header.frame_id)!r} is not {frame_id!r}", MessageReason.FRAME)


def _finite(values: np.ndarray, what: str) -> np.ndarray:
    if not np.all(np.isfinite(values)):
        raise MessageError(f"{what} contains NaN or inf: {values.tolist()}", MessageReason.NAN)
    return values


def _checked_pose(position: np.ndarray, quat_xyzw: np.ndarray, what: str) -> np.ndarray:
    """(4, 4) from a finite position and a unit quaternion (geometry's tolerance); MessageError otherwise."""
    _finite(position, f"{what} position")
    _finite(quat_xyzw, f"{what} quaternion")
    try:
        return geometry.pose_from_pos_quat(position, quat_xyzw)
    except geometry.GeometryError as err:  # finite, so only its length can be wrong
        raise MessageError(f"{what}: {err}", MessageReason.QUATERNION) from err


def position_from_msg(msg: Any, frame_id: str | None = None) -> np.ndarray:
    """PoseStamped or Pose (either flavour) -> position (3,); MessageError on NaN / inf or, with
    ``frame_id``, another frame. The orientation is not read (nor checked)."""
    _check_frame(msg, frame_id, "pose")
    p = getattr(msg, "pose", msg).position
    return _finite(np.array([p.x, p.y, p.z], dtype=np.float64), "pose position")


def _pos_quat_pose(msg: Any, frame_id: str | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    _check_frame(msg, frame_id, "pose")
    pose = getattr(msg, "pose", msg)
    p, o = pose.position, pose.orientation
    pos = np.array([p.x, p.y, p.z], dtype=np.float64)
    quat = np.array([o.x, o.y, o.z, o.w], dtype=np.float64)
    return pos, quat, _checked_pose(pos, quat, "pose")


def pos_quat_from_msg(msg: Any, frame_id: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """PoseStamped or Pose -> (position (3,), quaternion xyzw (4,)) exactly as sent; MessageError on
    NaN / inf, a quaternion off unit length, or, with ``frame_id``, another frame."""
    pos, quat, _ = _pos_quat_pose(msg, frame_id)
    return pos, quat


def pose_from_msg(msg: Any, frame_id: str | None = None) -> np.ndarray:
    """PoseStamped or Pose (either flavour) -> (4, 4); MessageError as ``pos_quat_from_msg``."""
    return _pos_quat_pose(msg, frame_id)[2]


def pose_from_transform(msg: Any, frame_id: str | None = None, child_frame_id: str | None = None) -> np.ndarray:
    """Transform or TransformStamped (either flavour) -> (4, 4); MessageError on NaN / inf, a quaternion
    off unit length, or, where given, another parent ``frame_id`` or ``child_frame_id``."""
    _check_frame(msg, frame_id, "transform")
    if child_frame_id is not None and str(getattr(msg, "child_frame_id", "")) != child_frame_id:
        raise MessageError(
            f"transform child_frame_id {str(getattr(msg, 'child_frame_id', None))!r} is not {child_frame_id!r}",
            MessageReason.FRAME,
        )
    transform = getattr(msg, "transform", msg)
    t, r = transform.translation, transform.rotation
    return _checked_pose(
        np.array([t.x, t.y, t.z], dtype=np.float64), np.array([r.x, r.y, r.z, r.w], dtype=np.float64), "transform"
    )


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
    """The arm's joints and, when the gripper width is known, the two finger joints at width/2 each:
    an unknown width (not read yet) is left out, not sent as a width the gripper may not have."""
    positions = list(map(float, state.joint_positions))
    velocities = list(map(float, state.joint_velocities))
    names = list(ARM_JOINT_NAMES)
    if np.isfinite(state.gripper_width):
        width = float(state.gripper_width)
        positions += [width / 2, width / 2]
        velocities += [0.0, 0.0]
        names += FINGER_JOINT_NAMES
    return factory.make(
        "sensor_msgs/msg/JointState",
        header=factory.header(stamp_ns, ""),
        name=names,
        position=factory.float64_array(positions),
        velocity=factory.float64_array(velocities),
        effort=factory.float64_array([]),
    )


# A measured width may read a little beyond the stroke (encoder noise, a simulated finger pressed
# into an object); more than this is not a width the hand can have.
GRIPPER_WIDTH_SLACK_M = 0.002


def _hand_max_width_m() -> float:
    from ..control.config import HAND_MAX_WIDTH_M  # imported late: control imports this module

    return HAND_MAX_WIDTH_M


def joint_positions(msg: Any) -> dict[str, float]:
    """A JointState's positions by joint name; MessageError unless it is well formed: names and
    positions of equal length (velocities and efforts each empty or as long), no name twice,
    every position finite."""
    names = [str(n) for n in msg.name]
    positions = np.asarray(msg.position, dtype=np.float64).reshape(-1)
    if len(positions) != len(names):
        raise MessageError(f"joint state has {len(names)} names but {len(positions)} positions")
    for field in ("velocity", "effort"):
        n = len(getattr(msg, field))
        if n not in (0, len(names)):
            raise MessageError(f"joint state has {len(names)} names but {n} {field} values (0 or one each)")
    if len(set(names)) != len(names):
        repeated = sorted({n for n in names if names.count(n) > 1})
        raise MessageError(f"joint state names {repeated} more than once")
    _finite(positions, "joint state positions")
    return dict(zip(names, positions.tolist(), strict=True))


def has_gripper_joints(msg: Any) -> bool:
    """Whether a well-formed JointState names both finger joints (an arm-only publisher does not);
    MessageError as ``joint_positions``."""
    positions = joint_positions(msg)
    return all(j in positions for j in FINGER_JOINT_NAMES)


def gripper_width_from_joint_state(msg: Any) -> float | None:
    """Gripper width = sum of the two finger joints; None if the message names no finger joints
    (an arm-only publisher). MessageError as ``joint_positions``, or (RANGE) a width outside
    [0, the hand's stroke] by more than ``GRIPPER_WIDTH_SLACK_M``."""
    positions = joint_positions(msg)
    if not all(j in positions for j in FINGER_JOINT_NAMES):
        return None
    width = float(sum(positions[j] for j in FINGER_JOINT_NAMES))
    stroke = _hand_max_width_m()
    if not -GRIPPER_WIDTH_SLACK_M <= width <= stroke + GRIPPER_WIDTH_SLACK_M:
        raise MessageError(
            f"gripper width {width:.4f} m is outside the hand's 0..{stroke} m (slack {GRIPPER_WIDTH_SLACK_M} m)",
            MessageReason.RANGE,
        )
    return width


def arm_joint_positions(msg: Any) -> np.ndarray | None:
    """The 7 arm joints' positions (rad, joint 1 first) of a JointState, by name; None if any is
    missing (a gripper-only publisher); MessageError as ``joint_positions``."""
    positions = joint_positions(msg)
    if not all(j in positions for j in ARM_JOINT_NAMES):
        return None
    return np.array([positions[j] for j in ARM_JOINT_NAMES], dtype=np.float64)


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


def _level(status: Any) -> int:
    level = status.level
    if isinstance(level, bytes | bytearray):
        if len(level) != 1:
            raise MessageError(f"diagnostic status {str(status.name)!r} has a level of {len(level)} bytes")
        level = level[0]
    level = int(level)
    if level not in (OK, WARN, ERROR, STALE):
        raise MessageError(f"diagnostic status {str(status.name)!r} has level {level}, not OK..STALE (0..3)")
    return level


def diagnostic_entries(msg: Any) -> list[DiagnosticEntry]:
    """DiagnosticArray (either flavour) -> its entries, values as the strings they were sent as;
    MessageError on a level other than OK..STALE, a key that is empty or repeated within a status,
    or a key or value that is not a string."""
    entries = []
    for status in msg.status:
        values: dict[str, str] = {}
        for kv in status.values:
            if not isinstance(kv.key, str) or not isinstance(kv.value, str):
                raise MessageError(
                    f"diagnostic status {str(status.name)!r} has a non-string key or value: {kv.key!r}: {kv.value!r}"
                )
            if not kv.key or kv.key in values:
                raise MessageError(
                    f"diagnostic status {str(status.name)!r} has an {'empty' if not kv.key else 'repeated'} "
                    f"key {kv.key!r}"
                )
            values[kv.key] = kv.value
        entries.append(
            DiagnosticEntry(str(status.name), _level(status), str(status.message), str(status.hardware_id), values)
        )
    return entries


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.3f}"
    return str(v)


# --- the policy's doubt ---------------------------------------------------------------------


def doubt_msg(factory: MsgFactory, doubt: ChunkDoubt) -> Any:
    """A chunk's ``ChunkDoubt`` as geometry_msgs/Vector3Stamped: stamped with the chunk's stamp, frame_id the
    signal's name, x its value, y the disagreement and z the spread (m; NaN where not computed)."""
    return factory.make(
        "geometry_msgs/msg/Vector3Stamped",
        header=factory.header(doubt.stamp_ns, doubt.signal),
        vector=factory.make(
            "geometry_msgs/msg/Vector3", x=float(doubt.value), y=float(doubt.disagreement_m), z=float(doubt.spread_m)
        ),
    )


def doubt_from_msg(msg: Any) -> ChunkDoubt:
    """``doubt_msg``'s message -> ChunkDoubt; MessageError on a signal name it does not know, a negative or
    infinite value, or an x that is not the named signal's value."""
    signal = str(msg.header.frame_id)
    if signal not in SIGNALS:
        raise MessageError(f"doubt signal {signal!r} is not one of {SIGNALS}", MessageReason.FRAME)
    v = msg.vector
    values = np.array([v.x, v.y, v.z], dtype=np.float64)
    if np.isinf(values).any():
        raise MessageError(f"doubt values contain inf: {values.tolist()}", MessageReason.NAN)
    if (values < 0).any():
        raise MessageError(f"doubt values must be >= 0 m, got {values.tolist()}", MessageReason.RANGE)
    doubt = ChunkDoubt(stamp_to_ns(msg.header.stamp), float(values[1]), float(values[2]), signal)
    if not np.array_equal(values[0], doubt.value, equal_nan=True):
        raise MessageError(f"doubt value {values[0]} is not the {signal} ({doubt.value})", MessageReason.MALFORMED)
    return doubt
