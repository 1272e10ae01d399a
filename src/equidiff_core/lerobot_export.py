"""Episode bags -> a LeRobot dataset in LeRobot's v3.0 layout, without LeRobot installed.

Why write it ourselves: LeRobot 0.5+ needs Python >= 3.12 and torch < 2.12, and cannot share
this venv (Python 3.11, torch 2.13). So this module writes the files LeRobot 0.6.1's own writer
writes (``lerobot.datasets.dataset_writer`` / ``dataset_metadata``; checked against a dataset
made by ``LeRobotDataset.create`` + ``save_episode`` + ``finalize``), with pyarrow and PyAV, and
``test_lerobot_export.py`` loads the result with LeRobot itself in a venv of its own.

Layout (v3.0: many episodes per file)::

    meta/info.json                                   features, fps, totals, path templates
    meta/stats.json                                  per feature: min max mean std count q01 q10 q50 q90 q99
    meta/tasks.parquet                               task (index) -> task_index
    meta/episodes/chunk-000/file-000.parquet         one row per episode: length, tasks, frame range,
                                                     data and video file indices, video from/to
                                                     timestamps, per-episode stats (stats/<key>/<stat>)
    data/chunk-000/file-000.parquet                  one row per frame (a new file past 100 MB)
    videos/<key>/chunk-000/file-000.mp4              one stream per camera, episodes back to back
                                                     (a new file past 200 MB)

One frame per observation, the dataset's own alignment (``dataset.load_episodes``: /voxels
header stamps, nearest TCP pose and finger width, the commanded target in effect):

* ``observation.state`` float32 (10,): measured TCP pose + width, ``[x, y, z, r6, width]``;
* ``action`` float32 (10,): the commanded absolute target in effect at the frame;
* ``observation.images.<camera>`` video (H, W, 3): the camera's recorded JPEG nearest the frame's
  stamp (within ``image_tolerance_s``), decoded and encoded to AV1 with LeRobot's default
  encoder settings (libsvtav1, yuv420p, GOP 2, CRF 30, preset 12);
* ``observation.voxels`` uint8 (4, R, R, R), optional: the occupancy + RGB grid;
* ``timestamp`` = frame_index / fps (LeRobot's convention: its video decoder looks frames up at
  exactly these times), ``frame_index``, ``episode_index``, ``index``, ``task_index``.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from .bags import BagError, read_episode
from .cameras.color import ImageError, image_from_msg
from .dataset import DatasetConfig, EpisodeArrays, load_episodes
from .geometry import ACTION_DIM
from .rosmsg import NS_PER_S
from .topics import camera_color_topic, camera_of_color_topic

CODEBASE_VERSION = "v3.0"
CHUNK_FILE = "chunk-{chunk_index:03d}/file-{file_index:03d}"
DATA_PATH = "data/" + CHUNK_FILE + ".parquet"
VIDEO_PATH = "videos/{video_key}/" + CHUNK_FILE + ".mp4"
EPISODES_PATH = "meta/episodes/" + CHUNK_FILE + ".parquet"
TASKS_PATH = "meta/tasks.parquet"
IMAGE_KEY = "observation.images.{camera}"
ACTION_NAMES = ["x", "y", "z", "r00", "r01", "r02", "r10", "r11", "r12", "gripper_width"]
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)  # LeRobot's DEFAULT_QUANTILES
MiB = 1024**2
# SVT-AV1 prints its whole configuration to stderr for each encoder it opens; errors only
os.environ.setdefault("SVT_LOG", "1")


class ExportError(RuntimeError):
    """Nothing can be exported (no usable episode, mixed rates, output exists, images missing)."""


@dataclass(frozen=True)
class VideoEncoding:
    """LeRobot 0.6.1's RGB encoder defaults (``lerobot.configs.video.VideoEncoderConfig``)."""

    vcodec: str = "libsvtav1"
    pix_fmt: str = "yuv420p"
    g: int = 2  # a key frame every 2 frames: random access for training
    crf: int = 30
    preset: int = 12
    fast_decode: int = 0

    def codec_options(self) -> dict[str, str]:
        """What LeRobot's ``get_codec_options(as_strings=True)`` passes to PyAV for this codec."""
        opts = {"g": str(self.g), "crf": str(self.crf), "preset": str(self.preset)}
        if self.vcodec == "libsvtav1":
            opts["svtav1-params"] = f"fast-decode={max(0, min(2, self.fast_decode))}"
        elif self.fast_decode:
            opts["tune"] = "fastdecode"
        return opts

    def info(self, stream) -> dict[str, Any]:
        """The feature's ``info`` block in info.json, as ``lerobot.datasets.video_utils.get_video_info``."""
        return {
            "video.height": stream.height,
            "video.width": stream.width,
            "video.codec": stream.codec_context.codec.canonical_name,
            "video.pix_fmt": self.pix_fmt,
            "video.fps": int(stream.base_rate or stream.average_rate),
            "video.channels": 3,
            "has_audio": False,
            "video.g": self.g,
            "video.crf": self.crf,
            "video.preset": self.preset,
            "video.fast_decode": self.fast_decode,
            "video.video_backend": "pyav",
            "video.extra_options": {},
            "is_depth_map": False,
        }


@dataclass(frozen=True)
class ExportOptions:
    voxels: bool = True  # observation.voxels (~1 MiB a frame before compression)
    images: bool = True  # observation.images.<camera> from the bags' colour images
    only_successful: bool = False
    robot_type: str = "franka_fr3"
    image_tolerance_s: float | None = None  # None: half an observation period
    video: VideoEncoding = field(default_factory=VideoEncoding)
    chunks_size: int = 1000  # files per chunk directory
    data_files_size_in_mb: int = 100
    video_files_size_in_mb: int = 200


@dataclass
class ExportReport:
    out: Path
    episodes: int
    frames: int
    fps: int
    tasks: list[str]
    cameras: list[str]
    skipped: list[tuple[str, str]]  # (bag, why)
    seconds: float

    def summary(self) -> dict[str, Any]:
        return {
            "out": str(self.out),
            "format": CODEBASE_VERSION,
            "episodes": self.episodes,
            "frames": self.frames,
            "fps": self.fps,
            "tasks": self.tasks,
            "cameras": self.cameras,
            "skipped": len(self.skipped),
            "seconds": round(self.seconds, 1),
        }


# --- statistics (lerobot.datasets.compute_stats) ---------------------------------------------


def feature_stats(x: np.ndarray, axis: int | tuple[int, ...] = 0, keepdims: bool = False) -> dict[str, np.ndarray]:
    """min, max, mean, std, count and LeRobot's quantiles over ``axis`` (float64)."""
    x = np.asarray(x, dtype=np.float64)
    count = x.shape[0]
    stats = {
        "min": x.min(axis=axis, keepdims=keepdims),
        "max": x.max(axis=axis, keepdims=keepdims),
        "mean": x.mean(axis=axis, keepdims=keepdims),
        "std": x.std(axis=axis, keepdims=keepdims),
        "count": np.array([count]),
    }
    for q in QUANTILES:
        stats[f"q{round(q * 100):02d}"] = np.quantile(x, q, axis=axis, keepdims=keepdims)
    return stats


def channel_stats(frames: np.ndarray, scale: float = 255.0) -> dict[str, np.ndarray]:
    """Per-channel stats of (T, C, ...) uint8 frames in [0, 1], shaped (C, 1, ...) as LeRobot keeps image stats."""
    axes = (0, *range(2, frames.ndim))
    stats = feature_stats(frames.astype(np.float32) / scale, axis=axes, keepdims=True)
    return {k: (v if k == "count" else v[0]) for k, v in stats.items()}


def merge_stats(parts: Sequence[dict[str, dict[str, np.ndarray]]]) -> dict[str, dict[str, np.ndarray]]:
    """Episode stats -> dataset stats as ``lerobot.datasets.compute_stats.aggregate_stats``: count-weighted
    means and quantiles, pooled variance, overall min/max."""
    out = {}
    for key in parts[0]:
        each = [p[key] for p in parts]
        n = np.array([s["count"][0] for s in each], dtype=np.float64)
        w = n / n.sum()

        def wsum(name: str, w=w, each=each) -> np.ndarray:
            return sum(wi * np.asarray(s[name], dtype=np.float64) for wi, s in zip(w, each))

        mean = wsum("mean")
        var = sum(wi * (np.asarray(s["std"]) ** 2 + (np.asarray(s["mean"]) - mean) ** 2) for wi, s in zip(w, each))
        merged = {
            "min": np.min([s["min"] for s in each], axis=0),
            "max": np.max([s["max"] for s in each], axis=0),
            "mean": mean,
            "std": np.sqrt(var),
            "count": np.array([int(n.sum())]),
        }
        for q in QUANTILES:
            name = f"q{round(q * 100):02d}"
            merged[name] = wsum(name)
        out[key] = merged
    return out


def _jsonable(stats: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, Any]]:
    return {k: {s: np.asarray(v).tolist() for s, v in d.items()} for k, d in stats.items()}


# --- files that roll over (lerobot.datasets.utils.update_chunk_file_indices) -----------------


def next_chunk_file(chunk_index: int, file_index: int, chunks_size: int) -> tuple[int, int]:
    return (chunk_index + 1, 0) if file_index == chunks_size - 1 else (chunk_index, file_index + 1)


class _DataFiles:
    """The frame table, many episodes per parquet file; a new file once one passes the size limit."""

    def __init__(self, root: Path, schema: pa.Schema, limit_mb: float, chunks_size: int):
        self.root, self.schema, self.limit_mb, self.chunks_size = root, schema, limit_mb, chunks_size
        self.chunk = self.file = 0
        self.writer: pq.ParquetWriter | None = None
        self.path: Path | None = None

    def write(self, table: pa.Table) -> tuple[int, int]:
        if self.writer is not None and self.path.stat().st_size / MiB >= self.limit_mb:
            self.close()
            self.chunk, self.file = next_chunk_file(self.chunk, self.file, self.chunks_size)
        if self.writer is None:
            self.path = self.root / DATA_PATH.format(chunk_index=self.chunk, file_index=self.file)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.writer = pq.ParquetWriter(self.path, self.schema, compression="snappy", use_dictionary=True)
        self.writer.write_table(table.cast(self.schema))
        return self.chunk, self.file

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None


class _VideoFiles:
    """One camera's frames as mp4 files, episodes back to back at exactly 1/fps per frame, so the
    k-th frame of an episode that starts at ``from_timestamp`` plays at ``from_timestamp + k/fps``."""

    def __init__(self, root: Path, key: str, fps: int, encoding: VideoEncoding, limit_mb: float, chunks_size: int):
        self.root, self.key, self.fps, self.encoding = root, key, fps, encoding
        self.limit_mb, self.chunks_size = limit_mb, chunks_size
        self.chunk = self.file = 0
        self.container = self.stream = self.path = None
        self.frames_in_file = 0
        self.info: dict[str, Any] | None = None
        self.shape: tuple[int, int, int] | None = None

    def _open(self, width: int, height: int) -> None:
        self.path = self.root / VIDEO_PATH.format(video_key=self.key, chunk_index=self.chunk, file_index=self.file)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.container = av.open(str(self.path), "w")
        self.stream = self.container.add_stream(
            self.encoding.vcodec, rate=self.fps, options=self.encoding.codec_options()
        )
        self.stream.pix_fmt = self.encoding.pix_fmt
        self.stream.width, self.stream.height = width, height
        self.stream.time_base = Fraction(1, self.fps)
        self.frames_in_file = 0
        if self.info is None:
            self.info = self.encoding.info(self.stream)
            self.shape = (height, width, 3)

    def add_episode(self, frames: Iterable[np.ndarray]) -> dict[str, Any]:
        """Append one episode's RGB frames (H, W, 3); returns its LeRobot episode-metadata columns."""
        if self.container is not None and self.path.stat().st_size / MiB >= self.limit_mb:
            self.close()
            self.chunk, self.file = next_chunk_file(self.chunk, self.file, self.chunks_size)
        start = None
        for rgb in frames:
            if self.container is None:
                self._open(rgb.shape[1], rgb.shape[0])
            if start is None:
                start = self.frames_in_file
            if (rgb.shape[1], rgb.shape[0]) != (self.stream.width, self.stream.height):
                raise ExportError(
                    f"{self.key}: a {rgb.shape[1]}x{rgb.shape[0]} image in a {self.stream.width}x"
                    f"{self.stream.height} video (one resolution per camera)"
                )
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
            frame.pts = self.frames_in_file
            self.frames_in_file += 1
            for packet in self.stream.encode(frame):
                self.container.mux(packet)
        start = self.frames_in_file if start is None else start
        prefix = f"videos/{self.key}/"
        return {
            prefix + "chunk_index": self.chunk,
            prefix + "file_index": self.file,
            prefix + "from_timestamp": start / self.fps,
            prefix + "to_timestamp": self.frames_in_file / self.fps,
        }

    def close(self) -> None:
        if self.container is not None:
            for packet in self.stream.encode():
                self.container.mux(packet)
            self.container.close()
            self.container = None


# --- the frames of one episode ----------------------------------------------------------------


def bag_cameras(ep: EpisodeArrays) -> list[str]:
    """Cameras with a recorded colour-image topic in the episode's bag (sorted)."""
    from rosbags.rosbag2 import Reader

    if not (Path(ep.path) / "metadata.yaml").is_file():
        return []  # a packed episode: no images kept
    with Reader(ep.path) as reader:
        return sorted({cam for t, info in reader.topics.items() if info.msgcount and (cam := camera_of_color_topic(t))})


def matched_images(ep: EpisodeArrays, cameras: Sequence[str], tolerance_ns: int) -> dict[str, list]:
    """Per camera, the CompressedImage message nearest each observation's stamp (header stamps).

    Raises ExportError naming the frame when a camera has no image within the tolerance."""
    episode = read_episode(ep.path, topics=[camera_color_topic(c) for c in cameras])
    out = {}
    for cam in cameras:
        topic = camera_color_topic(cam)
        if topic not in episode:
            raise ExportError(f"{ep.path}: no colour images of camera {cam!r} ({topic})")
        msgs = episode[topic]
        stamps = msgs.header_ns()
        order = np.argsort(stamps, kind="stable")
        stamps = stamps[order]
        after = np.minimum(np.searchsorted(stamps, ep.stamps_ns), len(stamps) - 1)
        before = np.maximum(after - 1, 0)
        closer_before = np.abs(stamps[before] - ep.stamps_ns) <= np.abs(stamps[after] - ep.stamps_ns)
        nearest = np.where(closer_before, before, after)
        gap = np.abs(stamps[nearest] - ep.stamps_ns)
        if np.any(gap > tolerance_ns):
            i = int(np.argmax(gap > tolerance_ns))
            raise ExportError(
                f"{ep.path}: camera {cam!r} has no image within {tolerance_ns / 1e6:.0f} ms of observation {i} "
                f"(nearest {gap[i] / 1e6:.0f} ms away)"
            )
        out[cam] = [msgs.messages[order[j]] for j in nearest]
    return out


def _decoded(messages: list, where: str) -> Iterable[np.ndarray]:
    for i, msg in enumerate(messages):
        try:
            yield image_from_msg(msg)[0]
        except ImageError as err:
            raise ExportError(f"{where}: frame {i}: {err}") from err


# --- the schema ---------------------------------------------------------------------------------


def _features(voxel_resolution: int | None) -> dict[str, dict]:
    """The frame table's features (the cameras' video features join once their first frame is known)."""
    axes = {"axes": ACTION_NAMES}
    features: dict[str, dict] = {
        "observation.state": {"dtype": "float32", "shape": [ACTION_DIM], "names": axes},
        "action": {"dtype": "float32", "shape": [ACTION_DIM], "names": axes},
    }
    if voxel_resolution is not None:
        R = voxel_resolution
        features["observation.voxels"] = {"dtype": "uint8", "shape": [4, R, R, R], "names": ["channel", "x", "y", "z"]}
    for name, dtype in (
        ("timestamp", "float32"),
        ("frame_index", "int64"),
        ("episode_index", "int64"),
        ("index", "int64"),
        ("task_index", "int64"),
    ):
        features[name] = {"dtype": dtype, "shape": [1], "names": None}
    return features


def _hf_feature(ft: dict) -> dict:
    """A LeRobot feature as Hugging Face ``datasets`` writes it into the parquet schema metadata."""
    shape = ft["shape"]
    if shape == [1]:
        return {"dtype": ft["dtype"], "_type": "Value"}
    if len(shape) == 1:
        return {"feature": {"dtype": ft["dtype"], "_type": "Value"}, "length": shape[0], "_type": "List"}
    return {"shape": shape, "dtype": ft["dtype"], "_type": f"Array{len(shape)}D"}


def _arrow_schema(features: dict[str, dict]) -> pa.Schema:
    types = {"float32": pa.float32(), "int64": pa.int64(), "uint8": pa.uint8()}
    fields = []
    for key, ft in features.items():
        if ft["dtype"] == "video":
            continue
        t, shape = types[ft["dtype"]], ft["shape"]
        if shape == [1]:
            fields.append(pa.field(key, t))
        elif len(shape) == 1:
            fields.append(pa.field(key, pa.list_(t, shape[0])))
        else:
            for _ in shape:
                t = pa.list_(t)
            fields.append(pa.field(key, t))
    hf = {"info": {"features": {k: _hf_feature(ft) for k, ft in features.items() if ft["dtype"] != "video"}}}
    return pa.schema(fields, metadata={"huggingface": json.dumps(hf)})


def _nested(array: np.ndarray) -> pa.Array:
    """(N, d1, ..., dk) array -> N rows of k-deep nested lists (Hugging Face ``ArrayND`` storage)."""
    values = pa.array(array.reshape(-1))
    for size in reversed(array.shape[1:]):
        values = pa.FixedSizeListArray.from_arrays(values, size)
    return values


def _tasks_table(tasks: dict[str, int]) -> pa.Table:
    """meta/tasks.parquet as pandas writes LeRobot's DataFrame (index ``task``, column ``task_index``)."""
    pandas_meta = {
        "index_columns": ["task"],
        "column_indexes": [
            {"name": None, "field_name": None, "pandas_type": "unicode", "numpy_type": "object", "metadata": None}
        ],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64"},
            {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object"},
        ],
        "attributes": {},
        "creator": {"library": "pyarrow", "version": pa.__version__},
    }
    for col in pandas_meta["columns"]:
        col["metadata"] = None
    return pa.table(
        {"task_index": pa.array(list(tasks.values()), pa.int64()), "task": pa.array(list(tasks), pa.string())},
        metadata={"pandas": json.dumps(pandas_meta)},
    )


# --- the export -------------------------------------------------------------------------------


def export_lerobot(
    bags: Iterable[str | Path],
    out: str | Path,
    options: ExportOptions = ExportOptions(),
    dataset_config: DatasetConfig | None = None,
    log: Callable[[str], None] = print,
) -> ExportReport:
    """Write ``out`` (a new directory) from the bags; bags that cannot be used are skipped and reported."""
    t0 = time.perf_counter()
    dataset_config = dataset_config or DatasetConfig()
    out = Path(out)
    if out.exists():
        raise ExportError(f"{out} exists; not overwriting")
    episodes, skipped = load_episodes(bags, dataset_config, log=log)
    skipped = [(str(p), str(why)) for p, why in skipped]
    if options.only_successful:
        episodes = [ep for ep in episodes if ep.meta.success]
    if not episodes:
        raise ExportError("no usable episodes")
    rates = {round(NS_PER_S / ep.obs_period_ns, 3) for ep in episodes}
    fps = round(next(iter(rates)))
    if any(abs(r - fps) > 0.05 * fps for r in rates):
        raise ExportError(f"episodes have different observation rates {sorted(rates)}; LeRobot datasets have one fps")
    tolerance_ns = int((options.image_tolerance_s or 0.5 / fps) * NS_PER_S)

    cameras: list[str] = []
    if options.images:
        per_bag = {str(ep.path): bag_cameras(ep) for ep in episodes}
        cameras = sorted(set().union(*per_bag.values()))
        lacking = {p: sorted(set(cameras) - set(c)) for p, c in per_bag.items() if set(c) != set(cameras)}
        if lacking:
            raise ExportError(
                "every episode needs every camera's images; missing: "
                + "; ".join(f"{p}: {c}" for p, c in lacking.items())
                + " (export without images: --no-images)"
            )
        if not cameras:
            log("no colour images in these bags (recorded before record_images existed?): exporting without images")

    R = dataset_config.resolution
    features = _features(R if options.voxels else None)
    schema = _arrow_schema(features)

    out.mkdir(parents=True)
    data = _DataFiles(out, schema, options.data_files_size_in_mb, options.chunks_size)
    videos = {
        cam: _VideoFiles(
            out,
            IMAGE_KEY.format(camera=cam),
            fps,
            options.video,
            options.video_files_size_in_mb,
            options.chunks_size,
        )
        for cam in cameras
    }
    tasks: dict[str, int] = {}
    rows: list[dict[str, Any]] = []
    all_stats: list[dict] = []
    index = 0
    try:
        for ep in episodes:  # one episode's images in memory at a time
            try:
                images = matched_images(ep, cameras, tolerance_ns) if cameras else {}
            except (ExportError, BagError) as err:
                skipped.append((str(ep.path), str(err)))
                log(f"skipped: {err}")
                continue
            e = len(rows)
            task = ep.meta.task or "unknown"
            task_index = tasks.setdefault(task, len(tasks))
            n = len(ep)
            state = ep.ee.astype(np.float32)
            action = ep.actions.astype(np.float32)
            scalars = {
                "timestamp": (np.arange(n) / fps).astype(np.float32),
                "frame_index": np.arange(n, dtype=np.int64),
                "episode_index": np.full(n, e, np.int64),
                "index": np.arange(index, index + n, dtype=np.int64),
                "task_index": np.full(n, task_index, np.int64),
            }
            columns = {"observation.state": _nested(state), "action": _nested(action)}
            stats = {"observation.state": feature_stats(state), "action": feature_stats(action)}
            row: dict[str, Any] = {"episode_index": e, "tasks": [task], "length": n}
            for cam in cameras:
                key = IMAGE_KEY.format(camera=cam)
                frames = []

                def keep(stream, frames=frames):
                    for rgb in stream:
                        frames.append(rgb[::4, ::4].transpose(2, 0, 1))  # a subsample for the stats, as LeRobot
                        yield rgb

                row.update(videos[cam].add_episode(keep(_decoded(images[cam], f"{ep.path}: {cam}"))))
                stats[key] = channel_stats(np.stack(frames))
            if options.voxels:
                grids = np.stack([ep.grid(k, R) for k in range(n)])
                columns["observation.voxels"] = _nested(grids)
                stats["observation.voxels"] = channel_stats(grids)
            for name, values in scalars.items():
                columns[name] = pa.array(values)
                stats[name] = feature_stats(values.reshape(-1, 1).astype(np.float64))
            chunk, file = data.write(pa.table(columns))
            row.update({"data/chunk_index": chunk, "data/file_index": file})
            row.update({"dataset_from_index": index, "dataset_to_index": index + n})
            row.update({f"stats/{k}/{s}": np.asarray(v).tolist() for k, d in stats.items() for s, v in d.items()})
            row.update({"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0})
            row.update({"source_bag": str(ep.path), "success": ep.meta.success})
            rows.append(row)
            all_stats.append(stats)
            index += n
    finally:
        data.close()
        for v in videos.values():
            v.close()

    if not rows:
        shutil.rmtree(out)  # nothing written that looks like a dataset
        raise ExportError("no usable episodes")
    for cam, v in videos.items():  # after the state and action, as LeRobot lists them
        key = IMAGE_KEY.format(camera=cam)
        features[key] = {
            "dtype": "video",
            "shape": list(v.shape),
            "names": ["height", "width", "channels"],
            "info": v.info,
        }
    order = ["observation.state", "action", *(IMAGE_KEY.format(camera=c) for c in cameras)]
    features = {k: features[k] for k in order} | {k: v for k, v in features.items() if k not in order}
    info = {
        "codebase_version": CODEBASE_VERSION,
        "fps": fps,
        "features": features,
        "total_episodes": len(rows),
        "total_frames": index,
        "total_tasks": len(tasks),
        "chunks_size": options.chunks_size,
        "data_files_size_in_mb": options.data_files_size_in_mb,
        "video_files_size_in_mb": options.video_files_size_in_mb,
        "data_path": DATA_PATH,
        "video_path": VIDEO_PATH if cameras else None,
        "robot_type": options.robot_type,
        "splits": {"train": f"0:{len(rows)}"},
    }
    meta = out / "meta"
    meta.mkdir()
    (meta / "info.json").write_text(json.dumps(info, indent=4))
    (meta / "stats.json").write_text(json.dumps(_jsonable(merge_stats(all_stats)), indent=4))
    pq.write_table(_tasks_table(tasks), out / TASKS_PATH)
    episodes_path = out / EPISODES_PATH.format(chunk_index=0, file_index=0)
    episodes_path.parent.mkdir(parents=True)
    pq.write_table(pa.Table.from_pylist(rows), episodes_path, compression="snappy")
    return ExportReport(out, len(rows), index, fps, sorted(tasks), cameras, skipped, time.perf_counter() - t0)
