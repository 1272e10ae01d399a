"""The two diffusion policies, diffusion_policy style: ``compute_loss``, ``predict_action``, ``set_normalizer``.

``make_policy("equidiff" | "baseline", preset, workspace)`` builds EquiDiff (Vo) (escnn, C_N) or
DiffPo-C (Vo) (plain 3D CNN, about the same parameter count): same U-Net, same diffusion, same
augmentation and training loop, so any difference between them is the equivariance.

Samples and batches (torch tensors, batches add a leading B):
``{"voxels": uint8 (To, 4, R, R, R), "ee": float32 (To, 10), "action": float32 (T, 10)}``
with ``ee`` the current TCP pose + width as an absolute action and ``action`` the commanded
absolute targets (geometry.pose_to_action).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ..config import Workspace, to_dict
from ..models import action_space
from ..models.sampling import (
    ActionCodec,
    ddim_sample,
    make_inference_scheduler,
    make_train_scheduler,
)
from . import augment
from .normalizer import Normalizer
from .presets import PolicyPreset

POLICY_NAMES = ("equidiff", "baseline")


class PolicyInputError(ValueError):
    """Observations or batches with the wrong shape, dtype or non-finite values."""


def check_obs(voxels: torch.Tensor, ee: torch.Tensor, preset: PolicyPreset) -> None:
    To = preset.n_obs_steps
    if voxels.ndim != 6 or voxels.shape[1] != To or voxels.shape[2] != preset.voxel_channels:
        raise PolicyInputError(f"voxels must be (B, {To}, {preset.voxel_channels}, R, R, R), got {tuple(voxels.shape)}")
    if voxels.dtype != torch.uint8:
        raise PolicyInputError(f"voxels must be uint8, got {voxels.dtype}")
    R = voxels.shape[-1]
    if voxels.shape[-3:] != (R, R, R) or R < preset.crop:
        raise PolicyInputError(f"voxel grid must be cubic and at least {preset.crop}^3, got {tuple(voxels.shape[-3:])}")
    if ee.shape != (voxels.shape[0], To, 10):
        raise PolicyInputError(f"ee must be (B, {To}, 10), got {tuple(ee.shape)}")
    if not torch.isfinite(ee).all():
        raise PolicyInputError("ee (gripper state) contains NaN or inf")


class DiffusionPolicy(nn.Module):
    def __init__(self, name: str, preset: PolicyPreset, workspace: Workspace, model: nn.Module):
        super().__init__()
        self.name = name
        self.preset = preset
        self.workspace = workspace
        self.model = model
        self.normalizer: Normalizer | None = None
        self.noise_scheduler = make_train_scheduler(preset)
        self.action_freqs = action_space.freqs_for(preset.control)

    # --- normaliser -------------------------------------------------------------------
    def set_normalizer(self, normalizer: Normalizer) -> None:
        self.normalizer = normalizer

    @property
    def codec(self) -> ActionCodec:
        if self.normalizer is None:
            raise RuntimeError("policy has no normaliser: call set_normalizer(Normalizer.fit(...)) first")
        return ActionCodec(self.preset.control, self.normalizer)

    def config_dict(self) -> dict:
        """Everything besides weights that rebuilds this policy (saved in checkpoints)."""
        return {
            "policy": self.name,
            "preset": self.preset.to_dict(),
            "workspace": to_dict(self.workspace),
            "normalizer": None if self.normalizer is None else self.normalizer.to_dict(),
        }

    # --- shared pre-processing --------------------------------------------------------
    def prepare_input(self, voxels: torch.Tensor, ee: torch.Tensor, crop: str, generator=None):
        """The network's input from a batch's uint8 grids and gripper states: the one place training,
        evaluation and distillation build it (``crop``: "random" or "center", ``augment.voxel_input``)."""
        device = next(self.model.parameters()).device
        vox = augment.voxel_input(voxels, self.preset.crop, crop, generator, device)
        return vox, self.normalizer.normalize(ee.to(device).float())

    def compute_loss(
        self, batch: dict, generator: torch.Generator | None = None, noise_repeats: int = 1
    ) -> torch.Tensor:
        """Epsilon-prediction MSE. ``noise_repeats`` > 1 denoises that many independent (noise, step)
        draws per observation with one encoder pass: cheaper gradient variance reduction when the
        3D encoder dominates the step time (the paper trains with 1). With ``batch["weight"]`` (B,) each
        sample's MSE counts that much (``data.segments.SourceWeights``: corrections against demonstrations)."""
        voxels, ee, action = batch["voxels"], batch["ee"], batch["action"]
        check_obs(voxels, ee, self.preset)
        if action.shape[1:] != (self.preset.horizon, 10) or not torch.isfinite(action).all():
            raise PolicyInputError(f"action must be finite (B, {self.preset.horizon}, 10), got {tuple(action.shape)}")
        weight = batch.get("weight")
        if weight is not None and (
            weight.shape != action.shape[:1] or not torch.isfinite(weight).all() or (weight < 0).any()
        ):
            raise PolicyInputError(f"weight must be finite, >= 0 and (B,), got {tuple(weight.shape)}")
        codec = self.codec
        # Augment where the model runs: rotating 64^3 grids on a CPU core left a GPU idle for most of each
        # step.
        voxels = voxels.to(next(self.model.parameters()).device)
        if self.training and self.preset.rotation_aug != "none":
            voxels, ee, action = augment.random_rotation(
                voxels, ee.double(), action.double(), self.preset.rotation_aug, self.workspace.center, generator
            )
        vox, ee_n = self.prepare_input(voxels, ee, "random" if self.training else "center", generator)
        device = vox.device
        x0 = codec.encode(action.to(device).float(), ee[:, -1].to(device).float())
        cond = self.model.encode_obs(vox, ee_n)
        if noise_repeats > 1:
            x0 = x0.repeat_interleave(noise_repeats, 0)
            rows = cond.shape[0] // voxels.shape[0]  # cond rows per sample (group elements for EquiDiff)
            cond = cond.unflatten(0, (-1, rows)).repeat_interleave(noise_repeats, 0).flatten(0, 1)
        noise = torch.randn(x0.shape, generator=generator, device="cpu").to(device)
        t = torch.randint(0, self.preset.num_train_timesteps, (x0.shape[0],), generator=generator).to(device)
        noisy = self.noise_scheduler.add_noise(x0, noise, t)
        pred = self.model.denoise(noisy, t, cond)
        if weight is None:
            return F.mse_loss(pred, noise)
        per_sample = F.mse_loss(pred, noise, reduction="none").flatten(1).mean(1)
        return (per_sample * weight.to(device).float().repeat_interleave(noise_repeats)).mean()

    @torch.no_grad()
    def predict_action(
        self, obs: dict, generator: torch.Generator | None = None, noise: torch.Tensor | None = None
    ) -> dict:
        """obs {"voxels": uint8 (B, To, 4, R, R, R), "ee": (B, To, 10)} -> absolute actions.

        ``noise`` (B, horizon, D) fixes the initial DDIM sample (model space), e.g. for the
        sampling-equivariance check."""
        voxels, ee = obs["voxels"], obs["ee"]
        check_obs(voxels, ee, self.preset)
        codec = self.codec
        vox, ee_n = self.prepare_input(voxels, ee, "center")
        cond = self.model.encode_obs(vox, ee_n)
        B, H = voxels.shape[0], self.preset.horizon
        x = ddim_sample(
            self.model.denoise,
            cond,
            (B, H, codec.dim),
            make_inference_scheduler(self.preset),
            generator=generator,
            noise=noise,
            device=vox.device,
        )
        action_pred = codec.decode(x, ee[:, -1].to(x.device).float())
        start = self.preset.n_obs_steps - 1
        return {
            "action": action_pred[:, start : start + self.preset.n_action_steps],
            "action_pred": action_pred,
            "model_sample": x,
        }


def make_policy(name: str, preset: PolicyPreset, workspace: Workspace) -> DiffusionPolicy:
    freqs = action_space.freqs_for(preset.control)
    if name == "equidiff":
        from ..models.equivariant import (
            EquiNoisePredictor,  # escnn is imported only here
        )

        model = EquiNoisePredictor(preset, freqs)
    elif name == "baseline":
        from ..models.baseline import BaselineNoisePredictor

        model = BaselineNoisePredictor(preset, freqs)
    else:
        raise ValueError(f"unknown policy {name!r}; choose one of {POLICY_NAMES}")
    return DiffusionPolicy(name, preset, workspace, model)


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())
