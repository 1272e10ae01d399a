"""Training augmentation: random crops and rotations about the workspace's vertical axis, and the
voxel input builder (``voxel_input``) that training, evaluation and deployment share.

A rotation acts on the whole sample at once: the voxel grid (geometry.rotate_voxel_grid, exact
for multiples of 90 deg, nearest-neighbour otherwise), every gripper state and the whole action
chunk (geometry.rotate_action about the workspace centre): the same group element everywhere,
so the sample stays physically consistent.
"""

from __future__ import annotations

import math

import torch

from .. import geometry


def center_crop(voxels: torch.Tensor, size: int) -> torch.Tensor:
    """(..., X, Y, Z) -> (..., size, size, size), centred (symmetric for even margins, so rot90 commutes)."""
    res = voxels.shape[-1]
    if res < size or voxels.shape[-3] != res or voxels.shape[-2] != res:
        raise ValueError(f"voxel grid {tuple(voxels.shape[-3:])} cannot be cropped to {size}^3")
    lo = (res - size) // 2
    return voxels[..., lo : lo + size, lo : lo + size, lo : lo + size]


def random_crop(voxels: torch.Tensor, size: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """(B, ..., X, Y, Z) -> (B, ..., size^3): one random offset per sample (shared by its obs steps)."""
    res = voxels.shape[-1]
    if res < size:
        raise ValueError(f"voxel grid {res}^3 cannot be cropped to {size}^3")
    B = voxels.shape[0]
    offs = torch.randint(0, res - size + 1, (B, 3), generator=generator)
    return torch.stack(
        [voxels[b, ..., i : i + size, j : j + size, k : k + size] for b, (i, j, k) in enumerate(offs.tolist())]
    )


CROP_MODES = ("random", "center")


def voxel_input(
    voxels: torch.Tensor,
    size: int,
    mode: str,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """uint8 grids (B, ..., R, R, R) -> the network's input (B, ..., size, size, size) in [0, 1].

    ``mode`` 'random': one random crop per sample, the training augmentation (the official code's
    VoxelCropRandomizer, 64³ -> 58³); 'center': the centred crop, for evaluation and deployment (it
    commutes with rot90, so C4 stays exact). Cropped before converting: a quarter less to convert."""
    if mode == "random":
        vox = random_crop(voxels, size, generator)
    elif mode == "center":
        vox = center_crop(voxels, size)
    else:
        raise ValueError(f"crop mode must be one of {CROP_MODES}, got {mode!r}")
    return vox.to(device=device, dtype=dtype).div_(255.0)


def sample_angles(batch: int, mode: str, generator: torch.Generator | None = None) -> list[float]:
    if mode == "none":
        return [0.0] * batch
    if mode in ("c4", "c8"):
        n = 4 if mode == "c4" else 8
        return [2 * math.pi * k / n for k in torch.randint(0, n, (batch,), generator=generator).tolist()]
    if mode == "continuous":
        return (torch.rand(batch, generator=generator, dtype=torch.float64) * 2 * math.pi - math.pi).tolist()
    raise ValueError(f"unknown rotation augmentation {mode!r}")


def rotate_sample(
    voxels: torch.Tensor, ee: torch.Tensor, action: torch.Tensor, theta: float, center
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One sample: voxels (To, C, X, Y, Z), ee (To, 10), action (T, 10), rotated by theta about the centre."""
    if theta == 0.0:
        return voxels, ee, action
    return (
        geometry.rotate_voxel_grid(voxels, theta, mode="nearest"),
        geometry.rotate_action(ee, theta, center),
        geometry.rotate_action(action, theta, center),
    )


def random_rotation(
    voxels: torch.Tensor,
    ee: torch.Tensor,
    action: torch.Tensor,
    mode: str,
    center,
    generator: torch.Generator | None = None,
):
    """Batched: each sample gets its own angle drawn per ``mode`` ('none', 'c4', 'c8', 'continuous')."""
    angles = sample_angles(voxels.shape[0], mode, generator)
    if not any(angles):
        return voxels, ee, action
    out = [rotate_sample(voxels[b], ee[b], action[b], a, center) for b, a in enumerate(angles)]
    return tuple(torch.stack(parts) for parts in zip(*out))
