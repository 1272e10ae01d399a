"""Typed model presets: the network sizes and diffusion settings saved inside every checkpoint.

* ``paper``: the sizes of the paper's real-robot EquiDiff (Vo): C8, encoder regular fields
  8→16→16→32→32→64→64→128 over a 58³ crop of the 64³ grid, U-Net down_dims 256/512/1024,
  horizon 16, one observation step, 8 executed steps. Needs a GPU for 5 Hz.
* ``compact``: same structure, fewer channels early in the encoder (they dominate the cost at
  58³) and a narrower U-Net, so DDIM-16 runs at 5 Hz with margin on a 2-core CPU.
* ``tiny``: for other areas' fast tests (one training step well under a second on a CPU).

Presets are frozen dataclasses built with ``config.from_dict``, so a checkpoint's saved preset
is validated the same way as a hand-written one.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from .config import ConfigError, from_dict, to_dict

CONTROL_MODES = ("absolute", "relative")
ROTATION_AUGS = ("none", "c4", "c8", "continuous")


@dataclass(frozen=True)
class PolicyPreset:
    name: str
    # Equivariant voxel encoder: regular fields of the 8 conv layers (channels = fields * group order).
    encoder_channels: tuple[int, ...] = (8, 16, 16, 32, 32, 64, 64, 128)
    group_order: int = 8  # C_N about the vertical axis
    # Non-equivariant baseline encoder: plain channels per layer (None: chosen to match the
    # equivariant encoder's parameter count, see models.baseline.matched_channels).
    baseline_channels: tuple[int, ...] | None = None
    obs_hidden: int = 128  # regular fields of the observation embedding (U-Net cond per group element)
    action_hidden: int = 64  # regular fields of the action embedding (U-Net input channels)
    down_dims: tuple[int, ...] = (256, 512, 1024)
    kernel_size: int = 5
    n_groups: int = 8  # GroupNorm groups in the U-Net
    diffusion_step_embed_dim: int = 256
    horizon: int = 16
    n_obs_steps: int = 1
    n_action_steps: int = 8
    crop: int = 58
    voxel_channels: int = 4  # occupancy + RGB
    dt: float = 0.2  # s between actions (5 Hz)
    num_train_timesteps: int = 100
    num_inference_steps: int = 16
    beta_schedule: str = "squaredcos_cap_v2"
    control: str = "absolute"
    rotation_aug: str = "continuous"  # rotate voxels + gripper state + actions together while training

    def __post_init__(self):
        if len(self.encoder_channels) != 8:
            raise ValueError(
                f"encoder_channels must have 8 entries (one per conv layer), got {len(self.encoder_channels)}"
            )
        if self.baseline_channels is not None and len(self.baseline_channels) != 8:
            raise ValueError(f"baseline_channels must have 8 entries, got {len(self.baseline_channels)}")
        if self.control not in CONTROL_MODES:
            raise ValueError(f"control must be one of {CONTROL_MODES}, got {self.control!r}")
        if self.rotation_aug not in ROTATION_AUGS:
            raise ValueError(f"rotation_aug must be one of {ROTATION_AUGS}, got {self.rotation_aug!r}")
        if not 1 <= self.n_action_steps <= self.horizon:
            raise ValueError(f"n_action_steps must be in 1..horizon ({self.horizon}), got {self.n_action_steps}")
        if self.horizon % (2 ** (len(self.down_dims) - 1)):
            raise ValueError(f"horizon {self.horizon} must be divisible by 2^{len(self.down_dims) - 1} (U-Net levels)")
        if self.group_order % 4:
            raise ValueError(
                f"group_order must be a multiple of 4 (C4 must be exact on the grid), got {self.group_order}"
            )
        if not 1 <= self.num_inference_steps <= self.num_train_timesteps:
            raise ValueError("num_inference_steps must be in 1..num_train_timesteps")
        if encoder_output_size(self.crop) != 1:
            raise ValueError(f"crop {self.crop} does not reduce to 1 voxel through the encoder (use 58)")
        for d in self.down_dims:
            if d % self.n_groups:
                raise ValueError(f"down_dims {self.down_dims} must be multiples of n_groups {self.n_groups}")

    def to_dict(self) -> dict:
        return to_dict(self)

    def replace(self, **changes) -> PolicyPreset:
        return dataclasses.replace(self, **changes)


# The encoder's layers: (kind, index or size). Conv layers are numbered 0..7 into encoder_channels;
# 'conv' pads by 1 (same size), 'conv0' pads by 0 (shrinks by 2), 'conv1x1' is the last layer at 1³
# (a 3³ kernel with padding 1 there only ever uses its centre tap). Shared with the plain-torch
# inference model so the two cannot drift apart.
ENCODER_LAYOUT = (
    ("conv", 0),
    ("pool", 2),  # 58 -> 29
    ("conv", 1),
    ("conv0", 2),
    ("pool", 3),  # 29 -> 27 -> 9
    ("conv", 3),
    ("conv", 4),
    ("pool", 3),  # 9 -> 3
    ("conv", 5),
    ("conv", 6),
    ("pool", 3),  # 3 -> 1
    ("conv1x1", 7),
)


def encoder_output_size(crop: int) -> int:
    size = crop
    for kind, arg in ENCODER_LAYOUT:
        if kind == "conv0":
            size -= 2
        elif kind == "pool":
            if size % arg:
                return -1
            size //= arg
    return size


PRESETS: dict[str, PolicyPreset] = {
    "paper": PolicyPreset(name="paper"),
    # Measured cost on the 2-core CPU (see docs/model.md): the 58^3 and 27^3 convolutions
    # dominate, so the first fields are cut hardest; the U-Net runs once per group element (8 rows).
    "compact": PolicyPreset(
        name="compact",
        encoder_channels=(1, 2, 4, 8, 16, 32, 32, 64),
        obs_hidden=32,
        action_hidden=16,
        down_dims=(32, 64, 128),
        kernel_size=5,
        diffusion_step_embed_dim=64,
    ),
    "tiny": PolicyPreset(
        name="tiny",
        encoder_channels=(1, 1, 2, 2, 2, 4, 4, 8),
        obs_hidden=16,
        action_hidden=8,
        down_dims=(32, 64),
        kernel_size=3,
        diffusion_step_embed_dim=32,
    ),
}


def get_preset(name: str, **overrides) -> PolicyPreset:
    """A named preset, optionally with fields replaced (validated again)."""
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; available: {sorted(PRESETS)}")
    preset = PRESETS[name]
    if overrides:
        try:
            preset = dataclasses.replace(preset, **overrides)
        except (TypeError, ValueError) as err:
            raise ConfigError(f"preset {name}: {err}") from err
    return preset


def preset_from_dict(data: dict) -> PolicyPreset:
    return from_dict(PolicyPreset, data, where="preset")
