"""One way to build and read ROS 2 messages, live (rclpy) or in bags (rosbags), without ROS in core.

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
import importlib
import struct
from typing import Any

import numpy as np

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
    return sec * 1_000_000_000 + nanosec


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


_DEFAULT_ROSBAGS: RosbagsFactory | None = None


def rosbags_factory() -> RosbagsFactory:
    """A shared RosbagsFactory (building the typestore takes ~0.1 s)."""
    global _DEFAULT_ROSBAGS
    if _DEFAULT_ROSBAGS is None:
        _DEFAULT_ROSBAGS = RosbagsFactory()
    return _DEFAULT_ROSBAGS
