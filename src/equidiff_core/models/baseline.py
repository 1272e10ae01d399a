"""DiffPo-C (Vo): the paper's baseline. A plain 3D conv encoder over the same cropped voxel grid, the
gripper state concatenated as the U-Net's global condition, the same U-Net. Plain torch: it trains,
exports and runs without escnn.

The encoder is the official code's ``CNNVoxelEncoder58`` (pointW/equidiff,
``diffusion_unet_voxel_policy.py``): the same stages as EquiDiff's encoder (``policy.presets.ENCODER_LAYOUTS``),
conv + ReLU, four max-pools, channels n/16, n/8, n/8, n/4, n/4, n/2, n/2, n for one width n
(``preset.baseline_width``, its ``enc_n_hidden``). ``preset.baseline_init`` "he" starts its
convolutions the way escnn starts EquiDiff's (He-normal, zero biases) instead of PyTorch's default,
under which the block's signal fades by the last layer (docs/results/model.md, "The baseline that learns").
"""

from __future__ import annotations

import torch
from torch import nn

from ..policy.presets import PolicyPreset
from . import action_space
from .plain import build_plain_encoder
from .sparse_stage import conv_pool_occupied, is_conv_pool_stage, sparse_first_stage_enabled
from .unet1d import ConditionalUnet1D

# Plain channels = round(scale * regular fields) gives the equivariant C8 encoder's parameter
# count within ~3 % for all presets (measured, official layout: paper 1.3006 M vs 1.3012 M, compact
# 124.0k vs 121.3k, tiny 5.5k vs 5.4k). The baselines trained before ``baseline_width`` existed were
# built this way (their saved presets have neither width nor channels), so they rebuild as trained;
# the legacy layout keeps its own scale for the same reason.
MATCH_SCALE = {"official": 1.72, "legacy": 1.77}
# CNNVoxelEncoder58's channels as divisors of its n_hidden, layer by layer
OFFICIAL_WIDTH_DIVISORS = (16, 8, 8, 4, 4, 2, 2, 1)


def official_channels(width: int) -> tuple[int, ...]:
    return tuple(width // d for d in OFFICIAL_WIDTH_DIVISORS)


def matched_channels(preset: PolicyPreset) -> tuple[int, ...]:
    scale = MATCH_SCALE[preset.encoder_layout]
    return tuple(max(1, round(scale * f)) for f in preset.encoder_channels)


def baseline_encoder_channels(preset: PolicyPreset) -> tuple[int, ...]:
    """The 8 convolutions' output channels: ``baseline_width``'s official pattern, else
    ``baseline_channels``, else matched to the equivariant encoder's parameter count."""
    if preset.baseline_width is not None:
        return official_channels(preset.baseline_width)
    if preset.baseline_channels is not None:
        return tuple(preset.baseline_channels)
    return matched_channels(preset)


def he_init_(encoder: nn.Module) -> None:
    """He-normal weights (fan-in, ReLU gain) and zero biases for every convolution of ``encoder``."""
    for module in encoder.modules():
        if isinstance(module, nn.Conv3d):
            nn.init.kaiming_normal_(module.weight, nonlinearity="relu")
            nn.init.zeros_(module.bias)


class BaselineNoisePredictor(nn.Module):
    def __init__(self, preset: PolicyPreset, action_freqs: tuple[int, ...]):
        super().__init__()
        self.preset = preset
        self.action_freqs = tuple(action_freqs)
        self.action_dim = action_space.dim_of(self.action_freqs)
        channels = [preset.voxel_channels, *baseline_encoder_channels(preset)]
        self.encoder = build_plain_encoder(preset, channels)
        if preset.baseline_init == "he":
            he_init_(self.encoder)
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
        x = voxels.flatten(0, 1)
        conv, pool = self.encoder[:2]
        if sparse_first_stage_enabled(x) and isinstance(pool, nn.MaxPool3d) and is_conv_pool_stage(conv, pool):
            feats = self.encoder[2:](conv_pool_occupied(x, conv.weight, conv.bias))  # channels-last from there
        else:
            # channels-last 3D: oneDNN's fast layout for these few-channel convolutions (measured with `equidiff
            # bench train --variants`, docs/results/model.md; EquiDiff's escnn convolutions gained nothing from it)
            feats = self.encoder(x.contiguous(memory_format=torch.channels_last_3d))
        feats = feats.reshape(B, -1)
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
