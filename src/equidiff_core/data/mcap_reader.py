"""The one way this project reads a bag's MCAP file: every record in file order, every CRC checked.

``iter_mcap(path, scan)`` yields ``(channel, log_time_ns, data)`` for each message and fills
``scan`` (an ``McapScan``) with what it found: the channels, how many chunks carried a CRC,
which chunks are damaged (their topics, times and message counts, from the message indexes
written beside them), where reading stopped. ``data.bags.read_episode``, ``data.bags.repair_bag``, the
rerun converter and re-voxelisation all read through it.

It walks the file with the ``mcap`` package's ``StreamReader`` (its record parser and chunk
and data-section CRC checks) rather than its seeking reader, for three reasons:

* the seeking reader trusts the summary section (channels, chunk index), which nothing in
  ``mcap`` checks; here channels come from the data section, covered by the chunk and
  data-section CRCs, and the summary's own CRC is checked too (``_check_summary_crc``: ``mcap``
  writes that CRC but none of its readers verifies it, hence these few lines of our own);
* a damaged chunk is reported with its topics and times and reading goes on, so repair keeps
  every intact chunk;
* the seeking reader does not check the data-section CRC (``mcap``'s own docstring says so).

A CRC of 0 means "not computed" in MCAP: bags written by rosbags' MCAP storage (this project's
bags before it wrote through ``mcap``) have only zeros. They still read, but ``scan.integrity``
says ``"unchecked"``, so nothing claims a check that never happened.
"""

from __future__ import annotations

import mmap
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Channel, Chunk, DataEnd, Footer, Message, MessageIndex, Schema, Statistics
from mcap.stream_reader import CRCValidationError, StreamReader, breakup_chunk

CHECKED = "checked"  # every chunk and the data section carry a CRC, and all matched
UNCHECKED = "unchecked"  # readable, but stored without CRCs (nothing could be checked)
MCAP_MAGIC = b"\x89MCAP0\r\n"
FOOTER_TAIL = 4 + len(MCAP_MAGIC)  # the footer's summary CRC field, then the closing magic


class BagError(RuntimeError):
    """A bag that cannot be read as an episode (missing, truncated, malformed); the message says why."""


class BagIntegrityError(BagError):
    """A bag whose stored CRCs do not match its bytes (a flipped bit, a damaged copy): its messages
    cannot be trusted. ``damaged`` lists the failing chunks with their topics and times; the message
    names the first one. ``equidiff bags repair`` keeps the intact chunks."""

    def __init__(self, message: str, damaged: list[DamagedChunk] | None = None):
        super().__init__(message)
        self.damaged = list(damaged or [])


@dataclass(frozen=True)
class McapChannel:
    id: int
    topic: str
    msgtype: str  # the schema name, e.g. sensor_msgs/msg/PointCloud2
    schema_encoding: str  # ros2msg / ros2idl
    schema_text: str
    message_encoding: str  # cdr
    metadata: dict[str, str]  # offered_qos_profiles


@dataclass
class DamagedChunk:
    """A chunk whose CRC (or structure) failed: what it held, from the message indexes beside it."""

    offset: int  # byte offset of the chunk record in the .mcap
    start_ns: int  # log time of its first message (from the chunk header)
    end_ns: int
    reason: str
    messages: dict[str, int] = field(default_factory=dict)  # topic -> messages lost, when indexed
    first_topic: str = ""  # topic of its first message, when indexed

    @property
    def total(self) -> int:
        return sum(self.messages.values())

    def describe(self, episode_start_ns: int | None = None) -> str:
        """e.g. "chunk at byte 4242 (first message /voxels at 1700000001.200000000 s, +1.200 s from ...; ...)"."""

        def when(ns: int) -> str:
            rel = f", {(ns - episode_start_ns) / 1e9:+.3f} s from the first intact message" if episode_start_ns else ""
            return f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d} s{rel}"

        first = f"first message {self.first_topic or '(topic unknown)'} at {when(self.start_ns)}"
        lost = ", ".join(f"{t} {n}" for t, n in sorted(self.messages.items())) or "message count unknown"
        return (
            f"chunk at byte {self.offset} ({first}; log times {self.start_ns}..{self.end_ns} ns; "
            f"messages: {lost}): {self.reason}"
        )


@dataclass
class McapScan:
    """What ``iter_mcap`` found in one .mcap file."""

    path: Path
    channels: dict[int, McapChannel] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)  # messages read per topic (intact chunks)
    chunks: int = 0  # intact chunks read
    unchecked_chunks: int = 0  # of them, stored without a CRC
    damaged: list[DamagedChunk] = field(default_factory=list)
    orphaned: int = 0  # messages of intact chunks whose channel was defined in a damaged one (lost too)
    data_crc_checked: bool = False  # the data-section CRC was present and matched
    summary_crc_checked: bool = False
    complete: bool = False  # the footer and closing magic were read
    good_until: int = 0  # byte offset after the last complete record
    stopped: str = ""  # why reading stopped before the footer ('' if it did not)
    start_ns: int | None = None  # first and last message log times
    end_ns: int | None = None

    @property
    def integrity(self) -> str:
        """``"checked"`` when every chunk and the data section carried a CRC (all matched, since a
        mismatch raises), else ``"unchecked"``."""
        return CHECKED if self.chunks and not self.unchecked_chunks and self.data_crc_checked else UNCHECKED

    @property
    def total(self) -> int:
        return sum(self.counts.values())


def iter_mcap(path: str | Path, scan: McapScan | None = None, *, tolerant: bool = False) -> Iterator:
    """Yield ``(McapChannel, log_time_ns, data)`` for every message of every intact chunk, in file order.

    Strict (default): a damaged chunk, a bad data-section or summary CRC raises ``BagIntegrityError``
    once the whole file was read (naming every damaged chunk); a truncated or malformed file raises
    ``BagError`` where it stops. ``tolerant`` (repair): nothing raises except a file that is not MCAP
    at all; ``scan.damaged`` and ``scan.stopped`` say what was skipped and why reading stopped."""
    path = Path(path)
    scan = scan if scan is not None else McapScan(path)
    try:
        fh = path.open("rb")
    except OSError as err:
        raise BagError(f"{path}: cannot open ({err})") from err
    with fh:
        size = path.stat().st_size
        if size < len(MCAP_MAGIC) or fh.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise BagError(f"{path}: not an MCAP file (bad magic)")
        # mmap: a corrupt length field makes the parser ask for huge reads, which a mapped file
        # answers with what is there instead of allocating the requested size
        with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as data:
            yield from _walk(data, scan, tolerant)
    if not tolerant:
        problems = [d.describe(scan.start_ns) for d in scan.damaged]
        if problems:
            more = f" (and {len(problems) - 1} more damaged chunks)" if len(problems) > 1 else ""
            raise BagIntegrityError(f"{path}: CRC mismatch in {problems[0]}{more}", scan.damaged)


def _walk(data: mmap.mmap, scan: McapScan, tolerant: bool) -> Iterator:
    schemas: dict[int, Schema] = {}
    reader = StreamReader(data, validate_crcs=True, emit_chunks=True, record_size_limit=len(data))
    last_damaged: DamagedChunk | None = None
    data_end_seen = footer_seen = False
    record_start = len(MCAP_MAGIC)
    records = reader.records
    while True:
        try:
            record = next(records)
        except StopIteration:
            break
        except CRCValidationError as err:  # the data-section CRC (chunk CRCs are checked below, per chunk)
            what = "data section" if isinstance(err.record, DataEnd) else type(err.record).__name__
            if scan.damaged:  # the damaged chunks' bytes are in the data section: they explain it
                scan.stopped = f"CRC mismatch in the {what}, from the damaged chunks"
                return  # strict: ``iter_mcap`` raises, naming them
            msg = f"CRC mismatch in the {what} (a damaged byte outside the chunks' messages)"
            if tolerant:
                scan.stopped = msg
                return
            raise BagIntegrityError(f"{scan.path}: {msg}", scan.damaged) from None
        except Exception as err:  # mcap raises EndOfFile, struct.error, ValueError... on bad bytes
            where = "summary section" if data_end_seen else f"record at byte {record_start}"
            if data.tell() >= len(data):  # the parser ran into the end of the file
                msg = f"{where} cut off (the file ends at byte {len(data)}: truncated)"
            else:
                msg = f"malformed {where} ({type(err).__name__}: {err})"
            if tolerant:
                scan.stopped = msg
                return
            raise BagError(f"{scan.path}: {msg}") from err
        record_start_next = data.tell()
        if isinstance(record, Chunk):
            last_damaged = None
            try:
                inner = breakup_chunk(record, validate_crc=True)
                if not record.compression and len(record.data) != record.uncompressed_size:
                    raise ValueError(f"{len(record.data)} bytes where the header says {record.uncompressed_size}")
            except Exception as err:  # noqa: BLE001 - a CRC mismatch or garbage inside: the whole chunk is lost
                reason = "CRC mismatch" if isinstance(err, CRCValidationError) else f"malformed ({err})"
                last_damaged = DamagedChunk(record_start, record.message_start_time, record.message_end_time, reason)
                scan.damaged.append(last_damaged)
            else:
                yield from _chunk_messages(inner, record, schemas, scan)
        elif isinstance(record, MessageIndex):
            if last_damaged is not None and record.records:
                topic = scan.channels[record.channel_id].topic if record.channel_id in scan.channels else ""
                topic = topic or f"(channel {record.channel_id})"
                last_damaged.messages[topic] = last_damaged.messages.get(topic, 0) + len(record.records)
                first = min(t for t, _ in record.records)
                if first <= last_damaged.start_ns or not last_damaged.first_topic:
                    last_damaged.first_topic = topic
        elif isinstance(record, Schema | Channel) and not data_end_seen:
            _add_schema_or_channel(record, schemas, scan)
        elif isinstance(record, DataEnd):
            data_end_seen = True
            scan.data_crc_checked = record.data_section_crc != 0  # a mismatch was raised above
        elif isinstance(record, Statistics) and not scan.damaged and not tolerant:
            _check_counts(record, scan)
        elif isinstance(record, Footer):
            footer_seen = True
            if not tolerant:
                if not data_end_seen:
                    raise BagError(f"{scan.path}: no data-end record before the footer (malformed)")
                scan.summary_crc_checked = _check_summary_crc(data, record, scan.path)
        scan.good_until = record_start = record_start_next
        if not isinstance(record, Chunk | MessageIndex):
            last_damaged = None
    scan.complete = footer_seen  # and the closing magic after it
    if footer_seen:
        scan.good_until = len(data)


def _chunk_messages(inner, chunk, schemas, scan: McapScan) -> Iterator:
    """The messages of one intact chunk (registering the schemas and channels it defines)."""
    scan.chunks += 1
    scan.unchecked_chunks += chunk.uncompressed_crc == 0
    out = []
    for rec in inner:
        if isinstance(rec, Schema | Channel):
            _add_schema_or_channel(rec, schemas, scan)
        elif isinstance(rec, Message):
            channel = scan.channels.get(rec.channel_id)
            if channel is None and scan.damaged:  # defined in a damaged chunk: lost with it
                scan.orphaned += 1
                continue
            if channel is None:
                raise BagError(f"{scan.path}: message on channel {rec.channel_id}, which no intact record defines")
            out.append((channel, rec.log_time, rec.data))
    for channel, log_time, payload in out:  # only once the whole chunk parsed: a chunk is all or nothing
        scan.counts[channel.topic] = scan.counts.get(channel.topic, 0) + 1
        scan.start_ns = log_time if scan.start_ns is None else min(scan.start_ns, log_time)
        scan.end_ns = log_time if scan.end_ns is None else max(scan.end_ns, log_time)
        yield channel, log_time, payload


def _add_schema_or_channel(rec, schemas, scan: McapScan) -> None:
    if isinstance(rec, Schema):
        schemas[rec.id] = rec
        return
    schema = schemas.get(rec.schema_id)
    if schema is None:
        raise BagError(f"{scan.path}: channel {rec.topic} refers to schema {rec.schema_id}, which is not defined")
    scan.channels[rec.id] = McapChannel(
        rec.id,
        rec.topic,
        schema.name,
        schema.encoding,
        schema.data.decode(errors="replace"),
        rec.message_encoding,
        dict(rec.metadata),
    )


def _check_counts(stats, scan: McapScan) -> None:
    """The summary's per-channel message counts must be what the data section held."""
    for cid, expected in stats.channel_message_counts.items():
        topic = scan.channels[cid].topic if cid in scan.channels else f"(channel {cid})"
        if scan.counts.get(topic, 0) != expected:
            raise BagIntegrityError(
                f"{scan.path}: the summary counts {expected} messages on {topic}, "
                f"the data section holds {scan.counts.get(topic, 0)}"
            )


def _check_summary_crc(data: mmap.mmap, footer, path: Path) -> bool:
    """Verify the footer's summary CRC (crc32 of the summary section and the footer up to the CRC
    field, per the MCAP spec); True if it was present. The ``mcap`` readers never check it."""
    if footer.summary_crc == 0:
        return False
    end = len(data) - FOOTER_TAIL
    footer_record = end - (1 + 8 + 8 + 8)  # opcode, record length, summary_start, summary_offset_start
    start = footer.summary_start or footer_record
    if not 0 < start <= footer_record:
        raise BagIntegrityError(f"{path}: the footer points its summary at byte {start}, outside the file")
    actual = zlib.crc32(data[start:end])
    if actual != footer.summary_crc:
        raise BagIntegrityError(
            f"{path}: CRC mismatch in the summary section (index and statistics; "
            f"stored {footer.summary_crc:#010x}, computed {actual:#010x})"
        )
    return True
