"""Replay backend: a camera's clouds from a recorded rosbag2 directory (``/cameras/<name>/points``).

Frames come out at the recorded pace (scaled by ``rate``) and are restamped with the current
clock by default (the downstream staleness checks then see live data); ``restamp=False``
keeps the recorded capture stamps. Reading uses rosbags (pure Python, no ROS needed).

The schedule is anchored to the wall clock, not to when the camera connected: a looping
replay plays bag time ``(now mod loop length)``, a single pass starts at the next multiple of
the camera's period. Cameras replayed by separate processes (one camera_node per camera)
therefore deliver the same recorded instant at the same moment.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from ...config import CameraConfig
from ...wire.pointcloud import CloudError, msg_to_cloud
from ..base import Camera, CameraError, CloudFrame
from .config import ReplayOptions

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"


class ReplayFinished(CameraError):
    """The bag has no more frames and ``loop`` is off."""


class ReplayCamera(Camera):
    """Camera ``camera.name`` played back from ``bag`` (topic default: ``camera.topic``)."""

    def __init__(self, camera: CameraConfig, clock: Callable[[], int] = time.time_ns, **options):
        """``options``: ``ReplayOptions``' fields; ``clock``: the restamping clock (ns)."""
        unknown = set(options) - set(ReplayOptions.__dataclass_fields__)
        if unknown:
            raise CameraError(
                f"replay camera {camera.name!r}: unknown option(s) {sorted(unknown)}; "
                f"allowed: {sorted(ReplayOptions.__dataclass_fields__)}"
            )
        self.options = o = ReplayOptions(**options)
        if o.bag is None or str(o.bag) == "":
            raise CameraError(f"replay camera {camera.name!r}: no bag given (set the 'bag' parameter)")
        if o.rate <= 0:
            raise CameraError(f"replay camera {camera.name!r}: rate must be positive, got {o.rate}")
        self.camera = camera
        self.bag = Path(o.bag)
        self.topic = o.topic or camera.topic
        self.loop = o.loop
        self.rate = float(o.rate)
        self.restamp = o.restamp
        self._clock = clock
        self._reader = None
        self._messages = None
        self._pending = None
        self.frames_read = 0

    @property
    def is_connected(self) -> bool:
        return self._reader is not None

    def connect(self) -> None:
        if self._reader is not None:
            return
        from rosbags.rosbag2 import Reader

        from ...data.bags import verify_bag
        from ...wire.rosmsg import rosbags_factory

        if not (self.bag / "metadata.yaml").is_file():
            raise CameraError(
                f"replay camera {self.camera.name!r}: {self.bag} is not a rosbag2 directory (no metadata.yaml)"
            )
        try:
            verify_bag(self.bag)  # every CRC checked first (rosbags' reader checks none)
            reader = Reader(self.bag)
            reader.open()
        except Exception as err:  # rosbags raises several types for damaged bags; ours is a BagError
            raise CameraError(f"replay camera {self.camera.name!r}: cannot open {self.bag}: {err}") from err
        self._connections = [c for c in reader.connections if c.topic == self.topic]
        if not self._connections or reader.message_count == 0:
            clouds = sorted({c.topic for c in reader.connections if c.msgtype == POINTCLOUD2})
            reader.close()
            raise CameraError(
                f"replay camera {self.camera.name!r}: {self.bag} has no messages on {self.topic}; "
                f"its PointCloud2 topics: {clouds or 'none'}"
            )
        if any(c.msgtype != POINTCLOUD2 for c in self._connections):
            reader.close()
            raise CameraError(f"replay camera {self.camera.name!r}: {self.topic} in {self.bag} is not {POINTCLOUD2}")
        self._typestore = rosbags_factory().typestore
        self._reader = reader
        self._bag_start_ns = reader.start_time
        self._period_ns = period_ns = int(1e9 / max(self.camera.publish_hz, 1e-3))
        # one pass of the bag, plus one frame period before it starts over
        self._loop_ns = int((reader.end_time - reader.start_time) / self.rate) + period_ns
        now = time.time_ns()
        if self.loop:
            self._origin = now - now % self._loop_ns  # this cycle's start on the wall-clock grid
            self._messages = reader.messages(connections=self._connections)
            self._skip_past(now)
        else:
            self._origin = -(-now // period_ns) * period_ns  # the next period boundary
            self._messages = reader.messages(connections=self._connections)

    def _due_ns(self, logtime: int) -> int:
        return self._origin + int((logtime - self._bag_start_ns) / self.rate)

    def _skip_past(self, now: int) -> None:
        """Drop the frames of this cycle that were due before ``now`` (without decoding them)."""
        while self._due_ns(self._next_raw()[1]) < now:
            self._pending = None

    def _next_raw(self):
        if self._pending is not None:
            return self._pending
        try:
            self._pending = next(self._messages)
        except StopIteration:
            if not self.loop:
                raise ReplayFinished(
                    f"replay camera {self.camera.name!r}: {self.bag} finished after {self.frames_read} frames"
                ) from None
            self._origin += self._loop_ns
            self._messages = self._reader.messages(connections=self._connections)
            self._pending = next(self._messages)
        return self._pending

    def read(self, timeout_s: float = 1.0) -> CloudFrame:
        if self._reader is None:
            raise CameraError(f"replay camera {self.camera.name!r} is not connected")
        self._skip_past(time.time_ns() - self._period_ns)  # fell behind (busy machine): drop, don't burst
        conn, logtime, raw = self._next_raw()
        wait_s = (self._due_ns(logtime) - time.time_ns()) / 1e9
        if wait_s > timeout_s:
            time.sleep(timeout_s)
            raise CameraError(f"replay camera {self.camera.name!r}: no frame due within {timeout_s} s")
        if wait_s > 0:
            time.sleep(wait_s)
        self._pending = None
        try:
            msg = self._typestore.deserialize_cdr(raw, conn.msgtype)
            cloud = msg_to_cloud(msg, drop_invalid=True)
        except (CloudError, Exception) as err:
            raise CameraError(
                f"replay camera {self.camera.name!r}: unusable message at {logtime} ns in {self.bag}: {err}"
            ) from err
        self.frames_read += 1
        stamp = self._clock() if self.restamp else cloud.stamp_ns
        return CloudFrame(cloud.points, cloud.colors, stamp)

    def disconnect(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None
            self._messages = None
            self._pending = None
