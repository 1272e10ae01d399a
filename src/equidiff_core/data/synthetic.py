"""Synthetic voxel/action samples that need no twin: a coloured cube somewhere on the table and a
straight 16-step reach from the gripper to above it, so the target depends on the voxels.

The model tests and ``bench overfit`` train on them: a policy that fits two of them has learned to
read its observation, in a minute of CPU, where recorded demos take hours.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import Dataset

from .. import geometry
from ..config import Workspace

__all__ = ["OPEN_WIDTH_M", "CubeDataset", "cube_sample"]

OPEN_WIDTH_M = 0.08  # the gripper stays open throughout a cube demo


def cube_sample(
    rng: np.random.Generator, ws: Workspace, horizon: int = 16, n_obs_steps: int = 1, random_yaw: bool = True
) -> dict:
    """One training sample (``voxels`` uint8 (n_obs, 4, R, R, R), ``ee`` (n_obs, 10), ``action`` (horizon, 10))."""
    R = ws.resolution
    vox = np.zeros((4, R, R, R), np.uint8)
    i, j = rng.integers(12, R - 16, size=2)
    k = 8
    vox[0, i : i + 4, j : j + 4, k : k + 4] = 255
    vox[1:, i : i + 4, j : j + 4, k : k + 4] = np.array([200, 40, 40], np.uint8)[:, None, None, None]
    vox[0, :, :, :2] = 255  # table
    vox[1:, :, :, :2] = 120
    cube = ws.lower + (np.array([i, j, k]) + 2) * ws.voxel_size
    yaw = rng.uniform(-np.pi, np.pi) if random_yaw else 0.0
    R_ee = geometry.rotz(yaw) @ np.diag([1.0, -1.0, -1.0])  # pointing down
    p0 = np.array([*ws.center[:2], ws.center[2] + 0.1]) + rng.uniform(-0.05, 0.05, 3)
    target = cube + np.array([0, 0, 0.05])
    s = np.linspace(0, 1, horizon + 1)[1:, None]
    pos = p0 + s * (target - p0)
    poses = geometry.make_pose(np.repeat(R_ee[None], horizon, 0), pos)
    action = geometry.pose_to_action(poses, np.full(horizon, OPEN_WIDTH_M))
    ee = geometry.pose_to_action(geometry.make_pose(R_ee, p0), np.array(OPEN_WIDTH_M))
    return {
        "voxels": torch.from_numpy(np.repeat(vox[None], n_obs_steps, 0)),
        "ee": torch.from_numpy(np.repeat(ee[None], n_obs_steps, 0).astype(np.float32)),
        "action": torch.from_numpy(action.astype(np.float32)),
    }


class CubeDataset(Dataset):
    """``n`` cube samples drawn with ``seed``; ``normalizer_arrays`` as training's normaliser fit expects."""

    def __init__(
        self,
        n: int,
        ws: Workspace | None = None,
        seed: int = 0,
        horizon: int = 16,
        n_obs_steps: int = 1,
        random_yaw: bool = True,
    ):
        self.ws = ws or Workspace()
        rng = np.random.default_rng(seed)
        self.samples = [cube_sample(rng, self.ws, horizon, n_obs_steps, random_yaw) for _ in range(n)]

    def __len__(self):
        return len(self.samples)

    def __getitem__(self, i):
        return self.samples[i]

    def normalizer_arrays(self):
        return (
            np.concatenate([s["action"].numpy() for s in self.samples]),
            np.concatenate([s["ee"].numpy() for s in self.samples]),
        )
