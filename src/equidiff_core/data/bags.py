"""Reading episode bags (rosbag2 directories, MCAP storage) and repairing killed or damaged recordings.

``read_episode(path)`` reads the bag's .mcap through ``data.mcap_reader.iter_mcap`` (every chunk,
data-section and summary CRC checked), decodes the requested topics with rosbags' Jazzy
typestore and returns them per topic with their bag (receive) times; the dataset aligns
observations by *header* stamps, which the messages carry. A flipped bit raises
``BagIntegrityError`` naming the episode, the damaged chunk's topics and times; a bag written
without CRCs (rosbags' MCAP storage, this project's bags before) still reads, with
``Episode.integrity == "unchecked"``. ``EpisodeMeta`` is what the recorder stores in
metadata.yaml ``custom_data`` (and in the ``episode.yaml`` sidecar, so it survives a killed
recorder).

``repair_bag(path)`` handles the two ways a recording goes wrong on its own: the recorder
process dies (SIGKILL, power) before the MCAP summary and metadata.yaml are written, or bytes
of the file change afterwards (a bad disk, a bad copy). It reads every record it can, keeps
every message of every intact chunk (chunk CRCs checked), drops damaged chunks (the report
names their topics, times and message counts), stops at the first truncated record, and
rewrites a proper bag with the same topics, types and QoS. The damaged original is kept next
to it (``<name>.unrepaired``); nothing is lost.
"""

from __future__ import annotations

import dataclasses
import shutil
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ..wire.rosmsg import rosbags_factory, stamp_to_ns
from .mcap_reader import UNCHECKED, BagError, BagIntegrityError, DamagedChunk, McapScan, iter_mcap

META_SIDECAR = "episode.yaml"
UNREPAIRED_SUFFIX = ".unrepaired"


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
    log_ns: np.ndarray  # (N,) int64 bag record (receive) times, ascending
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
    integrity: str = UNCHECKED  # "checked": every chunk's CRC matched; "unchecked": stored without CRCs

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


def bag_mcap(path: Path) -> Path:
    """The one .mcap file of the bag directory ``path`` (BagError if there is not exactly one)."""
    mcaps = sorted(path.glob("*.mcap"))
    if len(mcaps) != 1:
        raise BagError(f"{path}: expected one .mcap file, found {len(mcaps)}")
    return mcaps[0]


def read_episode(path: str | Path, topics: Iterable[str] | None = None) -> Episode:
    """Decode a bag's messages (all topics, or only ``wire.topics``), every CRC checked: ``BagIntegrityError``
    for a damaged bag, ``BagError`` with the reason for any other unreadable one."""
    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: no such bag directory")
    if not path.is_dir():
        raise BagError(f"{path}: not a rosbag2 directory (expected metadata.yaml + .mcap)")
    if not (path / "metadata.yaml").is_file():
        hint = " (a killed recording? run: equidiff bags repair " + str(path) + ")" if any(path.glob("*.mcap")) else ""
        raise BagError(f"{path}: no metadata.yaml{hint}")
    mcap = bag_mcap(path)
    wanted = None if topics is None else set(topics)
    scan = McapScan(mcap)
    raw = _read_checked(path, scan, lambda topic: wanted is None or topic in wanted)
    typestore = rosbags_factory().typestore
    out: dict[str, TopicMessages] = {
        ch.topic: TopicMessages(ch.msgtype, np.zeros(0, np.int64), [])
        for ch in scan.channels.values()
        if wanted is None or ch.topic in wanted
    }
    log: dict[str, list[int]] = {t: [] for t in out}
    for channel, ts, data in raw:
        try:
            msg = typestore.deserialize_cdr(data, channel.msgtype)
        except Exception as err:  # rosbags raises several kinds on bad CDR
            raise BagError(
                f"{path}: undecodable {channel.msgtype} message on {channel.topic} at {ts} ns: {err}"
            ) from err
        out[channel.topic].messages.append(msg)
        log[channel.topic].append(ts)
    for t, stamps in log.items():
        # per topic in log-time order, as rosbags' reader gives them (file order may interleave)
        order = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
        out[t].log_ns = np.asarray(stamps, dtype=np.int64)[order]
        out[t].messages = [out[t].messages[k] for k in order]
    counts = {ch.topic: scan.counts.get(ch.topic, 0) for ch in scan.channels.values()}
    start = scan.start_ns or 0
    duration = (scan.end_ns - scan.start_ns) if scan.start_ns is not None else 0
    return Episode(path, read_meta(path), start, duration, out, counts, scan.integrity)


def verify_bag(path: str | Path) -> McapScan:
    """Read the bag's whole .mcap, checking every CRC, without decoding: its ``McapScan`` (``integrity``
    says whether there was anything to check); ``BagIntegrityError`` / ``BagError`` like ``read_episode``."""
    path = Path(path)
    scan = McapScan(bag_mcap(path) if path.is_dir() else path)
    _read_checked(path, scan, lambda topic: False)
    return scan


def _read_checked(path: Path, scan: McapScan, keep: Callable[[str], bool]) -> list:
    """The (channel, log_ns, data) of ``scan.path`` whose topic ``keep`` accepts, every CRC checked; errors
    name the bag and what to run."""
    try:
        return [m for m in iter_mcap(scan.path, scan) if keep(m[0].topic)]
    except BagIntegrityError as err:
        raise BagIntegrityError(f"{err}; equidiff bags repair {path} keeps the intact chunks", err.damaged) from None
    except BagError as err:
        raise BagError(
            f"unreadable bag ({err}); if its recorder was killed, run: equidiff bags repair {path}"
        ) from None


# --- repair -------------------------------------------------------------------------------


@dataclass
class RepairReport:
    path: Path  # the repaired bag
    original: Path | None  # where the damaged original was kept
    messages: dict[str, int]  # recovered messages per topic
    chunks: int
    dropped_bytes: int  # unreadable tail (incomplete chunk)
    reason: str  # what stopped the scan ('end of file', 'truncated ... at byte N', a CRC mismatch ...)
    damaged: list[DamagedChunk] = field(default_factory=list)  # chunks dropped for a CRC mismatch
    orphaned: int = 0  # messages of intact chunks lost because their channel was defined in a damaged one

    @property
    def total(self) -> int:
        return sum(self.messages.values())

    def dropped(self) -> list[str]:
        """One line per dropped chunk: its topics, time range and message counts."""
        lines = [f"dropped {d.describe()}" for d in self.damaged]
        if self.orphaned:
            lines.append(f"dropped {self.orphaned} later messages whose channel was defined in a damaged chunk")
        return lines


@dataclass
class McapSalvage(McapScan):
    """What a tolerant read of a (possibly truncated or damaged) .mcap recovered, for repair."""

    messages: list[tuple] = field(default_factory=list)  # (McapChannel, log_time_ns, data) in file order

    @property
    def reason(self) -> str:
        return self.stopped or ("end of file" if self.complete else "end of file without a footer")


def scan_mcap(mcap: Path) -> McapSalvage:
    """Every message of every intact chunk of a (possibly truncated or damaged) MCAP file, and what
    was dropped (``damaged``, ``stopped``); BagError only if it is not an MCAP file at all."""
    salvage = McapSalvage(Path(mcap))
    salvage.messages = list(iter_mcap(mcap, salvage, tolerant=True))
    return salvage


def _needs_repair(path: Path) -> str | None:
    """Why the bag needs repair, or None if it reads fine (every CRC checked, rosbags opens it)."""
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
    """Rebuild a readable bag from a killed or damaged recording; returns None if ``path`` is healthy
    (unless ``force``). Damaged chunks are dropped and listed in the report (``RepairReport.dropped``).

    ``output`` defaults to ``path`` itself: the damaged directory is renamed to
    ``<path>.unrepaired`` and the repaired bag takes its place.
    """
    from rosbags.rosbag2.storage_mcap import parse_qos

    from .mcap_writer import open_bag_writer

    path = Path(path)
    if not path.is_dir():
        raise BagError(f"{path}: no such bag directory")
    mcap = bag_mcap(path)
    need = _needs_repair(path)
    if not force and need is None:
        return None
    scan = scan_mcap(mcap)
    size = mcap.stat().st_size
    if not scan.messages:
        raise BagError(f"{path}: nothing recoverable ({scan.reason}; no intact chunk was written)")

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
        for channel in sorted({ch.id: ch for ch, _, _ in scan.messages}.values(), key=lambda ch: ch.id):
            try:
                rihs = typestore.hash_rihs01(channel.msgtype)
            except KeyError:
                from rosbags.typesys import get_types_from_msg

                typestore.register(get_types_from_msg(channel.schema_text, channel.msgtype))
                rihs = typestore.hash_rihs01(channel.msgtype)
            qos = channel.metadata.get("offered_qos_profiles", "")
            conns[channel.id] = writer.add_connection(
                channel.topic,
                channel.msgtype,
                msgdef=channel.schema_text,
                rihs01=rihs,
                serialization_format=channel.message_encoding,
                offered_qos_profiles=parse_qos(qos) if qos else [],
            )
            counts[channel.topic] = 0
        for channel, log_time, data in scan.messages:
            writer.write(conns[channel.id], log_time, data)
            counts[channel.topic] += 1
        lost = size - scan.good_until
        dropped = f", {len(scan.damaged)} damaged chunks dropped" if scan.damaged else ""
        close_derived_bag(
            writer,
            path,
            target,
            f"recovered by equidiff bags repair: {sum(counts.values())} messages, {lost} trailing bytes lost{dropped}",
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
    reason = scan.stopped or (need if scan.complete and need else scan.reason)
    return RepairReport(
        target, original, counts, scan.chunks, size - scan.good_until, reason, scan.damaged, scan.orphaned
    )
