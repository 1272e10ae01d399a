"""The EquiDiff noise predictor as plain torch modules: what an exported policy runs.

Its layers and their order mirror ``models.equivariant.EquiNoisePredictor`` exactly (both are
built from ``policy.presets.ENCODER_LAYOUTS`` and ``obs_embedding_relu``), so the escnn model's exported weights load into it
with ``load_state_dict(strict=True)``. Nothing here imports escnn.
"""

from __future__ import annotations

import contextlib
from contextvars import ContextVar

import torch
from torch import nn

from ..policy.presets import ENCODER_LAYOUTS, PolicyPreset
from . import action_space
from .unet1d import ConditionalUnet1D

# encoder_layer_specs' order; relu_before_pool_order() builds the old one (a context variable: scoped, thread-safe)
_POOL_BEFORE_RELU: ContextVar[bool] = ContextVar("pool_before_relu", default=True)


@contextlib.contextmanager
def relu_before_pool_order():
    """Encoders built inside have each ReLU before the max-pool after it, the order before
    ``encoder_layer_specs`` swapped them: the same function at the old cost, for the benches
    (``equidiff bench train --variants relu_before_pool``, ``equidiff bench policy --compare-relu-order``)."""
    token = _POOL_BEFORE_RELU.set(False)
    try:
        yield
    finally:
        _POOL_BEFORE_RELU.reset(token)


def encoder_layer_specs(preset: PolicyPreset, channels: list[int]) -> list[tuple]:
    """[(kind, in_ch, out_ch, kernel, padding) | ('relu',) | ('pool', k)] for channels[0..8].

    A max-pool that follows a conv's ReLU runs before it: ReLU is monotone, so relu(maxpool(x)) ==
    maxpool(relu(x)), and the ReLU then touches k³ times fewer values. At the first stage (56³, the
    largest tensors) that removed most of a compact training step's ReLU and its backward
    (docs/results/model.md, ``equidiff bench train --variants``). The modules hold no weights, so the order
    changes no state-dict key and every checkpoint loads either way."""
    specs = []
    c_in = channels[0]
    for kind, arg in ENCODER_LAYOUTS[preset.encoder_layout]:
        if kind == "pool":
            if _POOL_BEFORE_RELU.get() and specs and specs[-1] == ("relu",):
                specs.insert(len(specs) - 1, ("pool", arg))
            else:
                specs.append(("pool", arg))
            continue
        c_out = channels[arg + 1]
        kernel, pad = {"conv": (3, 1), "conv0": (3, 0), "conv1x1": (1, 0)}[kind]
        specs += [("conv", c_in, c_out, kernel, pad), ("relu",)]
        c_in = c_out
    return specs


def obs_embedding_relu(preset: PolicyPreset) -> bool:
    """Whether a ReLU follows the observation embedding: only in the legacy layout (the official
    code's ``enc_out`` is a bare equivariant Linear)."""
    return preset.encoder_layout == "legacy"


def build_plain_encoder(preset: PolicyPreset, channels: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for spec in encoder_layer_specs(preset, channels):
        if spec[0] == "conv":
            _, c_in, c_out, k, pad = spec
            layers.append(nn.Conv3d(c_in, c_out, k, padding=pad))
        elif spec[0] == "relu":
            layers.append(nn.ReLU(inplace=True))
        else:
            layers.append(nn.MaxPool3d(spec[1]))
    return nn.Sequential(*layers)


def to_escnn_layout(voxels: torch.Tensor) -> torch.Tensor:
    """(B, C, X, Y, Z) -> (B, C, Z, X, Y): escnn's rot2dOnR3 rotates about the first spatial axis,
    and rot90 from its 2nd to 3rd spatial axis is +90 deg, the same as geometry.rotate_voxel_grid."""
    return voxels.permute(0, 1, 4, 2, 3)


def from_escnn_layout(voxels: torch.Tensor) -> torch.Tensor:
    """The inverse of ``to_escnn_layout``: (B, C, Z, X, Y) -> (B, C, X, Y, Z), a view."""
    return voxels.permute(0, 1, 3, 4, 2)


class EquiNoiseCore(nn.Module):
    """Shape plumbing shared by the escnn and the plain model (subclasses supply the layers)."""

    group_order: int
    action_dim: int

    def _init_common(self, preset: PolicyPreset, action_freqs: tuple[int, ...]):
        self.preset = preset
        self.group_order = preset.group_order
        self.action_freqs = tuple(action_freqs)
        self.action_dim = action_space.dim_of(self.action_freqs)
        self.register_buffer("ee_order", torch.tensor(action_space.ABS_ORDER), persistent=False)
        self.unet = ConditionalUnet1D(
            input_dim=preset.action_hidden,
            global_cond_dim=preset.obs_hidden,
            diffusion_step_embed_dim=preset.diffusion_step_embed_dim,
            down_dims=tuple(preset.down_dims),
            kernel_size=preset.kernel_size,
            n_groups=preset.n_groups,
        )

    # subclasses: _encode_voxels(x) -> (B', F*N); _obs_linear(x) -> (B, H*N); _action_enc(x); _action_dec(x)

    def encode_obs(self, voxels: torch.Tensor, ee: torch.Tensor) -> torch.Tensor:
        """voxels (B, To, C, S, S, S) float in [0, 1], ee (B, To, 10) normalised -> cond (B*N, obs_hidden)."""
        B, _To = voxels.shape[:2]
        feats = self._encode_voxels(to_escnn_layout(voxels.flatten(0, 1))).reshape(B, -1)
        ee_field = ee.index_select(-1, self.ee_order).reshape(B, -1).to(feats.dtype)
        h = self._obs_linear(torch.cat([feats, ee_field], dim=1))  # (B, H*N), field-major
        N = self.group_order
        return h.reshape(B, -1, N).transpose(1, 2).reshape(B * N, -1)

    def denoise(self, sample: torch.Tensor, timestep: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """sample (B, T, D) model-space vectors, timestep (B,), cond from encode_obs -> epsilon (B, T, D)."""
        return self.denoise_films(sample, self.unet.films(timestep, cond))  # cond has B*N rows

    def denoise_films(self, sample: torch.Tensor, films: torch.Tensor) -> torch.Tensor:
        """``denoise`` with the U-Net's FiLM terms given (B*N rows, ConditionalUnet1D.films)."""
        B, T, D = sample.shape
        N = self.group_order
        a = self._action_enc(sample.reshape(B * T, D).to(films.dtype))  # (B*T, A*N)
        a = a.reshape(B, T, -1, N).permute(0, 3, 2, 1).reshape(B * N, -1, T)  # each group element is a batch row
        out = self.unet.forward_films(a, films)  # (B*N, A, T)
        out = out.reshape(B, N, -1, T).permute(0, 3, 2, 1).reshape(B * T, -1)
        return self._action_dec(out).reshape(B, T, D)

    def forward(self, sample, timestep, voxels, ee):
        return self.denoise(sample, timestep, self.encode_obs(voxels, ee))


class PlainEquiNoisePredictor(EquiNoiseCore):
    def __init__(self, preset: PolicyPreset, action_freqs: tuple[int, ...]):
        super().__init__()
        self._init_common(preset, action_freqs)
        N = preset.group_order
        channels = [preset.voxel_channels] + [f * N for f in preset.encoder_channels]
        self.encoder = build_plain_encoder(preset, channels)
        obs_in = preset.n_obs_steps * (preset.encoder_channels[-1] * N + action_space.dim_of(action_space.EE_FREQS))
        obs_layers = [nn.Linear(obs_in, preset.obs_hidden * N)] + ([nn.ReLU()] if obs_embedding_relu(preset) else [])
        self.obs_linear = nn.Sequential(*obs_layers)
        self.action_enc = nn.Sequential(nn.Linear(self.action_dim, preset.action_hidden * N), nn.ReLU())
        self.action_dec = nn.Linear(preset.action_hidden * N, self.action_dim)

    def _encode_voxels(self, x):
        return self.encoder(x)

    def _obs_linear(self, x):
        return self.obs_linear(x)

    def _action_enc(self, x):
        return self.action_enc(x)

    def _action_dec(self, x):
        return self.action_dec(x)
