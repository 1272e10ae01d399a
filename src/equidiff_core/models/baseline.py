"""DiffPo-C (Vo): the paper's baseline. A plain 3D conv encoder over the same cropped voxel grid
(same layer layout as the equivariant encoder, channels scaled to about the same parameter
count), the gripper state concatenated as the U-Net's global condition, the same U-Net.
Plain torch: it trains, exports and runs without escnn.
"""

from __future__ import annotations

import torch
from torch import nn

from ..presets import PolicyPreset
from . import action_space
from .plain import build_plain_encoder
from .unet1d import ConditionalUnet1D

# Plain channels = round(scale * regular fields) gives the equivariant C8 encoder's parameter
# count within ~3 % for all presets (measured, official layout: paper 1.3006 M vs 1.3012 M, compact
# 124.0k vs 121.3k, tiny 5.5k vs 5.4k). The legacy layout keeps its scale, so that baseline
# checkpoints saved with it rebuild the network they were trained with.
MATCH_SCALE = {"official": 1.72, "legacy": 1.77}


def matched_channels(preset: PolicyPreset) -> tuple[int, ...]:
    if preset.baseline_channels is not None:
        return tuple(preset.baseline_channels)
    scale = MATCH_SCALE[preset.encoder_layout]
    return tuple(max(1, round(scale * f)) for f in preset.encoder_channels)


class BaselineNoisePredictor(nn.Module):
    def __init__(self, preset: PolicyPreset, action_freqs: tuple[int, ...]):
        super().__init__()
        self.preset = preset
        self.action_freqs = tuple(action_freqs)
        self.action_dim = action_space.dim_of(self.action_freqs)
        channels = [preset.voxel_channels, *matched_channels(preset)]
        self.encoder = build_plain_encoder(preset, channels)
        cond_dim = preset.n_obs_steps * (channels[-1] + action_space.dim_of(action_space.EE_FREQS))
        self.unet = ConditionalUnet1D(
            input_dim=self.action_dim,
            global_cond_dim=cond_dim,
            diffusion_step_embed_dim=preset.diffusion_step_embed_dim,
            down_dims=tuple(preset.down_dims),
            kernel_size=preset.kernel_size,
            n_groups=preset.n_groups,
        )

    def encode_obs(self, voxels: torch.Tensor, ee: torch.Tensor) -> torch.Tensor:
        B = voxels.shape[0]
        feats = self.encoder(voxels.flatten(0, 1)).reshape(B, -1)
        return torch.cat([feats, ee.reshape(B, -1).to(feats.dtype)], dim=1)

    def denoise(self, sample: torch.Tensor, timestep: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        return self.denoise_films(sample, self.unet.films(timestep, cond))

    def denoise_films(self, sample: torch.Tensor, films: torch.Tensor) -> torch.Tensor:
        """``denoise`` with the U-Net's FiLM terms given (ConditionalUnet1D.films)."""
        return self.unet.forward_films(sample.transpose(1, 2).to(films.dtype), films).transpose(1, 2)

    def forward(self, sample, timestep, voxels, ee):
        return self.denoise(sample, timestep, self.encode_obs(voxels, ee))

    def export_plain(self) -> BaselineNoisePredictor:
        return self
