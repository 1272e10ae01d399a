"""Episode recording: one rosbag2 directory (metadata.yaml + .mcap, Jazzy definitions, CDR) per episode.

``EpisodeWriter`` wraps rosbags' ``Writer`` (we never hand-write MCAP) and adds what a
demonstration recorder needs on top of it:

* **never overwrites**: the target directory must not exist (rosbags refuses too, we fail
  earlier with a clearer message); ``next_episode_path`` picks the next free name;
* **free-disk check** before starting and at every chunk, so a full disk stops the episode
  cleanly instead of leaving a half-written file;
* **large chunks** (8 MiB default; rosbags hard-codes 1 MiB): rosbag2's Jazzy C++ reader
  mishandles messages larger than the chunk and one voxel grid can approach 1 MiB. Chunks are also closed after ``chunk_max_age_s`` and flushed to the OS, so a
  recorder killed with SIGKILL loses at most the last few seconds: ``data.bags.repair_bag``
  recovers everything in completed chunks;
* **episode metadata** (task, operator, success, notes, seed) in metadata.yaml's
  ``custom_data`` and, from the first moment, in a sidecar ``episode.yaml`` that repair uses
  when the recorder never reached ``close``;
* ``/tf_static`` written from the lab config, so every bag carries the camera extrinsics
  even where tf2_msgs cannot be published (architecture.md note 1).

Messages arrive either serialised (the recorder node subscribes with ``raw=True`` and writes
the CDR bytes untouched) or as rosbags message objects (tests, the sample-bag generator).
"""

from __future__ import annotations

import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Self

import yaml

from ..config import LabConfig, bounded, described
from ..wire.rosmsg import RosbagsFactory, rosbags_factory, transform_msg_from_pos_quat
from ..wire.topics import (
    CLOUD_TYPE,
    COMPRESSED_IMAGE_TYPE,
    RECORDED_TOPICS,
    TF_TYPE,
    TOPIC_TF_STATIC,
    camera_color_topic,
)
from .bags import META_SIDECAR, EpisodeMeta
from .mcap_writer import MiB, open_bag_writer


class RecordingError(RuntimeError):
    """The episode cannot be started or continued (path exists, disk full, writer closed)."""


@dataclass
class InterventionLog:
    """The operator's takeovers during one episode (``/teleop/active`` edges), for its metadata.

    A lab correcting a policy needs to find them without replaying the bag: ``metadata()``
    gives ``interventions`` (``start-end`` seconds from the episode start, space-separated)
    and ``intervention_count``; the edges themselves are in the bag on /teleop/active.
    """

    start_ns: int
    spans: list[tuple[int, int | None]] = field(default_factory=list)

    def update(self, active: bool, stamp_ns: int) -> None:
        ongoing = bool(self.spans) and self.spans[-1][1] is None
        if active and not ongoing:
            self.spans.append((max(stamp_ns, self.start_ns), None))
        elif not active and ongoing:
            self.spans[-1] = (self.spans[-1][0], stamp_ns)

    def metadata(self, end_ns: int) -> dict[str, str]:
        def s(t: int) -> str:
            return f"{(t - self.start_ns) / 1e9:.2f}"

        spans = [(a, end_ns if b is None else b) for a, b in self.spans]
        return {"interventions": " ".join(f"{s(a)}-{s(b)}" for a, b in spans), "intervention_count": str(len(spans))}


@dataclass(frozen=True)
class RecordingConfig:
    """How episodes are written (config/data.yaml ``recorder`` section)."""

    output_dir: str = described(
        "episodes", "Directory of the episodes: one rosbag2 directory <output_dir>/<task>_NNNN each"
    )
    # docs/data.md: what the clouds and images cost a bag
    record_clouds: bool = described(False, "Record each camera's point cloud")
    record_images: bool = described(True, "Record each camera's JPEG colour image")
    # above the largest message (a voxel grid, about 1 MiB; config/data.yaml says why)
    chunk_size_mib: float = bounded(8.0, unit="MiB", ge=2, le=1024, description="MCAP chunk size")
    chunk_max_age_s: float = bounded(
        2.0, unit="s", gt=0, le=60, description="A chunk is flushed at least this often: what a SIGKILL can lose"
    )
    min_free_gib: float = bounded(
        2.0,
        unit="GiB",
        ge=0,
        le=100_000,
        description="Free disk below which no episode starts (or it stops and is kept)",
    )

    def __post_init__(self):
        if self.chunk_size_mib < 2:
            raise ValueError(f"chunk_size_mib must be >= 2 (messages reach 1 MiB), got {self.chunk_size_mib}")
        if self.chunk_max_age_s <= 0:
            raise ValueError(f"chunk_max_age_s must be positive, got {self.chunk_max_age_s}")


def free_bytes(path: str | Path) -> int:
    """Free bytes on the file system holding ``path`` (or its nearest existing parent)."""
    path = Path(path).absolute()
    while not path.exists():
        path = path.parent
    return shutil.disk_usage(path).free


def next_episode_path(output_dir: str | Path, task: str = "episode") -> Path:
    """``<output_dir>/<task>_NNNN``: the first index after every existing episode of that task."""
    output_dir = Path(output_dir)
    slug = re.sub(r"[^A-Za-z0-9_-]+", "_", task).strip("_") or "episode"
    pattern = re.compile(rf"^{re.escape(slug)}_(\d+)(?:\.\w+)?$")
    taken = [
        int(m.group(1)) for p in (output_dir.iterdir() if output_dir.is_dir() else ()) if (m := pattern.match(p.name))
    ]
    return output_dir / f"{slug}_{(max(taken) + 1 if taken else 0):04d}"


def _qos(reliable: bool = True, transient_local: bool = False, depth: int = 10):
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    zero = QosTime(0, 0)
    return Qos(
        QosHistory.KEEP_LAST,
        depth,
        QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
        QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
        zero,
        zero,
        QosLiveliness.AUTOMATIC,
        zero,
        False,
    )


class EpisodeWriter:
    """Writes one episode bag. ``open`` -> ``write``/``write_raw`` ... -> ``close`` (keep) or ``discard``."""

    def __init__(
        self,
        path: str | Path,
        meta: EpisodeMeta | None = None,
        config: RecordingConfig = RecordingConfig(),
        factory: RosbagsFactory | None = None,
    ):
        self.path = Path(path)
        self.meta = meta or EpisodeMeta()
        self.config = config
        self.factory = factory or rosbags_factory()
        self._writer = None
        self._connections: dict[str, Any] = {}
        self.counts: dict[str, int] = {}
        self.low_disk = False

    # -- lifecycle --------------------------------------------------------------------------
    def open(self) -> EpisodeWriter:
        if self.path.exists():
            raise RecordingError(f"{self.path} already exists: episodes are never overwritten")
        need = int(self.config.min_free_gib * (1 << 30))
        have = free_bytes(self.path.parent)
        if have < need:
            raise RecordingError(
                f"only {have / (1 << 30):.2f} GiB free on {self.path.parent} "
                f"(need {self.config.min_free_gib} GiB, recorder.min_free_gib)"
            )
        self.path.parent.mkdir(parents=True, exist_ok=True)

        self._writer = open_bag_writer(
            self.path, int(self.config.chunk_size_mib * MiB), self.config.chunk_max_age_s, on_chunk=self._check_disk
        )
        self._write_sidecar()
        return self

    @property
    def is_open(self) -> bool:
        return self._writer is not None

    def _require_open(self):
        if self._writer is None:
            raise RecordingError(f"episode {self.path} is not open")
        return self._writer

    def _check_disk(self) -> None:
        if free_bytes(self.path) < int(self.config.min_free_gib * (1 << 30)) // 2:
            self.low_disk = True  # the node stops and keeps the episode on its next tick

    def _write_sidecar(self) -> None:
        tmp = self.path / (META_SIDECAR + ".tmp")
        tmp.write_text(yaml.safe_dump(self.meta.to_dict(), sort_keys=False))
        tmp.replace(self.path / META_SIDECAR)

    def close(self, **meta_updates: Any) -> Path:
        """Finish the bag (metadata.yaml with custom_data); ``meta_updates`` e.g. success=True, notes=..."""
        writer = self._require_open()
        self.meta = self.meta.replace(**meta_updates)
        for key, value in self.meta.to_custom_data().items():
            writer.set_custom_data(key, value)
        writer.close()
        self._writer = None
        self._write_sidecar()
        return self.path

    def discard(self) -> None:
        """Abort and delete the episode directory."""
        if self._writer is not None:
            self._writer.abort()
            self._writer = None
        shutil.rmtree(self.path, ignore_errors=True)

    def __enter__(self) -> Self:
        return self.open() if not self.is_open else self

    def __exit__(self, exc_type, exc, tb) -> None:
        if self.is_open:
            if exc_type is None:
                self.close()
            else:  # keep what was recorded: an exception is no reason to lose a demonstration
                self.close(notes=(self.meta.notes + f" [recording ended by {exc_type.__name__}]").strip())

    # -- topics -----------------------------------------------------------------------------
    def add_topic(self, topic: str, msgtype: str, *, reliable: bool = True, transient_local: bool = False):
        writer = self._require_open()
        if topic in self._connections:
            conn = self._connections[topic]
            if conn.msgtype != msgtype:
                raise RecordingError(f"{topic} already recorded as {conn.msgtype}, not {msgtype}")
            return conn
        conn = writer.add_connection(
            topic, msgtype, typestore=self.factory.typestore, offered_qos_profiles=[_qos(reliable, transient_local)]
        )
        self._connections[topic] = conn
        self.counts[topic] = 0
        return conn

    def write_raw(self, topic: str, stamp_ns: int, data: bytes | memoryview, msgtype: str | None = None) -> None:
        """Write already serialised CDR (from an rclpy ``raw=True`` subscription) at receive time ``stamp_ns``."""
        writer = self._require_open()
        conn = self._connections.get(topic)
        if conn is None:
            if msgtype is None:
                raise RecordingError(f"topic {topic} was not added and no type was given")
            conn = self.add_topic(topic, msgtype)
        writer.write(conn, int(stamp_ns), data)
        self.counts[topic] += 1

    def write(self, topic: str, msg: Any, stamp_ns: int, msgtype: str | None = None) -> None:
        """Serialise a rosbags message and write it."""
        msgtype = msgtype or getattr(msg, "__msgtype__", None)
        if msgtype is None:
            raise RecordingError(f"cannot tell the type of {type(msg).__name__} for {topic}")
        data = self.factory.typestore.serialize_cdr(msg, msgtype)
        self.write_raw(topic, stamp_ns, data, msgtype)

    def flush_if_old(self) -> None:
        """Close the pending chunk if it is older than chunk_max_age_s (call from a timer)."""
        if self._writer is not None:
            self._writer.storage.flush_if_old()

    def write_tf_static(self, lab: LabConfig, stamp_ns: int) -> None:
        """The configured camera extrinsics as one /tf_static TFMessage (base -> optical frames)."""
        self.add_topic(TOPIC_TF_STATIC, TF_TYPE, transient_local=True)
        transforms = [
            self.factory.make(
                "geometry_msgs/msg/TransformStamped",
                header=self.factory.header(stamp_ns, lab.base_frame),
                child_frame_id=cam.frame_id,
                # the configured values as they are (not through a 4x4 pose): the bag says what lab.yaml says
                transform=transform_msg_from_pos_quat(
                    self.factory, cam.extrinsics.translation, cam.extrinsics.quaternion_xyzw
                ),
            )
            for cam in lab.cameras
        ]
        self.write(TOPIC_TF_STATIC, self.factory.make(TF_TYPE, transforms=transforms), stamp_ns, TF_TYPE)


def recorded_topics(lab: LabConfig, record_clouds: bool, record_images: bool = True) -> dict[str, str]:
    """Topic -> type of everything the recorder subscribes to."""
    topics = dict(RECORDED_TOPICS)
    if record_images:
        topics.update({camera_color_topic(cam.name): COMPRESSED_IMAGE_TYPE for cam in lab.cameras})
    if record_clouds:
        topics.update({cam.topic: CLOUD_TYPE for cam in lab.cameras})
    return topics
