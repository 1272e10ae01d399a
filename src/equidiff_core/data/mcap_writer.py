"""The one way this project opens a rosbag2 (MCAP) bag for writing: rosbags' ``Writer`` (the
rosbag2 directory and its metadata.yaml) over an MCAP file written by the ``mcap`` package's
``Writer`` with CRCs, in large, promptly flushed chunks.

Everything that writes bags (the episode recorder ``data.recording.EpisodeWriter``, bag repair
``data.bags.repair_bag``, re-voxelisation ``perception.fusion``) goes through ``open_bag_writer``; it lives apart
from them so none imports another.

Why not rosbags' stock MCAP storage:

* it stores every chunk CRC as 0 (and its reader checks only non-zero CRCs), so its bags carry
  no integrity check at all. The ``mcap`` package writes the chunk, data-section and summary
  CRCs, which ``data.bags.read_episode`` verifies (and ``ros2 bag``, Foxglove, rerun ignore or check);
* it closes a chunk once it exceeds a hard-coded 1 MiB and leaves it in Python's write buffer.
  rosbag2's Jazzy C++ reader mishandles messages larger than the chunk (one voxel grid approaches
  1 MiB), and a SIGKILLed recorder loses whatever is still buffered. So chunks here have a
  configurable size (8 MiB by default), are also closed after ``chunk_max_age_s``, and each
  completed chunk is flushed to the OS.

The storage keeps what rosbag2's own MCAP plugin writes: the ``ros2`` profile, ``ros2msg``
schemas, ``cdr`` channels with their ``offered_qos_profiles``, and a ``rosbag2`` metadata record.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import ClassVar

MiB = 1 << 20
# an MCAP message record around its data: opcode 1 + length 8 + channel 2 + sequence 4 + two times 16
MESSAGE_RECORD_OVERHEAD = 31


def open_bag_writer(
    path: str | Path,
    chunk_size: int = 8 * MiB,
    chunk_max_age_s: float = 2.0,
    on_chunk: Callable[[], None] | None = None,
):
    """An opened rosbags ``Writer`` (rosbag2 version 9, MCAP storage with CRCs) at ``path``, which must not exist.

    ``on_chunk`` is called after each completed chunk (the recorder checks free disk there)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    class _BagWriter(Writer):
        STORAGE_PLUGINS: ClassVar = {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: CheckedMcapStorage}

    writer = _BagWriter(Path(path), version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    writer.storage.chunk_size = int(chunk_size)
    writer.storage.chunk_max_age_s = float(chunk_max_age_s)
    writer.storage.on_chunk = on_chunk
    return writer


class CheckedMcapStorage:
    """rosbags' storage-plugin interface (``add_msgtype``, ``add_connection``, ``write``, ``close``,
    ``abort``) over ``mcap.writer.Writer`` with chunk, data-section and summary CRCs.

    Chunks are closed here (through the writer's public ``flush``), not by the ``mcap`` writer's
    own size check, so that each completed chunk can be flushed, aged and reported."""

    chunk_size = 8 * MiB
    chunk_max_age_s = 2.0
    on_chunk: Callable[[], None] | None = None  # callback after each completed chunk (free-disk check)

    def __init__(self, path: Path, compression) -> None:
        from mcap.writer import CompressionType, Writer
        from rosbags.rosbag2.enums import CompressionMode

        self.path = path / f"{path.name}.mcap"
        self.stream = self.path.open("xb")
        self.mcap = Writer(
            self.stream,
            chunk_size=1 << 62,  # never: chunks are closed by ``write`` below
            compression=CompressionType.ZSTD if compression == CompressionMode.STORAGE else CompressionType.NONE,
            enable_crcs=True,
            enable_data_crcs=True,
        )
        self.mcap.start(profile="ros2", library=f"equidiff_ros (mcap-python {_mcap_version()})")
        self.schema_ids: dict[str, int] = {}
        self.channel_ids: dict[int, int] = {}  # rosbags connection id -> MCAP channel id
        self.pending_bytes = 0
        self.chunk_opened = time.monotonic()

    def add_msgtype(self, connection) -> None:
        from rosbags.interfaces import MessageDefinitionFormat

        encoding = "ros2msg" if connection.msgdef.format == MessageDefinitionFormat.MSG else "ros2idl"
        self.schema_ids[connection.msgtype] = self.mcap.register_schema(
            connection.msgtype, encoding, connection.msgdef.data.encode()
        )

    def add_connection(self, connection, offered_qos_profiles: str) -> None:
        self.channel_ids[connection.id] = self.mcap.register_channel(
            connection.topic,
            connection.ext.serialization_format,
            self.schema_ids[connection.msgtype],
            {"offered_qos_profiles": offered_qos_profiles},
        )

    def write(self, connection, timestamp: int, data: bytes | memoryview) -> None:
        if not self.pending_bytes:
            self.chunk_opened = time.monotonic()
        self.mcap.add_message(self.channel_ids[connection.id], int(timestamp), bytes(data), int(timestamp))
        self.pending_bytes += MESSAGE_RECORD_OVERHEAD + len(data)
        if self.pending_bytes > self.chunk_size or self.chunk_age_s() > self.chunk_max_age_s:
            self.close_chunk()

    def close_chunk(self) -> None:
        """Write the pending chunk (with its CRC) and its message indexes, and flush them to the OS."""
        self.mcap.flush()
        self.pending_bytes = 0
        self.chunk_opened = time.monotonic()
        if self.on_chunk is not None:
            self.on_chunk()

    def chunk_age_s(self) -> float:
        return time.monotonic() - self.chunk_opened if self.pending_bytes else 0.0

    def flush_if_old(self) -> None:
        if self.pending_bytes and self.chunk_age_s() > self.chunk_max_age_s:
            self.close_chunk()

    def close(self, version: int, metadata: str) -> None:
        """Finish the file: last chunk, rosbag2's metadata record, data end, summary, footer (all CRC'd)."""
        del version  # the rosbag2 version is in ``metadata``
        if self.pending_bytes:
            self.close_chunk()
        self.mcap.add_metadata("rosbag2", {"serialized_metadata": metadata})
        self.mcap.finish()
        self.stream.close()

    def abort(self) -> None:
        """Close without the summary and footer (the caller deletes or keeps the file)."""
        self.stream.close()


def _mcap_version() -> str:
    from importlib.metadata import version

    return version("mcap")
