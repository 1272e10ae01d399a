"""LeRobot's v3.0 layout: path templates, the frame table's schema, statistics, files that roll over.

What ``data.lerobot.export`` writes besides the videos (``data.lerobot.video``), each part following the
LeRobot 0.6.1 function named in its section.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ...geometry import ACTION_DIM

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


class ExportError(RuntimeError):
    """Nothing can be exported (no usable episode, mixed rates, output exists, images missing)."""


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


def jsonable_stats(stats: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, Any]]:
    return {k: {s: np.asarray(v).tolist() for s, v in d.items()} for k, d in stats.items()}


# --- files that roll over (lerobot.datasets.utils.update_chunk_file_indices) -----------------


def next_chunk_file(chunk_index: int, file_index: int, chunks_size: int) -> tuple[int, int]:
    return (chunk_index + 1, 0) if file_index == chunks_size - 1 else (chunk_index, file_index + 1)


class DataFiles:
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


# --- the schema ---------------------------------------------------------------------------------


def frame_features(voxel_resolution: int | None) -> dict[str, dict]:
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


def hf_feature(ft: dict) -> dict:
    """A LeRobot feature as Hugging Face ``datasets`` writes it into the parquet schema metadata."""
    shape = ft["shape"]
    if shape == [1]:
        return {"dtype": ft["dtype"], "_type": "Value"}
    if len(shape) == 1:
        return {"feature": {"dtype": ft["dtype"], "_type": "Value"}, "length": shape[0], "_type": "List"}
    return {"shape": shape, "dtype": ft["dtype"], "_type": f"Array{len(shape)}D"}


def arrow_schema(features: dict[str, dict]) -> pa.Schema:
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
    hf = {"info": {"features": {k: hf_feature(ft) for k, ft in features.items() if ft["dtype"] != "video"}}}
    return pa.schema(fields, metadata={"huggingface": json.dumps(hf)})


def nested_lists(array: np.ndarray) -> pa.Array:
    """(N, d1, ..., dk) array -> N rows of k-deep nested lists (Hugging Face ``ArrayND`` storage)."""
    values = pa.array(array.reshape(-1))
    for size in reversed(array.shape[1:]):
        values = pa.FixedSizeListArray.from_arrays(values, size)
    return values


def tasks_table(tasks: dict[str, int]) -> pa.Table:
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
