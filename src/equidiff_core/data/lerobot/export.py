"""Episode bags -> a LeRobot dataset in LeRobot's v3.0 layout, without LeRobot installed.

Why write it ourselves: LeRobot 0.5+ needs Python >= 3.12 and torch < 2.12, and cannot share
this venv (Python 3.11, torch 2.13). So this module writes the files LeRobot 0.6.1's own writer
writes (``lerobot.datasets.dataset_writer`` / ``dataset_metadata``; checked against a dataset
made by ``LeRobotDataset.create`` + ``save_episode`` + ``finalize``), with pyarrow and PyAV, and
``test_lerobot_export.py`` loads the result with LeRobot itself in a venv of its own. The layout's
parts (paths, schema, statistics) are in ``data.lerobot.layout``, the camera videos in ``data.lerobot.video``.

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

One frame per observation, the dataset's own alignment (``data.dataset.load_episodes``: /voxels
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
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ...runtime.output_files import refuse_existing, staged_output
from ...wire.rosmsg import NS_PER_S
from ..dataset import load_episodes
from ..episode_arrays import DatasetConfig
from ..mcap_reader import BagError
from .layout import (
    CODEBASE_VERSION,
    DATA_PATH,
    EPISODES_PATH,
    IMAGE_KEY,
    TASKS_PATH,
    VIDEO_PATH,
    DataFiles,
    ExportError,
    arrow_schema,
    channel_stats,
    feature_stats,
    frame_features,
    jsonable_stats,
    merge_stats,
    nested_lists,
    tasks_table,
)
from .video import VideoEncoding, VideoFiles, bag_cameras, decoded_images, matched_images


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


# --- the export -------------------------------------------------------------------------------


def export_lerobot(
    bags: Iterable[str | Path],
    out: str | Path,
    options: ExportOptions = ExportOptions(),
    dataset_config: DatasetConfig | None = None,
    log: Callable[[str], None] = print,
    *,
    force: bool = False,
) -> ExportReport:
    """Write ``out`` (a new directory) from the bags; bags that cannot be used are skipped and reported.

    ``out`` is written beside itself and renamed into place once complete (``runtime.output_files.staged_output``):
    an existing one raises ``OutputExistsError`` unless ``force``; an export that fails half-way (a corrupt
    image, Ctrl-C) leaves no partial dataset and the old ``out`` as it was."""
    t0 = time.perf_counter()
    dataset_config = dataset_config or DatasetConfig()
    out = Path(out)
    refuse_existing(out, force)  # before decoding anything
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

    with staged_output(out, force=force) as staged:
        written, frames, tasks = _write_dataset(
            staged.path, episodes, cameras, fps, tolerance_ns, options, dataset_config.resolution, skipped, log
        )
    return ExportReport(out, written, frames, fps, tasks, cameras, skipped, time.perf_counter() - t0)


def _write_dataset(
    root: Path,
    episodes: list,
    cameras: list[str],
    fps: int,
    tolerance_ns: int,
    options: ExportOptions,
    resolution: int,
    skipped: list[tuple[str, str]],
    log: Callable[[str], None],
) -> tuple[int, int, list[str]]:
    """The dataset's files under ``root`` (a new folder); (episodes written, frames, tasks). Episodes whose
    images do not match go to ``skipped``; ``ExportError`` when none is left."""
    R = resolution
    features = frame_features(R if options.voxels else None)
    schema = arrow_schema(features)

    root.mkdir()
    data = DataFiles(root, schema, options.data_files_size_in_mb, options.chunks_size)
    videos = {
        cam: VideoFiles(
            root,
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
            columns = {"observation.state": nested_lists(state), "action": nested_lists(action)}
            stats = {"observation.state": feature_stats(state), "action": feature_stats(action)}
            row: dict[str, Any] = {"episode_index": e, "tasks": [task], "length": n}
            for cam in cameras:
                key = IMAGE_KEY.format(camera=cam)
                frames = []

                def keep(stream, frames=frames):
                    for rgb in stream:
                        frames.append(rgb[::4, ::4].transpose(2, 0, 1))  # a subsample for the stats, as LeRobot
                        yield rgb

                row.update(videos[cam].add_episode(keep(decoded_images(images[cam], f"{ep.path}: {cam}"))))
                stats[key] = channel_stats(np.stack(frames))
            if options.voxels:
                grids = np.stack([ep.grid(k, R) for k in range(n)])
                columns["observation.voxels"] = nested_lists(grids)
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
    meta = root / "meta"
    meta.mkdir()
    (meta / "info.json").write_text(json.dumps(info, indent=4))
    (meta / "stats.json").write_text(json.dumps(jsonable_stats(merge_stats(all_stats)), indent=4))
    pq.write_table(tasks_table(tasks), root / TASKS_PATH)
    episodes_path = root / EPISODES_PATH.format(chunk_index=0, file_index=0)
    episodes_path.parent.mkdir(parents=True)
    pq.write_table(pa.Table.from_pylist(rows), episodes_path, compression="snappy")
    return len(rows), index, sorted(tasks)
