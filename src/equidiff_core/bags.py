"""Reading episode bags (rosbag2 directories, MCAP storage) and repairing killed recordings.

``read_episode(path)`` decodes every message of the requested topics with rosbags' Jazzy
typestore and returns them per topic with their bag (receive) times; the dataset aligns
observations by *header* stamps, which the messages carry. ``EpisodeMeta`` is what the
recorder stores in metadata.yaml ``custom_data`` (and in the ``episode.yaml`` sidecar, so
it survives a killed recorder).

``repair_bag(path)`` handles the one way a recording goes wrong on its own: the recorder
process dies (SIGKILL, power) before rosbags writes the MCAP summary and metadata.yaml.
rosbags' reader needs the summary section, so repair scans the MCAP records itself,
keeps every message of every complete chunk (CRC-checked by rosbags' ``decompress``), stops
at the first truncated record, and rewrites a proper bag with the same topics, types and
QoS. The damaged original is kept next to it (``<name>.unrepaired``); nothing is lost.
"""

from __future__ import annotations

import dataclasses
import shutil
import struct
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .rosmsg import rosbags_factory, stamp_to_ns

META_SIDECAR = "episode.yaml"
UNREPAIRED_SUFFIX = ".unrepaired"
MCAP_MAGIC = b"\x89MCAP0\r\n"


class BagError(RuntimeError):
    """A bag that cannot be read as an episode (missing, truncated, malformed); the message says why."""


# --- metadata ------------------------------------------------------------------------------


@dataclass(frozen=True)
class EpisodeMeta:
    """Operator-facing facts about an episode, stored in metadata.yaml custom_data (all strings there)."""

    task: str = ""
    operator: str = ""
    success: bool | None = None  # None: not judged (e.g. a recovered recording)
    notes: str = ""
    seed: int | None = None
    extra: dict[str, str] = field(default_factory=dict)

    def replace(self, **changes: Any) -> EpisodeMeta:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_custom_data(self) -> dict[str, str]:
        data = {
            "task": self.task,
            "operator": self.operator,
            "success": "" if self.success is None else str(self.success).lower(),
            "notes": self.notes,
            "seed": "" if self.seed is None else str(self.seed),
        }
        data.update({f"extra.{k}": str(v) for k, v in self.extra.items()})
        return data

    @classmethod
    def from_custom_data(cls, data: dict[str, str] | None) -> EpisodeMeta:
        data = dict(data or {})
        success = data.get("success", "")
        seed = data.get("seed", "")
        return cls(
            task=data.get("task", ""),
            operator=data.get("operator", ""),
            success=None if success in ("", None) else success.lower() == "true",
            notes=data.get("notes", ""),
            seed=int(seed) if seed not in ("", None) else None,
            extra={k[6:]: v for k, v in data.items() if k.startswith("extra.")},
        )

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> EpisodeMeta:
        data = dict(data or {})
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in known})


# --- reading ------------------------------------------------------------------------------


@dataclass
class TopicMessages:
    msgtype: str
    log_ns: np.ndarray  # (N,) int64 bag record (receive) times, in file order
    messages: list  # decoded rosbags messages

    def __len__(self) -> int:
        return len(self.messages)

    def header_ns(self) -> np.ndarray:
        """(N,) int64 header stamps (raises BagError if the type has no header)."""
        try:
            return np.array([stamp_to_ns(m.header.stamp) for m in self.messages], dtype=np.int64)
        except AttributeError:
            raise BagError(f"{self.msgtype} messages have no header stamp") from None


@dataclass
class Episode:
    path: Path
    meta: EpisodeMeta
    start_ns: int
    duration_ns: int
    topics: dict[str, TopicMessages]
    message_counts: dict[str, int]  # per topic in the bag (including topics not decoded)

    def __getitem__(self, topic: str) -> TopicMessages:
        if topic not in self.topics:
            raise BagError(f"{self.path}: no messages on {topic} (topics: {sorted(self.message_counts)})")
        return self.topics[topic]

    def __contains__(self, topic: str) -> bool:
        return topic in self.topics and len(self.topics[topic]) > 0


def is_bag_dir(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.yaml").is_file() or (path.is_dir() and any(path.glob("*.mcap")))


def find_bags(paths: Iterable[str | Path]) -> list[Path]:
    """Expand each argument: a bag directory itself, or a folder whose sub-directories are bags (sorted)."""
    out: list[Path] = []
    for p in map(Path, paths):
        if is_bag_dir(p) or not p.is_dir():
            out.append(p)  # missing paths are reported by the reader, not dropped here
            continue
        subs = sorted(
            s for s in p.iterdir() if s.is_dir() and not s.name.endswith(UNREPAIRED_SUFFIX) and (is_bag_dir(s))
        )
        out.extend(subs)
    return out


def read_meta(path: str | Path) -> EpisodeMeta:
    """Episode metadata from metadata.yaml custom_data, else from the recorder's sidecar."""
    path = Path(path)
    meta_file = path / "metadata.yaml"
    if meta_file.is_file():
        info = yaml.safe_load(meta_file.read_text()) or {}
        custom = (info.get("rosbag2_bagfile_information") or {}).get("custom_data")
        if custom:
            return EpisodeMeta.from_custom_data(custom)
    sidecar = path / META_SIDECAR
    if sidecar.is_file():
        return EpisodeMeta.from_dict(yaml.safe_load(sidecar.read_text()))
    return EpisodeMeta()


def read_episode(path: str | Path, topics: Iterable[str] | None = None) -> Episode:
    """Decode a bag's messages (all topics, or only ``topics``); BagError with the reason if unreadable."""
    from rosbags.rosbag2 import Reader

    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: no such bag directory")
    if not path.is_dir():
        raise BagError(f"{path}: not a rosbag2 directory (expected metadata.yaml + .mcap)")
    if not (path / "metadata.yaml").is_file():
        hint = " (a killed recording? run: equidiff bags repair " + str(path) + ")" if any(path.glob("*.mcap")) else ""
        raise BagError(f"{path}: no metadata.yaml{hint}")
    typestore = rosbags_factory().typestore
    wanted = None if topics is None else set(topics)
    try:
        with Reader(path) as reader:
            counts = {t: info.msgcount for t, info in reader.topics.items()}
            conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
            out: dict[str, TopicMessages] = {}
            for conn in conns:
                out.setdefault(conn.topic, TopicMessages(conn.msgtype, np.zeros(0, np.int64), []))
            log: dict[str, list[int]] = {t: [] for t in out}
            # rosbags reads every topic when given no connections: only read what was asked for
            for conn, ts, raw in reader.messages(connections=conns) if conns else ():
                try:
                    msg = typestore.deserialize_cdr(raw, conn.msgtype)
                except Exception as err:  # rosbags raises several kinds on bad CDR
                    raise BagError(
                        f"{path}: undecodable {conn.msgtype} message on {conn.topic} at {ts} ns: {err}"
                    ) from err
                out[conn.topic].messages.append(msg)
                log[conn.topic].append(ts)
            for t, stamps in log.items():
                out[t].log_ns = np.asarray(stamps, dtype=np.int64)
            start, duration = reader.start_time, reader.duration
    except BagError:
        raise
    except Exception as err:  # ReaderError, struct.error, OSError on truncated/corrupt files
        raise BagError(
            f"{path}: unreadable bag ({type(err).__name__}: {err}); "
            f"if its recorder was killed, run: equidiff bags repair {path}"
        ) from err
    return Episode(
        path, read_meta(path), int(start) if counts and sum(counts.values()) else 0, int(duration), out, counts
    )


# --- repair -------------------------------------------------------------------------------


@dataclass
class RepairReport:
    path: Path  # the repaired bag
    original: Path | None  # where the damaged original was kept
    messages: dict[str, int]  # recovered messages per topic
    chunks: int
    dropped_bytes: int  # unreadable tail (incomplete chunk)
    reason: str  # what stopped the scan ('end of file', 'truncated chunk at byte N', ...)

    @property
    def total(self) -> int:
        return sum(self.messages.values())


@dataclass
class _Scan:
    schemas: dict[int, tuple[str, str, str]] = field(default_factory=dict)  # id -> (name, encoding, text)
    channels: dict[int, tuple[int, str, str, bytes]] = field(default_factory=dict)  # id -> (schema, topic, enc, meta)
    messages: list[tuple[int, int, bytes]] = field(default_factory=list)  # (channel, log_time, data)
    chunks: int = 0
    good_until: int = 0
    reason: str = "end of file"


def _string(buf: bytes, off: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", buf, off)
    return buf[off + 4 : off + 4 + n].decode(), off + 4 + n


def _records(buf: bytes, scan: _Scan, top_level: bool, base: int = 0) -> None:
    """Parse MCAP records of ``buf``; on the top level stop cleanly at a truncated record."""
    from rosbags.rosbag2.storage_mcap import decompress

    off = 0
    while off < len(buf):
        if off + 9 > len(buf):
            raise _Truncated(base + off, "truncated record header")
        op, size = buf[off], struct.unpack_from("<Q", buf, off + 1)[0]
        body_start, body_end = off + 9, off + 9 + size
        if body_end > len(buf):
            raise _Truncated(base + off, f"record 0x{op:02x} of {size} bytes cut off")
        body = buf[body_start:body_end]
        if op == 0x02:  # footer: the file was closed properly after all
            scan.good_until = base + body_end
            return
        if op == 0x03:
            (sid,) = struct.unpack_from("<H", body, 0)
            name, p = _string(body, 2)
            enc, p = _string(body, p)
            (n,) = struct.unpack_from("<I", body, p)
            scan.schemas[sid] = (name, enc, body[p + 4 : p + 4 + n].decode())
        elif op == 0x04:
            cid, sid = struct.unpack_from("<HH", body, 0)
            topic, p = _string(body, 4)
            enc, p = _string(body, p)
            (n,) = struct.unpack_from("<I", body, p)
            scan.channels[cid] = (sid, topic, enc, body[p + 4 : p + 4 + n])
        elif op == 0x05:
            cid, _seq, log_time = struct.unpack_from("<HIQ", body, 0)
            scan.messages.append((cid, log_time, body[22:]))
        elif op == 0x06:
            if not top_level:
                raise _Truncated(base + off, "nested chunk")
            _start, _end, usize, crc = struct.unpack_from("<QQQI", body, 0)
            comp, p = _string(body, 28)
            (csize,) = struct.unpack_from("<Q", body, p)
            try:
                inner = decompress(body[p + 8 : p + 8 + csize], comp, usize, crc)
            except Exception as err:
                raise _Truncated(base + off, f"corrupt chunk ({err})") from err
            before = (len(scan.messages), dict(scan.schemas), dict(scan.channels))
            try:
                _records(inner, scan, top_level=False)
            except _Truncated as err:  # a chunk is all or nothing
                del scan.messages[before[0] :]
                scan.schemas, scan.channels = before[1], before[2]
                raise _Truncated(base + off, f"corrupt chunk ({err.reason})") from None
            scan.chunks += 1
        if top_level:
            scan.good_until = base + body_end
        off = body_end


class _Truncated(Exception):
    def __init__(self, offset: int, reason: str):
        super().__init__(reason)
        self.offset, self.reason = offset, reason


def scan_mcap(mcap: Path) -> _Scan:
    """Every schema, channel and message of the complete records of a (possibly truncated) MCAP file."""
    data = mcap.read_bytes()
    if not data.startswith(MCAP_MAGIC):
        raise BagError(f"{mcap}: not an MCAP file (bad magic)")
    scan = _Scan(good_until=len(MCAP_MAGIC))
    try:
        _records(data[len(MCAP_MAGIC) :], scan, top_level=True, base=len(MCAP_MAGIC))
    except _Truncated as err:
        scan.reason = f"{err.reason} at byte {err.offset}"
    return scan


def _needs_repair(path: Path) -> str | None:
    """Why the bag needs repair, or None if it reads fine."""
    if not (path / "metadata.yaml").is_file():
        return "no metadata.yaml"
    try:
        read_episode(path, topics=())
        from rosbags.rosbag2 import Reader

        with Reader(path) as reader:
            for _ in reader.messages():
                pass
    except Exception as err:  # noqa: BLE001 - any failure to read means the bag needs repair; say why
        return str(err)
    return None


def close_derived_bag(
    writer, source: Path, target: Path, note: str, extra: dict[str, str] | None = None
) -> EpisodeMeta:
    """Close ``writer`` (the new bag at ``target``, made from the bag at ``source``) with the
    source's episode metadata plus ``note`` (what was done to it) and ``extra`` entries (replacing
    the source's of the same key), in metadata.yaml and the sidecar."""
    meta = read_meta(source)
    meta = meta.replace(
        notes=(meta.notes + " | " + note) if meta.notes else note, extra={**meta.extra, **(extra or {})}
    )
    for key, value in meta.to_custom_data().items():
        writer.set_custom_data(key, value)
    writer.close()
    (target / META_SIDECAR).write_text(yaml.safe_dump(meta.to_dict(), sort_keys=False))
    return meta


def repair_bag(path: str | Path, output: str | Path | None = None, force: bool = False) -> RepairReport | None:
    """Rebuild a readable bag from a killed recording; returns None if ``path`` is healthy (unless ``force``).

    ``output`` defaults to ``path`` itself: the damaged directory is renamed to
    ``<path>.unrepaired`` and the repaired bag takes its place.
    """
    from rosbags.rosbag2.storage_mcap import get_qos

    from .mcap_writer import open_bag_writer

    path = Path(path)
    if not path.is_dir():
        raise BagError(f"{path}: no such bag directory")
    mcaps = sorted(path.glob("*.mcap"))
    if len(mcaps) != 1:
        raise BagError(f"{path}: expected one .mcap file, found {len(mcaps)}")
    if not force and _needs_repair(path) is None:
        return None
    scan = scan_mcap(mcaps[0])
    size = mcaps[0].stat().st_size
    if not scan.messages:
        raise BagError(f"{path}: nothing recoverable ({scan.reason}; no complete chunk was written)")

    in_place = output is None or Path(output).resolve() == path.resolve()
    # In place: build next to it under the same name (the .mcap is named after its directory).
    staging = path.parent / f".{path.name}.repairing"
    target = staging / path.name if in_place else Path(output)
    if target.exists():
        raise BagError(f"{target} already exists: not overwriting")
    target.parent.mkdir(parents=True, exist_ok=True)
    typestore = rosbags_factory().typestore

    writer = open_bag_writer(target, chunk_max_age_s=float("inf"))
    conns, counts = {}, {}
    try:
        for cid, (sid, topic, enc, meta) in sorted(scan.channels.items()):
            name, _schema_enc, text = scan.schemas.get(sid, ("", "", ""))
            if not name:
                continue
            try:
                rihs = typestore.hash_rihs01(name)
            except KeyError:
                from rosbags.typesys import get_types_from_msg

                typestore.register(get_types_from_msg(text, name))
                rihs = typestore.hash_rihs01(name)
            conns[cid] = writer.add_connection(
                topic, name, msgdef=text, rihs01=rihs, serialization_format=enc, offered_qos_profiles=get_qos(meta)
            )
            counts[topic] = 0
        for cid, log_time, data in scan.messages:
            if cid in conns:
                writer.write(conns[cid], log_time, data)
                counts[conns[cid].topic] += 1
        lost = size - scan.good_until
        close_derived_bag(
            writer,
            path,
            target,
            f"recovered by equidiff bags repair: {sum(counts.values())} messages, {lost} trailing bytes lost",
        )
    except BaseException:
        writer.abort()
        shutil.rmtree(staging if in_place else target, ignore_errors=True)
        raise
    original = None
    if in_place:
        original = path.with_name(path.name + UNREPAIRED_SUFFIX)
        if original.exists():
            raise BagError(f"{original} already exists; repaired bag left at {target}")
        path.rename(original)
        target.rename(path)
        staging.rmdir()
        target = path
    return RepairReport(target, original, counts, scan.chunks, size - scan.good_until, scan.reason)
