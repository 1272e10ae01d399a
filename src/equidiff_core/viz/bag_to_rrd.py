"""Recorded episodes (rosbag2 directories) -> rerun recordings, without a ROS install.

Same entity paths and blueprint as the live ``equidiff viz``. Two layouts:

* all in one (default): one recording in ``out.rrd``; each bag is an ``episode`` (sequence
  timeline) and ``episode_time`` counts from each episode's first message, so episodes can
  be overlaid or stepped through;
* ``per_episode``: one ``<bag name>.rrd`` per bag in the directory ``out``.

The all-in-one recording can also go straight to a viewer (``spawn`` / ``connect``) instead
of a file.

Messages are streamed in file order through ``data.mcap_reader.iter_mcap`` (every CRC checked; not
collected per episode as ``equidiff_core.data.bags.read_episode`` does) so a long episode with raw
clouds does not have to fit in memory. An unreadable or damaged bag is reported and skipped
(a damaged one once it was read: what came before the damage is already in the recording);
the others are still converted.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from ..config import LabConfig
from ..data.bags import bag_mcap
from ..data.mcap_reader import BagIntegrityError, iter_mcap
from ..runtime.output_files import distinct_names, staged_output, unique_paths
from ..wire.rosmsg import rosbags_factory
from ..wire.topics import camera_of_color_topic
from .logger import TOPICS_HANDLED, RerunLogger
from .recording_setup import APPLICATION_ID, VizConfig, default_blueprint, open_recording


class BagConversionError(RuntimeError):
    """A bag that cannot be converted (missing, not a rosbag2 directory, corrupt)."""


@dataclass
class EpisodeResult:
    bag: Path
    output: Path | None
    messages: int = 0  # messages read from the bag on the topics shown
    logged: dict[str, int] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    dropped: dict[str, int] = field(default_factory=dict)
    error: str | None = None  # why the bag was skipped (None: converted)


@dataclass
class ConversionReport:
    episodes: list[EpisodeResult]
    outputs: list[Path]
    seconds: float

    @property
    def ok(self) -> bool:
        return all(e.error is None for e in self.episodes) and bool(self.episodes)


def expand_bag_paths(paths: Iterable[str | Path]) -> list[Path]:
    """Each argument is a bag directory, or a folder whose sub-directories are bags (sorted by name)."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir() and not (p / "metadata.yaml").is_file() and not any(p.glob("*.mcap")):
            subs = sorted(s for s in p.iterdir() if s.is_dir() and (s / "metadata.yaml").is_file())
            if subs:
                out.extend(subs)
                continue
        out.append(p)  # missing / malformed paths are reported per bag, not silently dropped
    return out


def episode_info(bag: Path) -> dict[str, str]:
    """The bag's metadata.yaml ``custom_data`` (task, operator, success, notes, seed ...), plus its name."""
    info = {"bag": bag.name}
    try:
        meta = yaml.safe_load((bag / "metadata.yaml").read_text()) or {}
        custom = (meta.get("rosbag2_bagfile_information") or {}).get("custom_data") or {}
        info.update({str(k): str(v) for k, v in custom.items()})
    except (OSError, yaml.YAMLError, AttributeError):
        pass  # the reader reports unreadable metadata with a proper message
    return info


def _wanted(topic: str, config: VizConfig) -> bool:
    if topic in TOPICS_HANDLED:
        return True
    if camera_of_color_topic(topic) is not None:
        return config.images
    return config.clouds and topic.startswith("/cameras/") and topic.endswith("/points")


def _log_bag(logger: RerunLogger, bag: Path, index: int, result: EpisodeResult) -> None:
    from rosbags.rosbag2 import Reader

    if not bag.exists():
        raise BagConversionError(f"{bag}: no such bag directory")
    if not bag.is_dir() or not (bag / "metadata.yaml").is_file():
        raise BagConversionError(
            f"{bag}: not a rosbag2 directory (expected metadata.yaml + .mcap); "
            f"a killed recording can be recovered with: equidiff bags repair {bag}"
        )
    typestore = rosbags_factory().typestore
    try:
        with Reader(bag) as reader:  # metadata.yaml's start time (the .mcap is read below, CRCs checked)
            start_ns = reader.start_time if reader.message_count else 0
        logger.begin_episode(index, start_ns, episode_info(bag))
        # streamed: a CRC mismatch raises BagIntegrityError (naming the chunk) once the file was read
        for channel, receive_ns, raw in iter_mcap(bag_mcap(bag)):
            if not _wanted(channel.topic, logger.config):
                continue
            result.messages += 1
            try:
                msg = typestore.deserialize_cdr(raw, channel.msgtype)
            except Exception as err:  # noqa: BLE001 - rosbags raises several kinds on bad CDR: drop one message
                logger._drop(f"undecodable {channel.topic}", err)
                continue
            logger.log_message(channel.topic, msg, receive_ns)
    except BagIntegrityError as err:
        raise BagConversionError(
            f"{bag}: damaged bag: {err}; equidiff bags repair {bag} keeps the intact chunks"
        ) from err
    except BagConversionError:
        raise
    except Exception as err:  # ReaderError, struct.error, OSError on truncated/corrupt files
        raise BagConversionError(
            f"{bag}: unreadable bag ({type(err).__name__}: {err}); if its recorder "
            f"was killed, run: equidiff bags repair {bag}"
        ) from err


def convert_bags(
    bags: Iterable[str | Path],
    out: str | Path | None,
    lab: LabConfig,
    config: VizConfig = VizConfig(),
    per_episode: bool = False,
    *,
    spawn: bool = False,
    connect: str | None = None,
    force: bool = False,
) -> ConversionReport:
    """Convert bags to .rrd (``out`` a file, or a directory with ``per_episode``), or stream them to a viewer
    (``spawn`` / ``connect``, one recording); never raises because of one bad bag. ``out`` is written beside
    itself and renamed into place once complete (``runtime.output_files.staged_output``): an existing one raises
    ``OutputExistsError`` unless ``force``, and is kept when nothing could be converted."""
    t0 = time.perf_counter()
    bags = unique_paths(expand_bag_paths(bags))
    out = Path(out) if out is not None else None
    results: list[EpisodeResult] = []
    outputs: list[Path] = []
    if per_episode:
        if out is None or out.suffix == ".rrd":
            raise BagConversionError(f"--per-episode writes one file per bag: give a directory, not {out}")
        with staged_output(out, force=force) as staged:
            staged.path.mkdir()
            for index, (bag, name) in enumerate(zip(bags, distinct_names(bags), strict=True)):
                target = out / f"{name}.rrd"
                result = EpisodeResult(bag, target)
                rec = open_recording(
                    recording_id=bag.name,
                    save=staged.path / target.name,
                    application_id=APPLICATION_ID,
                    blueprint=default_blueprint([c.name for c in lab.cameras] if config.images else ()),
                )
                logger = RerunLogger(rec, lab, config)
                logger.log_static_scene(static_cameras=False)
                try:
                    _log_bag(logger, bag, index, result)
                except BagConversionError as err:
                    result.error, result.output = str(err), None
                _finish(rec)
                if result.error is not None:
                    (staged.path / target.name).unlink(missing_ok=True)  # no half-empty .rrd: not an episode
                else:
                    outputs.append(target)
                result.logged = dict(logger.logged)
                result.dropped, result.warnings = dict(logger.errors), logger.warnings
                results.append(result)
            if not outputs:
                staged.discard()
        return ConversionReport(results, outputs, time.perf_counter() - t0)

    if out is not None and out.suffix != ".rrd":
        raise BagConversionError(f"output must be a .rrd file (or use --per-episode with a directory), got {out}")
    name = out.stem if out is not None else (bags[0].name if len(bags) == 1 else "episodes")
    with staged_output(out, force=force) if out is not None else nullcontext() as staged:
        rec = open_recording(
            recording_id=name,
            save=staged.path if staged is not None else None,
            spawn=spawn,
            connect=connect,
            application_id=APPLICATION_ID,
            blueprint=default_blueprint([c.name for c in lab.cameras] if config.images else ()),
        )
        logger = RerunLogger(rec, lab, config)
        logger.log_static_scene(static_cameras=False)
        for index, bag in enumerate(bags):
            result = EpisodeResult(bag, out)
            before_logged, before_dropped = logger.logged.copy(), logger.errors.copy()
            logger._voxel_size_checked = False  # each bag may come from another lab set-up
            before_warnings = len(logger.warnings)
            try:
                _log_bag(logger, bag, index, result)
            except BagConversionError as err:
                result.error, result.output = str(err), None
            result.logged = dict(logger.logged - before_logged)
            result.dropped = dict(logger.errors - before_dropped)
            result.warnings = logger.warnings[before_warnings:]
            results.append(result)
        _finish(rec)
        if staged is not None:
            if any(r.error is None for r in results):
                outputs.append(out)
            else:
                staged.discard()  # nothing converted: no file that looks like a recording
    return ConversionReport(results, outputs, time.perf_counter() - t0)


def _finish(rec: Any) -> None:
    rec.flush()
    rec.disconnect()
