"""Training samples from episode bags (no ROS install needed): the model contract's batch format.

One observation per ``/voxels`` message (5 Hz), at its header stamp ``t``:

* ``voxels``: the exact uint8 (4, R, R, R) grid (``wire.pointcloud.voxel_msg_to_grid``);
* ``ee``: the ``/franka/ee_pose`` nearest to ``t`` (header stamps) and the gripper width from
  the ``/franka/joint_states`` nearest to ``t`` (sum of the two finger joints), as a 10-D
  absolute action; both must lie within ``state_tolerance_s`` or the step is dropped (and
  counted) rather than paired with a stale state. A pose or joint state that ``wire.rosmsg`` refuses
  (NaN / inf, a non-unit quaternion, names and positions that disagree, a width outside the
  hand's stroke; with ``DatasetConfig.grid`` a pose in another frame) is left out, as the live
  policy node drops it: its step pairs with the next nearest usable state, or is dropped.

Grids are checked against ``DatasetConfig.grid`` (lab.yaml's workspace: origin, voxel size,
base frame; ``DatasetConfig.for_lab``) where the caller knows the lab; without it, only the
resolution is checked, and a bag from a lab with another workspace of that resolution decodes.

Actions: the commanded absolute target *in effect* at ``t + i·dt`` (i = 0 … horizon−1, dt =
the observation period). "In effect" replays what the franka node does with
``/franka/command_chunk``: a newer chunk replaces the not-yet-reached steps of older ones,
and between steps the latest reached step holds (teleop chunks have one step). Before the
first command the robot holds its measured pose.

Windows and padding follow the official code's ``SequenceSampler`` (pad_before =
n_obs_steps − 1, pad_after = n_action_steps − 1): window starts run from −pad_before to
N − horizon + pad_after, indices outside the episode repeat the first/last step.

Decoding happens once per bag: episodes are kept in memory as sparse voxel lists (a grid is
~1 MiB dense, ~40 KiB sparse), and with ``cache_dir`` also on disk keyed by the bag's size
and mtime, so neither the second epoch nor the second run decodes bags again.

Packed episodes (``equidiff dataset pack``): the same arrays, compressed, in one
``<episode>.episode.npz`` per bag, about 7 % of the bag's size (``data.episode_arrays``, with the cache). Training accepts them wherever it
accepts bags, so a dataset can be copied to a GPU machine without its MCAP files.
"""

from __future__ import annotations

import random
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .. import geometry
from ..perception.observation import ee_input, nearest
from ..robots.base import FINGER_JOINT_NAMES
from ..runtime.output_files import distinct_names, staged_output, unique_paths
from ..wire.chunk import ChunkError, chunk_from_msg
from ..wire.pointcloud import CloudError, voxel_msg_to_grid
from ..wire.rosmsg import NS_PER_S, MessageError, gripper_width_from_joint_state, pose_from_msg
from ..wire.topics import (
    TOPIC_COMMAND_CHUNK,
    TOPIC_EE_POSE,
    TOPIC_JOINT_STATES,
    TOPIC_POLICY_STATE,
    TOPIC_TELEOP_ACTIVE,
    TOPIC_VOXELS,
    TRAINING_TOPICS,
)
from .bags import find_bags, is_bag_dir, read_episode
from .episode_arrays import (
    PACKED_SUFFIX,
    DatasetConfig,
    EpisodeArrays,
    cache_load,
    cache_save,
    read_packed,
    write_packed,
)
from .mcap_reader import CHECKED, BagError
from .segments import FrameSource, SourceWeights, frame_sources, gate_alarms_ns, source_seconds


def command_schedule(chunks: Sequence[Any]) -> tuple[np.ndarray, np.ndarray]:
    """PoseChunks in arrival order -> the effective (times, targets) as the franka node executes them.

    A newer chunk replaces every step of the previous schedule at or after its first step.
    """
    times: list[int] = []
    targets: list[np.ndarray] = []
    for chunk in sorted(chunks, key=lambda c: c.stamp_ns):
        first = int(chunk.times_ns[0])
        while times and times[-1] >= first:
            times.pop()
            targets.pop()
        times.extend(int(t) for t in chunk.times_ns)
        targets.extend(chunk.actions)
    if not times:
        return np.zeros(0, np.int64), np.zeros((0, geometry.ACTION_DIM))
    return np.asarray(times, dtype=np.int64), np.asarray(targets, dtype=np.float64)


def _ee_actions(episode, stamps_ns: np.ndarray, tol_ns: int, frame_id: str | None) -> tuple[np.ndarray, np.ndarray]:
    """(N, 10) measured pose + width at each stamp and a (N,) mask of steps within tolerance."""
    poses_t = episode[TOPIC_EE_POSE]
    pose_ns = poses_t.header_ns()
    order = np.argsort(pose_ns, kind="stable")
    pose_ns = pose_ns[order]
    js_t = episode[TOPIC_JOINT_STATES]
    js_ns = js_t.header_ns()
    js_order = np.argsort(js_ns, kind="stable")
    # a message without finger joints (e.g. an arm-only publisher) or one rosmsg refuses is no gripper state
    widths = np.array([_width_or_nan(js_t.messages[i]) for i in js_order], dtype=np.float64)
    valid_js = np.isfinite(widths)
    if not valid_js.any():
        raise BagError(f"{episode.path}: /franka/joint_states has no usable {' / '.join(FINGER_JOINT_NAMES)} positions")
    js_ns_valid, widths = js_ns[js_order][valid_js], widths[valid_js]
    wi, wd = nearest(js_ns_valid, stamps_ns)
    # Poses are decoded only where a step needs one (a bag holds ~20 per observation); a refused one
    # is left out and the steps that wanted it look again among the rest.
    usable = np.ones(len(pose_ns), dtype=bool)
    decoded: dict[int, np.ndarray] = {}
    while True:
        if not usable.any():
            raise BagError(f"{episode.path}: no usable /franka/ee_pose{'' if frame_id is None else f' in {frame_id}'}")
        candidates = np.nonzero(usable)[0]
        pi, pd = nearest(pose_ns[candidates], stamps_ns)
        ok = (pd <= tol_ns) & (wd <= tol_ns)
        wanted = {int(candidates[pi[n]]) for n in np.nonzero(ok)[0]} - decoded.keys()
        for k in wanted:
            pose = _pose_or_none(poses_t.messages[order[k]], frame_id)
            if pose is None:
                usable[k] = False
            else:
                decoded[k] = pose
        if all(usable[k] for k in wanted):
            break
    out = np.zeros((len(stamps_ns), geometry.ACTION_DIM), dtype=np.float32)
    for n in np.nonzero(ok)[0]:
        out[n] = ee_input(decoded[int(candidates[pi[n]])], widths[wi[n]])
    return out, ok


def _width_or_nan(msg) -> float:
    try:
        width = gripper_width_from_joint_state(msg)
    except MessageError:
        return np.nan
    return np.nan if width is None else width


def _pose_or_none(msg, frame_id: str | None) -> np.ndarray | None:
    try:
        return pose_from_msg(msg, frame_id)
    except MessageError:
        return None


def load_episode_arrays(path: str | Path, config: DatasetConfig = DatasetConfig()) -> EpisodeArrays:
    """Decode one bag (or read one packed episode) into EpisodeArrays; BagError (with the reason)
    if it cannot make a clean episode."""
    path = Path(path)
    if path.name.endswith(PACKED_SUFFIX):
        return read_packed(path, config)
    cached = cache_load(path, config)
    if cached is not None:
        return cached
    # who drove (data.segments) comes from the two latched state topics, where a roll-out's bag has them
    episode = read_episode(path, topics=(*TRAINING_TOPICS, TOPIC_POLICY_STATE, TOPIC_TELEOP_ACTIVE))
    for topic in TRAINING_TOPICS:
        if topic not in episode:
            raise BagError(f"{path}: no messages on {topic}")
    vox = episode[TOPIC_VOXELS]
    stamps = vox.header_ns()
    order = np.argsort(stamps, kind="stable")
    stamps = stamps[order]
    if np.any(np.diff(stamps) <= 0):
        raise BagError(f"{path}: /voxels has repeated header stamps")
    if len(stamps) >= 2:
        period = round(config.obs_period_s * NS_PER_S) if config.obs_period_s else int(np.median(np.diff(stamps)))
    else:
        period = round((config.obs_period_s or 0.2) * NS_PER_S)
    frame_id = None if config.grid is None else config.grid.frame_id
    ee, ok = _ee_actions(episode, stamps, int(config.state_tolerance_s * NS_PER_S), frame_id)

    chunks, rejected = [], 0
    for msg in episode[TOPIC_COMMAND_CHUNK].messages:
        try:
            chunks.append(chunk_from_msg(msg))
        except ChunkError:
            rejected += 1  # the franka node rejected it too: it was never executed
    sched_ns, sched = command_schedule(chunks)
    if not len(sched_ns):
        raise BagError(f"{path}: no valid command chunks")

    keep = np.nonzero(ok)[0]
    if not len(keep):
        raise BagError(
            f"{path}: no /voxels stamp has an ee pose and joint state within {config.state_tolerance_s * 1e3:.0f} ms"
        )
    offsets, idx_parts, rgb_parts = [0], [], []
    for n in keep:
        try:
            grid = voxel_msg_to_grid(vox.messages[order[n]], config.grid or config.resolution)
        except CloudError as err:
            raise BagError(f"{path}: malformed /voxels message {n}: {err}") from err
        occ = np.nonzero(grid[0])
        idx_parts.append(np.stack(occ, axis=1).astype(np.uint16))
        rgb_parts.append(grid[1:, occ[0], occ[1], occ[2]].T.copy())
        offsets.append(offsets[-1] + len(occ[0]))
    # Before the first command the robot holds its measured pose.
    hold = ee[keep[0]].astype(np.float64)
    sched_ns = np.concatenate([[np.iinfo(np.int64).min], sched_ns])
    sched = np.concatenate([hold[None], sched])
    arrays = EpisodeArrays(
        path=path,
        meta=episode.meta,
        stamps_ns=stamps[keep],
        voxel_offsets=np.asarray(offsets, dtype=np.int64),
        voxel_idx=np.concatenate(idx_parts) if idx_parts else np.zeros((0, 3), np.uint16),
        voxel_rgb=np.concatenate(rgb_parts) if rgb_parts else np.zeros((0, 3), np.uint8),
        ee=ee[keep],
        schedule_ns=sched_ns,
        schedule=sched,
        obs_period_ns=period,
        dropped_steps=int(len(stamps) - len(keep)),
        rejected_chunks=rejected,
        integrity=episode.integrity,
        sources=frame_sources(episode, stamps[keep]),
        gate_alarms=len(gate_alarms_ns(episode)),
    )
    if not np.all(np.isfinite(arrays.ee)) or not np.all(np.isfinite(arrays.schedule)):
        raise BagError(f"{path}: NaN/inf in poses or commands")
    cache_save(arrays, config)
    return arrays


# --- packed episodes -------------------------------------------------------------------------


def find_episodes(paths: Iterable[str | Path]) -> list[Path]:
    """Bags (``data.bags.find_bags``) and packed episodes: a folder expands to both kinds inside it."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir() and not is_bag_dir(p):
            out.extend(sorted(p.glob(f"*{PACKED_SUFFIX}")))
        out.extend(find_bags([p]))  # a file (a packed episode) or a missing path passes through
    return out


def pack_episodes(
    paths: Iterable[str | Path],
    out_dir: str | Path,
    config: DatasetConfig = DatasetConfig(),
    log=None,
    *,
    force: bool = False,
) -> tuple[list[Path], list[tuple[Path, str]]]:
    """Decode every bag under ``paths`` and write one packed episode per bag into ``out_dir``, a new folder
    (``runtime.output_files.staged_output``: ``OutputExistsError`` if it holds anything, unless ``force``; it lands
    only once every bag is packed, and not at all when none could be). Each file is named after its bag's
    path below the bags' common folder, so same-named bags of two days both land. Returns (the packed
    files in ``out_dir``, the skipped bags with their reasons)."""
    out_dir = Path(out_dir)
    bags = unique_paths(find_bags(paths))
    skipped: list[tuple[Path, str]] = []
    with staged_output(out_dir, force=force) as staged:
        staged.path.mkdir()
        packed = 0
        for bag, name in zip(bags, distinct_names(bags), strict=True):
            for episode in iter_episodes([bag], config, skipped, log, find=find_bags):
                write_packed(episode, staged.path / f"{name}{PACKED_SUFFIX}", config)
                packed += 1
        if not packed:
            staged.discard()
    return (sorted(out_dir.glob(f"*{PACKED_SUFFIX}")) if packed else []), skipped


# --- sampling ---------------------------------------------------------------------------------


def sample_starts(n: int, horizon: int, n_obs_steps: int, n_action_steps: int) -> np.ndarray:
    """Window starts of the official SequenceSampler: -pad_before ... n - horizon + pad_after."""
    pad_before, pad_after = n_obs_steps - 1, n_action_steps - 1
    lo, hi = -pad_before, n - horizon + pad_after
    return np.arange(lo, hi + 1, dtype=np.int64) if hi >= lo else np.zeros(0, np.int64)


def iter_episodes(
    paths: Iterable[str | Path], config: DatasetConfig, skipped: list, log=None, find=find_episodes
) -> Iterable[EpisodeArrays]:
    """Decode each episode in turn; bad ones go to ``skipped`` as ``(path, reason)`` (and ``log``)."""
    for path in find(paths):
        try:
            yield load_episode_arrays(path, config)
        except (BagError, geometry.GeometryError, OSError) as err:
            skipped.append((Path(path), str(err)))
            if log:
                log(f"skipping {path}: {err}")


def load_episodes(
    paths: Iterable[str | Path], config: DatasetConfig = DatasetConfig(), log=None
) -> tuple[list[EpisodeArrays], list[tuple[Path, str]]]:
    """Decode every bag or packed episode (folders expand to those inside); bad ones are reported and skipped."""
    skipped: list[tuple[Path, str]] = []
    return list(iter_episodes(paths, config, skipped, log)), skipped


def split_episodes(episodes: Sequence[Any], val_fraction: float, seed: int) -> tuple[list, list]:
    """Hold out whole episodes (never steps of a training episode) for validation."""
    if not 0 <= val_fraction < 1:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    order = list(range(len(episodes)))
    random.Random(seed).shuffle(order)
    n_val = round(len(episodes) * val_fraction)
    if val_fraction > 0 and n_val == 0 and len(episodes) > 1:
        n_val = 1
    val = sorted(order[:n_val])
    train = sorted(order[n_val:])
    return [episodes[i] for i in train], [episodes[i] for i in val]


try:
    from torch.utils.data import Dataset as _TorchDataset
except ImportError:  # pragma: no cover
    _TorchDataset = object


class DemoDataset(_TorchDataset):
    """Samples ``{"voxels": uint8 (To, 4, R, R, R), "ee": float32 (To, 10), "action": float32 (H, 10)}``, and
    ``"weight"`` (float32) where corrected roll-outs make samples count differently.

    A sample's weight is its current frame's (the last observation step's) under ``weights``
    (``data.segments.SourceWeights``): a demonstration's frames count 1, an operator's correction and the
    policy's own frames as ``weights`` says; frames of weight 0 (the policy's by default, the arm held) are
    not sampled at all."""

    def __init__(
        self,
        episodes: Sequence[EpisodeArrays],
        config: DatasetConfig = DatasetConfig(),
        weights: SourceWeights = SourceWeights(),
    ):
        self.config = config
        self.source_weights = weights
        self.episodes = list(episodes)
        index, sample_weights, sample_sources = [], [], []
        for e, ep in enumerate(self.episodes):
            starts = sample_starts(len(ep), config.horizon, config.n_obs_steps, config.n_action_steps)
            sources = ep.sources[np.clip(starts + config.n_obs_steps - 1, 0, len(ep) - 1)]
            w = weights.of(sources) if len(starts) else np.zeros(0, np.float32)
            index.extend((e, int(s)) for s in starts[w > 0])
            sample_weights.append(w[w > 0])
            sample_sources.append(sources[w > 0])
        self.index = np.asarray(index, dtype=np.int64).reshape(-1, 2)
        # (N,) data.segments.FrameSource of each sample's current frame
        self.sources = np.concatenate(sample_sources) if sample_sources else np.zeros(0, np.uint8)
        w = np.concatenate(sample_weights) if sample_weights else np.zeros(0, np.float32)
        # None when every sample counts 1: the batches and the loss stay exactly those of plain demonstrations
        self.weights: np.ndarray | None = None if np.all(w == 1.0) else w

    @classmethod
    def from_bags(
        cls,
        paths: Iterable[str | Path],
        config: DatasetConfig = DatasetConfig(),
        log=None,
        weights: SourceWeights = SourceWeights(),
    ):
        episodes, skipped = load_episodes(paths, config, log)
        ds = cls(episodes, config, weights)
        ds.skipped = skipped
        return ds

    def __len__(self) -> int:
        return len(self.index)

    def window(self, i: int) -> tuple[EpisodeArrays, np.ndarray, np.ndarray]:
        """(episode, observation step indices (To,), action times (H,)) of sample ``i``."""
        e, start = self.index[i]
        ep = self.episodes[e]
        cfg = self.config
        n = len(ep)
        obs_idx = np.clip(start + np.arange(cfg.n_obs_steps), 0, n - 1)
        # Action step j is the target in effect at observation step start + j; steps outside
        # the episode repeat the first/last one (SequenceSampler padding). Using the recorded
        # stamps (= t + j*dt for a regular stream) keeps camera jitter from shifting targets.
        steps = np.clip(start + np.arange(cfg.horizon), 0, n - 1)
        times = ep.stamps_ns[steps]
        return ep, obs_idx, times

    def __getitem__(self, i: int) -> dict:
        import torch

        ep, obs_idx, times = self.window(i)
        voxels = np.stack([ep.grid(int(k), self.config.resolution) for k in obs_idx])
        sample = {
            "voxels": torch.from_numpy(voxels),
            "ee": torch.from_numpy(ep.ee[obs_idx].astype(np.float32)),
            "action": torch.from_numpy(ep.targets_at(times).astype(np.float32)),
        }
        if self.weights is not None:
            sample["weight"] = torch.tensor(self.weights[i])
        return sample

    def all_actions(self) -> np.ndarray:
        """(N, 10) every observation step's commanded target (for Normalizer.fit)."""
        parts = [ep.actions for ep in self.episodes]
        return np.concatenate(parts).astype(np.float32) if parts else np.zeros((0, 10), np.float32)

    def all_ee(self) -> np.ndarray:
        parts = [ep.ee for ep in self.episodes]
        return np.concatenate(parts).astype(np.float32) if parts else np.zeros((0, 10), np.float32)

    def normalizer_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(actions, ee) for ``Normalizer.fit`` without building every sample (training.fit_normalizer)."""
        return self.all_actions(), self.all_ee()


# --- stats ------------------------------------------------------------------------------------


def dataset_stats(paths: Iterable[str | Path], config: DatasetConfig = DatasetConfig()) -> dict:
    """Episodes, durations, steps, samples and action ranges of bags, who drove for how long (corrections of a
    policy, its doubt gate's alarms: ``data.segments``); bad bags listed with reasons."""
    episodes, skipped = load_episodes(paths, config)
    rows = []
    for ep in episodes:
        acts = ep.actions
        rows.append(
            {
                "path": str(ep.path),
                "task": ep.meta.task,
                "operator": ep.meta.operator,
                "success": ep.meta.success,
                "duration_s": round(ep.duration_s, 3),
                "steps": len(ep),
                "obs_hz": round(NS_PER_S / ep.obs_period_ns, 2) if ep.obs_period_ns else None,
                "samples": len(sample_starts(len(ep), config.horizon, config.n_obs_steps, config.n_action_steps)),
                "dropped_steps": ep.dropped_steps,
                "rejected_chunks": ep.rejected_chunks,
                "integrity": ep.integrity,
                # who drove (data.segments): seconds of demonstration, policy, operator correction, holding
                "seconds_by_source": source_seconds(ep.sources, ep.obs_period_ns),
                "corrected": bool(
                    np.any(ep.sources == FrameSource.OPERATOR) and np.any(ep.sources == FrameSource.POLICY)
                ),
                "gate_alarms": ep.gate_alarms,
                "action_min": acts.min(0).round(4).tolist(),
                "action_max": acts.max(0).round(4).tolist(),
            }
        )
    all_actions = np.concatenate([ep.actions for ep in episodes]) if episodes else np.zeros((0, 10))
    return {
        "episodes": rows,
        "skipped": [{"path": str(p), "reason": r} for p, r in skipped],
        "total": {
            "episodes": len(episodes),
            "skipped": len(skipped),
            # bags stored without CRCs (written before the project wrote them): read, but nothing was checked
            "unchecked": sum(r["integrity"] != CHECKED for r in rows),
            "duration_s": round(sum(r["duration_s"] for r in rows), 3),
            "episodes_with_corrections": sum(r["corrected"] for r in rows),
            "correction_s": round(sum(r["seconds_by_source"]["operator"] for r in rows if r["corrected"]), 3),
            "policy_s": round(sum(r["seconds_by_source"]["policy"] for r in rows), 3),
            "gate_alarms": sum(r["gate_alarms"] for r in rows),
            "steps": int(sum(r["steps"] for r in rows)),
            "samples": int(sum(r["samples"] for r in rows)),
            "action_min": all_actions.min(0).round(4).tolist() if len(all_actions) else None,
            "action_max": all_actions.max(0).round(4).tolist() if len(all_actions) else None,
        },
    }
