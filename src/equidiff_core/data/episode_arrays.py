"""One decoded episode as arrays (``EpisodeArrays``), the settings it was decoded with (``DatasetConfig``),
and its compressed form on disk: a packed episode (``equidiff dataset pack``) or the decoding cache.

``dataset`` decodes bags into these and samples training windows from them.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..perception.observation import STATE_TOLERANCE_S
from ..runtime.output_files import staged_output
from ..wire.pointcloud import VoxelGridSpec
from ..wire.rosmsg import NS_PER_S
from .bags import EpisodeMeta
from .mcap_reader import UNCHECKED, BagError
from .segments import FrameSource

# 2: compressed, with the decoding settings inside (shared with packed episodes); 3: each frame's source
# (data.segments) and the gate's alarms: a version 2 file cannot tell the policy's frames from a demo's
CACHE_VERSION = 3
PACKED_SUFFIX = ".episode.npz"


@dataclass(frozen=True)
class DatasetConfig:
    horizon: int = 16
    n_obs_steps: int = 1
    n_action_steps: int = 8
    resolution: int = 64
    state_tolerance_s: float = STATE_TOLERANCE_S  # ee pose / joint state must be this close to the voxel stamp
    obs_period_s: float | None = None  # None: the median interval of the bag's /voxels stamps
    cache_dir: str | None = None
    # The grid every /voxels message must be (origin, voxel size, base frame; that frame also for
    # /franka/ee_pose), where the lab is known: ``for_lab``. None (a bag from a lab whose lab.yaml
    # is not at hand): only the resolution is checked, and poses in any frame are taken.
    grid: VoxelGridSpec | None = None

    def __post_init__(self):
        if self.horizon < 1 or self.n_obs_steps < 1 or not 1 <= self.n_action_steps <= self.horizon:
            raise ValueError(f"need horizon >= n_action_steps >= 1 and n_obs_steps >= 1, got {self}")
        if self.grid is not None and self.grid.resolution != self.resolution:
            raise ValueError(f"grid {self.grid} does not have the resolution {self.resolution}")
        if self.state_tolerance_s <= 0:
            raise ValueError("state_tolerance_s must be positive")

    @classmethod
    def from_preset(cls, preset: Any, **overrides: Any) -> DatasetConfig:
        """Horizon, observation steps and action steps from a model preset (``policy.presets.PolicyPreset``)."""
        kw = {"horizon": preset.horizon, "n_obs_steps": preset.n_obs_steps, "n_action_steps": preset.n_action_steps}
        kw.update(overrides)
        return cls(**kw)

    @classmethod
    def for_lab(cls, lab: Any, **overrides: Any) -> DatasetConfig:
        """Decoding checked against ``lab`` (a ``config.LabConfig``): its workspace's grid in its base frame."""
        grid = VoxelGridSpec.of(lab.workspace, lab.base_frame)
        return cls(**{"resolution": grid.resolution, "grid": grid, **overrides})


@dataclass
class EpisodeArrays:
    """One decoded episode, ready for sampling."""

    path: Path
    meta: EpisodeMeta
    stamps_ns: np.ndarray  # (N,) observation (voxel header) stamps
    voxel_offsets: np.ndarray  # (N + 1,) into voxel_idx / voxel_rgb
    voxel_idx: np.ndarray  # (M, 3) uint16 occupied voxel indices
    voxel_rgb: np.ndarray  # (M, 3) uint8
    ee: np.ndarray  # (N, 10) float32 measured TCP pose + gripper width
    schedule_ns: np.ndarray  # (K,) times of the effective command schedule (first = -inf sentinel)
    schedule: np.ndarray  # (K, 10) float64 absolute targets
    obs_period_ns: int
    dropped_steps: int = 0
    rejected_chunks: int = 0
    integrity: str = UNCHECKED  # of the source bag: "checked" (every CRC matched) or "unchecked" (no CRCs)
    # (N,) uint8 data.segments.FrameSource of each observation; None: every frame a demonstration's
    sources: np.ndarray | None = None
    gate_alarms: int = 0  # times the policy's doubt gate held the arm and asked for help

    def __post_init__(self):
        if self.sources is None:
            self.sources = np.full(len(self.stamps_ns), FrameSource.DEMO, np.uint8)
        if self.sources.shape != self.stamps_ns.shape or self.sources.dtype != np.uint8:
            raise ValueError(f"{self.path}: {self.sources.shape} frame sources for {self.stamps_ns.shape} frames")
        if len(self.sources) and self.sources.max() >= len(FrameSource):
            raise ValueError(f"{self.path}: frame source {self.sources.max()} is none of {list(FrameSource)}")

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @property
    def duration_s(self) -> float:
        return float(self.stamps_ns[-1] - self.stamps_ns[0]) / NS_PER_S if len(self) else 0.0

    def grid(self, i: int, resolution: int) -> np.ndarray:
        a, b = self.voxel_offsets[i], self.voxel_offsets[i + 1]
        idx, rgb = self.voxel_idx[a:b].astype(np.intp), self.voxel_rgb[a:b]
        grid = np.zeros((4, resolution, resolution, resolution), dtype=np.uint8)
        grid[0, idx[:, 0], idx[:, 1], idx[:, 2]] = 255
        for c in range(3):
            grid[1 + c, idx[:, 0], idx[:, 1], idx[:, 2]] = rgb[:, c]
        return grid

    def targets_at(self, times_ns: np.ndarray) -> np.ndarray:
        """(T,) times -> (T, 10) the commanded target in effect at each (zero-order hold)."""
        k = np.searchsorted(self.schedule_ns, np.asarray(times_ns, dtype=np.int64), side="right") - 1
        return self.schedule[np.maximum(k, 0)]

    @property
    def actions(self) -> np.ndarray:
        """(N, 10) the target in effect at each observation."""
        return self.targets_at(self.stamps_ns)


# --- packed episodes and the disk cache ------------------------------------------------------

_ARRAY_FIELDS = ("stamps_ns", "voxel_offsets", "voxel_idx", "voxel_rgb", "ee", "schedule_ns", "schedule", "sources")


def _decoding(config: DatasetConfig) -> dict:
    """The settings that change what a bag decodes to (the rest only change the sampling). ``grid``
    is not one: it only decides whether a bag decodes at all, so a bag packed without it still reads."""
    return {
        "resolution": config.resolution,
        "state_tolerance_s": config.state_tolerance_s,
        "obs_period_s": config.obs_period_s,
    }


def write_packed(arrays: EpisodeArrays, file: Path, config: DatasetConfig) -> Path:
    """Write ``arrays`` compressed to ``file`` (atomically: a killed writer leaves no partial file)."""
    extra = json.dumps(
        {
            "version": CACHE_VERSION,
            "source": str(arrays.path),
            "decoding": _decoding(config),
            "meta": arrays.meta.to_dict(),
            "obs_period_ns": arrays.obs_period_ns,
            "dropped_steps": arrays.dropped_steps,
            "rejected_chunks": arrays.rejected_chunks,
            "integrity": arrays.integrity,
            "gate_alarms": arrays.gate_alarms,
        }
    )
    fields = {k: getattr(arrays, k) for k in _ARRAY_FIELDS if k != "voxel_idx"}
    # Occupied voxels come in C order, so their flat indices rise within a frame: stored as
    # differences they compress 4x better than the (M, 3) indices.
    res = config.resolution
    flat = (
        np.ravel_multi_index(arrays.voxel_idx.T.astype(np.intp), (res, res, res))
        if len(arrays.voxel_idx)
        else np.zeros(0, np.intp)
    )
    fields["voxel_flat_delta"] = np.diff(flat, prepend=0).astype(np.int32)
    # replaced when there: data-parallel ranks decoding the same bag may cache it at once, each staged apart
    with staged_output(file, force=True) as staged:
        np.savez_compressed(staged.path, extra=np.array(extra), **fields)
    return file


def read_packed(file: Path, config: DatasetConfig, path: Path | None = None) -> EpisodeArrays:
    """EpisodeArrays from a packed file; BagError if it is unreadable or was decoded with other settings."""
    try:
        with np.load(file, allow_pickle=False) as z:
            extra = json.loads(str(z["extra"]))
            current = extra.get("version") == CACHE_VERSION and extra.get("decoding") == _decoding(config)
            if current:  # an older format may lack today's arrays: refused below with what to do
                arrays = {k: z[k] for k in _ARRAY_FIELDS if k != "voxel_idx"}
                flat = np.cumsum(z["voxel_flat_delta"].astype(np.int64))
                gate_alarms = int(extra["gate_alarms"])
    except Exception as err:  # zipfile, ValueError, KeyError, JSON: all mean "not a usable packed episode"
        raise BagError(f"{file}: not a readable packed episode ({type(err).__name__}: {err})") from err
    if not current:
        raise BagError(
            f"{file}: packed with {extra.get('decoding')} (format {extra.get('version')}), but "
            f"training asks for {_decoding(config)} (format {CACHE_VERSION}): pack the bags again"
        )
    res = config.resolution
    arrays["voxel_idx"] = np.stack(np.unravel_index(flat, (res, res, res)), axis=1).astype(np.uint16)
    try:
        return EpisodeArrays(
            path=path or file,
            meta=EpisodeMeta.from_dict(extra["meta"]),
            obs_period_ns=extra["obs_period_ns"],
            dropped_steps=extra["dropped_steps"],
            rejected_chunks=extra["rejected_chunks"],
            integrity=extra.get("integrity", UNCHECKED),
            gate_alarms=gate_alarms,
            **arrays,
        )
    except (KeyError, ValueError) as err:
        raise BagError(f"{file}: not a readable packed episode ({type(err).__name__}: {err})") from err


# The disk cache is a packed episode keyed by the bag's absolute path, size and mtime.
def cache_key(path: Path, config: DatasetConfig) -> str | None:
    mcaps = sorted(path.glob("*.mcap"))
    meta = path / "metadata.yaml"
    if not mcaps or not meta.is_file():
        return None
    st = [(m.name, m.stat().st_size, m.stat().st_mtime_ns) for m in mcaps] + [(meta.stat().st_mtime_ns,)]
    blob = json.dumps([CACHE_VERSION, str(path.resolve()), st, _decoding(config)])
    return hashlib.sha1(blob.encode()).hexdigest()[:20]


def cache_load(path: Path, config: DatasetConfig) -> EpisodeArrays | None:
    key = cache_key(path, config) if config.cache_dir else None
    file = Path(config.cache_dir) / f"{key}.npz" if key else None
    if file is None or not file.is_file():
        return None
    try:
        return read_packed(file, config, path)
    except BagError:  # a stale or partial cache file is rebuilt, never trusted
        return None


def cache_save(arrays: EpisodeArrays, config: DatasetConfig) -> None:
    key = cache_key(arrays.path, config) if config.cache_dir else None
    if key:
        write_packed(arrays, Path(config.cache_dir) / f"{key}.npz", config)
