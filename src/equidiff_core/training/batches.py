"""Training batches from a map-style dataset, in one of two ways with one sample order.

* :class:`DeviceBatchSource`: the whole training set as tensors on the model's device (the GPU
  path): every distinct voxel frame once (uint8, an episode's frames are shared by the windows
  that overlap them), plus per-sample frame indices, states and action targets. A batch is an
  index gather on the device: no CPU loader, no host-to-device copy of voxels per step.
* :func:`loader_batches`: torch's ``DataLoader`` over the dataset (the CPU path: the episodes
  stay sparse in RAM and each sample is densified when drawn).

Both draw indices from the same ``DistributedSampler`` (:func:`make_sampler`): a fresh seeded
permutation every epoch, split into disjoint equal shards, one per rank (one shard of everything
in a single process), so the two sources yield the same batches for the same seed.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, DistributedSampler


class BatchSourceError(RuntimeError):
    pass


def make_sampler(dataset: Dataset, seed: int, rank: int = 0, world_size: int = 1) -> DistributedSampler:
    """Shuffling sampler of ``rank``'s shard (every rank builds it with the same ``seed``)."""
    if len(dataset) == 0:
        raise BatchSourceError("training set is empty")
    return DistributedSampler(dataset, num_replicas=world_size, rank=rank, shuffle=True, seed=seed, drop_last=False)


def _epochs(sampler: DistributedSampler) -> Iterator[list[int]]:
    epoch = 0
    while True:
        sampler.set_epoch(epoch)
        yield list(sampler)
        epoch += 1


def loader_batches(
    dataset: Dataset, sampler: DistributedSampler, batch_size: int, num_workers: int = 0
) -> Iterator[dict]:
    """Endless batches through a DataLoader (a partial last batch only when the shard is smaller than one)."""
    loader = DataLoader(
        dataset,
        batch_size=batch_size,
        sampler=sampler,
        drop_last=len(sampler) >= batch_size,
        num_workers=num_workers,
        persistent_workers=num_workers > 0,
    )
    epoch = 0
    while True:
        sampler.set_epoch(epoch)
        yield from loader
        epoch += 1


def _is_episode_dataset(dataset) -> bool:
    """``data.dataset.DemoDataset``-like: windows over decoded episodes with sparse voxels."""
    return hasattr(dataset, "episodes") and hasattr(dataset, "window") and hasattr(dataset, "index")


def estimate_nbytes(dataset: Dataset) -> int:
    """Device memory :meth:`DeviceBatchSource.from_dataset` will take for ``dataset`` (voxel frames dominate)."""
    n = len(dataset)
    if n == 0:
        return 0
    if _is_episode_dataset(dataset):
        frames = sum(len(ep) for ep in dataset.episodes)
        R = dataset.config.resolution
        frame_bytes = 4 * R**3
        To, H = dataset.config.n_obs_steps, dataset.config.horizon
        return frames * frame_bytes + n * (To * (8 + 40) + H * 40)
    s = dataset[0]
    return n * sum(int(v.numel()) * v.element_size() for v in s.values() if isinstance(v, torch.Tensor))


class DeviceBatchSource:
    """The training set resident on ``device``: ``frames`` uint8 (F, 4, R, R, R), ``obs_index`` long
    (N, To) into frames, ``ee`` float32 (N, To, 10), ``action`` float32 (N, H, 10) and, where samples count
    differently (``data.dataset.DemoDataset.weights``), ``weight`` float32 (N,)."""

    def __init__(
        self,
        frames: torch.Tensor,
        obs_index: torch.Tensor,
        ee: torch.Tensor,
        action: torch.Tensor,
        weight: torch.Tensor | None = None,
    ):
        if not (len(obs_index) == len(ee) == len(action)) or (weight is not None and len(weight) != len(action)):
            raise BatchSourceError("obs_index, ee, action and weight must have one row per sample")
        self.frames, self.obs_index, self.ee, self.action, self.weight = frames, obs_index, ee, action, weight

    @property
    def device(self) -> torch.device:
        return self.frames.device

    def __len__(self) -> int:
        return len(self.obs_index)

    @property
    def nbytes(self) -> int:
        tensors = (self.frames, self.obs_index, self.ee, self.action, self.weight)
        return sum(t.numel() * t.element_size() for t in tensors if t is not None)

    @classmethod
    def from_dataset(cls, dataset: Dataset, device: torch.device | str) -> DeviceBatchSource:
        device = torch.device(device)
        if len(dataset) == 0:
            raise BatchSourceError("training set is empty")
        if _is_episode_dataset(dataset):
            return cls._from_episodes(dataset, device)
        return cls._from_samples(dataset, device)

    @classmethod
    def _from_episodes(cls, dataset, device: torch.device) -> DeviceBatchSource:
        # Densify on the device: only the sparse voxel lists cross the bus.
        R = dataset.config.resolution
        episodes = dataset.episodes
        first = np.concatenate([[0], np.cumsum([len(ep) for ep in episodes])])
        frames = torch.zeros((int(first[-1]), 4, R, R, R), dtype=torch.uint8, device=device)
        for e, ep in enumerate(episodes):
            if len(ep.voxel_idx) == 0:
                continue
            frame = np.repeat(np.arange(len(ep)), np.diff(ep.voxel_offsets)) + first[e]
            f = torch.from_numpy(frame).to(device)
            i, j, k = torch.from_numpy(ep.voxel_idx.astype(np.int64)).to(device).unbind(1)
            rgb = torch.from_numpy(np.ascontiguousarray(ep.voxel_rgb)).to(device)
            frames[f, 0, i, j, k] = 255
            for c in range(3):
                frames[f, 1 + c, i, j, k] = rgb[:, c]
        obs_index, ee, action = [], [], []
        for n in range(len(dataset)):
            ep, obs_idx, times = dataset.window(n)
            obs_index.append(first[dataset.index[n, 0]] + obs_idx)
            ee.append(ep.ee[obs_idx])
            action.append(ep.targets_at(times))
        as_t = lambda rows, dtype: torch.from_numpy(np.stack(rows)).to(device=device, dtype=dtype)
        weights = getattr(dataset, "weights", None)
        weight = None if weights is None else torch.from_numpy(weights).to(device)
        return cls(frames, as_t(obs_index, torch.long), as_t(ee, torch.float32), as_t(action, torch.float32), weight)

    @classmethod
    def _from_samples(cls, dataset, device: torch.device) -> DeviceBatchSource:
        first = dataset[0]
        n, (To, *grid) = len(dataset), first["voxels"].shape
        frames = torch.empty((n * To, *grid), dtype=torch.uint8, device=device)
        ee = torch.empty((n, *first["ee"].shape), dtype=torch.float32, device=device)
        action = torch.empty((n, *first["action"].shape), dtype=torch.float32, device=device)
        weight = torch.empty(n, dtype=torch.float32, device=device) if "weight" in first else None
        for i in range(n):  # one sample at a time: host memory stays at one sample
            s = dataset[i]
            frames[i * To : (i + 1) * To] = torch.as_tensor(s["voxels"]).to(device)
            ee[i] = torch.as_tensor(s["ee"]).to(device)
            action[i] = torch.as_tensor(s["action"]).to(device)
            if weight is not None:
                weight[i] = torch.as_tensor(s["weight"])
        obs_index = torch.arange(n * To, device=device).view(n, To)
        return cls(frames, obs_index, ee, action, weight)

    def batch(self, idx: torch.Tensor) -> dict:
        """Samples ``idx`` (long, on the device) as a training batch (the DataLoader's format)."""
        batch = {"voxels": self.frames[self.obs_index[idx]], "ee": self.ee[idx], "action": self.action[idx]}
        if self.weight is not None:
            batch["weight"] = self.weight[idx]
        return batch

    def batches(self, sampler: DistributedSampler, batch_size: int) -> Iterator[dict]:
        """Endless batches in ``sampler``'s order, drop-last as :func:`loader_batches`."""
        if len(sampler.dataset) != len(self):
            raise BatchSourceError(f"sampler over {len(sampler.dataset)} samples, source holds {len(self)}")
        for epoch in _epochs(sampler):
            order = torch.as_tensor(epoch, dtype=torch.long, device=self.device)
            stop = len(order) - len(order) % batch_size if len(order) >= batch_size else len(order)
            for a in range(0, stop, batch_size):
                yield self.batch(order[a : a + batch_size])
