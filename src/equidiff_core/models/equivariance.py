"""Measuring equivariance of a policy's noise predictor and of its DDIM sampler.

For g in C_N (rotation by theta about the workspace's vertical axis):

* noise predictor: eps(g.o, g.a^k, k) against g.eps(o, a^k, k), relative error
  ||eps(g.o, g.a) - g.eps(o, a)|| / ||eps(o, a)||;
* sampler: DDIM from noise z on o and from g.z on g.o, actions compared as g.a(o, z) vs a(g.o, g.z),
  relative to the actions' extent about the workspace centre.

g acts on voxels with geometry.rotate_voxel_grid (exact for multiples of 90 deg, nearest
neighbour otherwise), on gripper states and actions with geometry.rotate_action about the
workspace centre, and on model-space vectors with action_space.rep_matrix. Observations are
random coloured voxels inside the cylinder the centred crop keeps under any rotation, so the
odd elements of C8 measure the network, not voxels falling off the grid.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .. import geometry
from . import action_space


def random_observation(policy, batch: int = 2, seed: int = 0, fill: float = 0.03) -> tuple[torch.Tensor, torch.Tensor]:
    """(voxels uint8 (B, To, 4, R, R, R), ee (B, To, 10)) with content inside the crop's inscribed cylinder."""
    p, ws = policy.preset, policy.workspace
    R = ws.resolution
    rng = np.random.default_rng(seed)
    c = (R - 1) / 2
    ii, jj = np.meshgrid(np.arange(R), np.arange(R), indexing="ij")
    inside = ((ii - c) ** 2 + (jj - c) ** 2) <= (p.crop / 2 - 3) ** 2
    occ = (rng.random((batch, p.n_obs_steps, R, R, R)) < fill) & inside[None, None, :, :, None]
    vox = np.zeros((batch, p.n_obs_steps, p.voxel_channels, R, R, R), np.uint8)
    vox[:, :, 0] = occ * 255
    vox[:, :, 1:] = rng.integers(1, 256, (batch, p.n_obs_steps, p.voxel_channels - 1, R, R, R)) * occ[:, :, None]
    yaw = rng.uniform(-math.pi, math.pi, batch)
    Rm = np.stack([geometry.rotz(y) @ np.diag([1.0, -1.0, -1.0]) for y in yaw])
    pos = np.asarray(ws.center) + rng.uniform(-0.1, 0.1, (batch, 3))
    ee = geometry.pose_to_action(geometry.make_pose(Rm, pos), rng.uniform(0.0, 0.08, batch))
    ee = np.repeat(ee[:, None], p.n_obs_steps, 1)
    return torch.from_numpy(vox), torch.from_numpy(ee.astype(np.float32))


def rotate_observation(policy, voxels, ee, theta):
    vox = geometry.rotate_voxel_grid(voxels, theta, mode="nearest")
    return vox, geometry.rotate_action(ee.double(), theta, policy.workspace.center).float()


@torch.no_grad()
def noise_predictor_error(policy, theta: float, batch: int = 2, seed: int = 0, timestep: int = 10) -> float:
    policy.eval()
    voxels, ee = random_observation(policy, batch, seed)
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(batch, policy.preset.horizon, policy.codec.dim, generator=gen)
    t = torch.full((batch,), timestep, dtype=torch.long)
    rep = torch.as_tensor(action_space.rep_matrix(policy.action_freqs, theta), dtype=torch.float32)
    vox, ee_n = policy._prepare(voxels, ee, "center")
    eps = policy.model(x, t, vox, ee_n)
    vox_g, ee_g = rotate_observation(policy, voxels, ee, theta)
    vox_g, ee_gn = policy._prepare(vox_g, ee_g, "center")
    eps_g = policy.model(x @ rep.T, t, vox_g, ee_gn)
    return float(torch.linalg.norm(eps_g - eps @ rep.T) / torch.linalg.norm(eps))


@torch.no_grad()
def sampling_error(policy, theta: float, batch: int = 2, seed: int = 0) -> float:
    policy.eval()
    voxels, ee = random_observation(policy, batch, seed)
    gen = torch.Generator().manual_seed(seed + 1)
    z = torch.randn(batch, policy.preset.horizon, policy.codec.dim, generator=gen)
    rep = torch.as_tensor(action_space.rep_matrix(policy.action_freqs, theta), dtype=torch.float32)
    a = policy.predict_action({"voxels": voxels, "ee": ee}, noise=z)["action_pred"].double()
    vox_g, ee_g = rotate_observation(policy, voxels, ee, theta)
    a_g = policy.predict_action({"voxels": vox_g, "ee": ee_g}, noise=z @ rep.T)["action_pred"].double()
    center = torch.zeros(10, dtype=torch.float64)
    center[:3] = torch.tensor(policy.workspace.center)
    expected = geometry.rotate_action(a, theta, policy.workspace.center)
    return float(torch.linalg.norm(a_g - expected) / torch.linalg.norm(a - center))


def group_report(policy, group_order: int | None = None, batch: int = 2, seed: int = 0,
                 sampling: bool = False) -> dict:
    """Errors for every non-identity element of C_N: max over C4 and over all of C_N."""
    N = group_order or policy.preset.group_order
    errs = {}
    for k in range(1, N):
        theta = 2 * math.pi * k / N
        errs[k] = (sampling_error if sampling else noise_predictor_error)(policy, theta, batch, seed)
    c4 = [e for k, e in errs.items() if (k * 4) % N == 0]
    return {"c4_max_rel_err": max(c4) if c4 else float("nan"), "c8_max_rel_err": max(errs.values()),
            "per_element": {f"{360 * k / N:g}deg": e for k, e in errs.items()}}
