"""The one way this project opens a rosbag2 (MCAP) bag for writing: rosbags' ``Writer`` with
large, promptly flushed chunks.

Both the episode recorder (``recording.EpisodeWriter``) and bag repair (``bags.repair_bag``)
write through ``open_bag_writer``; it lives apart from both so neither imports the other.

Why not rosbags' stock MCAP storage: it closes a chunk once it exceeds a hard-coded 1 MiB
and leaves it in Python's write buffer. rosbag2's Jazzy C++ reader mishandles messages larger
than the chunk (one voxel grid approaches 1 MiB), and a SIGKILLed recorder loses whatever is
still buffered. So chunks here have a configurable size (8 MiB by default), are also closed
after ``chunk_max_age_s``, and each completed chunk is flushed to the OS.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import ClassVar

MiB = 1 << 20


def open_bag_writer(
    path: str | Path,
    chunk_size: int = 8 * MiB,
    chunk_max_age_s: float = 2.0,
    on_chunk: Callable[[], None] | None = None,
):
    """An opened rosbags ``Writer`` (rosbag2 version 9, MCAP storage) at ``path``, which must not exist.

    ``on_chunk`` is called after each completed chunk (the recorder checks free disk there)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    class _BagWriter(Writer):
        STORAGE_PLUGINS: ClassVar = {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: _chunked_mcap_writer_cls()}

    writer = _BagWriter(Path(path), version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    writer.storage.chunk_size = int(chunk_size)
    writer.storage.chunk_max_age_s = float(chunk_max_age_s)
    writer.storage.on_chunk = on_chunk
    return writer


def _chunked_mcap_writer_cls():
    """rosbags' McapWriter with our chunking: ``write`` is overridden (same record layout, our
    threshold) and ``close_chunk`` flushes (see the module doc)."""
    from io import BytesIO

    from rosbags.rosbag2.storage_mcap import (
        McapWriter,
        write_record,
        write_uint16,
        write_uint32,
        write_uint64,
    )

    class ChunkedMcapWriter(McapWriter):
        chunk_size = 8 * MiB
        chunk_max_age_s = 2.0
        on_chunk = None  # callback after each completed chunk (free-disk check)

        def __init__(self, path, compression):
            super().__init__(path, compression)
            self.chunk_opened = time.monotonic()

        def close_chunk(self) -> None:
            super().close_chunk()
            self.bio.flush()
            self.chunk_opened = time.monotonic()
            if self.on_chunk is not None:
                self.on_chunk()

        def write(self, connection, timestamp: int, data) -> None:
            if not self.chunk.msgs:
                self.chunk_opened = time.monotonic()
            self.message_start_time = min(timestamp, self.message_start_time)
            self.message_end_time = max(timestamp, self.message_end_time)
            self.channel_stats[connection.id] += 1
            self.chunk.message_start_time = min(timestamp, self.chunk.message_start_time)
            self.chunk.message_end_time = max(timestamp, self.chunk.message_end_time)
            self.chunk.msgs[connection.id].append((timestamp, self.chunk.bio.tell()))
            rec = BytesIO()
            write_uint16(rec, connection.id)
            write_uint32(rec, 0)
            write_uint64(rec, timestamp)
            write_uint64(rec, timestamp)
            rec.write(data)
            write_record(self.chunk.bio, 0x05, rec)
            if self.chunk.bio.tell() > self.chunk_size or self.chunk_age_s() > self.chunk_max_age_s:
                self.close_chunk()

        def chunk_age_s(self) -> float:
            return time.monotonic() - self.chunk_opened if self.chunk.msgs else 0.0

        def flush_if_old(self) -> None:
            if self.chunk.msgs and self.chunk_age_s() > self.chunk_max_age_s:
                self.close_chunk()

    return ChunkedMcapWriter
