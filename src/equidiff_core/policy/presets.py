"""Typed model presets: the network sizes and diffusion settings saved inside every checkpoint.

* ``paper``: the official EquiDiff code's voxel policy (pointW/equidiff,
  ``train_equi_diffusion_unet_voxel_abs.yaml``): C8, its 58³ voxel encoder
  (``EquivariantVoxelEncoder58Cyclic``: regular fields 8→16→16→32→32→64→64→128, layout
  ``ENCODER_LAYOUTS["official"]``), an observation embedding of 128 regular fields, action
  embedding 64, U-Net down_dims 256/512/1024 kernel 5, horizon 16, one observation step, 8
  executed steps. Differences from it: no wrist camera (the official policy adds a ResNet-18 on
  the in-hand image), the gripper state is one width instead of two finger positions, and a
  256-wide diffusion-step embedding (the official config uses 128); docs/results/model.md counts both.
  Needs a GPU for 5 Hz.
* ``compact``: the same stages with fewer channels (the early ones dominate the cost at 58³) and
  a narrower U-Net, so DDIM-16 runs at 5 Hz with margin on a 2-core CPU.
* ``tiny``: for other areas' fast tests (one training step well under a second on a CPU).

Each also sets the baseline's (DiffPo-C, Vo) encoder: the official ``CNNVoxelEncoder58`` layout at
width ``baseline_width``, He-initialised (``models.baseline``).

``encoder_layout`` picks the encoder's stages: ``official`` (above) or ``legacy`` (this project's
first layout: max-pools 29 → 27 → 9 → 3 → 1, a 1³ last layer, and a ReLU after the observation
embedding). Checkpoints saved before the field existed were trained with ``legacy``, so
``preset_from_dict`` reads a missing field as ``legacy``.

Presets are frozen dataclasses built with ``config.from_dict``, so a checkpoint's saved preset
is validated the same way as a hand-written one.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ..config import ConfigError, from_dict, to_dict

CONTROL_MODES = ("absolute", "relative")
ROTATION_AUGS = ("none", "c4", "c8", "continuous")
BASELINE_INITS = ("torch", "he")

# The encoder's stages, numbered 0..7 into encoder_channels: ('conv', i) a 3³ conv with padding 1
# (same size), ('conv0', i) a 3³ conv without padding (shrinks by 2), ('conv1x1', i) a 1³ conv, each
# followed by a ReLU; ('pool', k) a k³ max-pool. Shared with the plain-torch inference model and the
# baseline so that they cannot drift apart.
ENCODER_LAYOUTS = {
    # EquivariantVoxelEncoder58Cyclic of the official code; the last 3³ conv sees the whole 3³ grid
    "official": (
        ("conv0", 0),  # 58 -> 56
        ("pool", 2),  # 28
        ("conv", 1),
        ("conv", 2),
        ("pool", 2),  # 14
        ("conv0", 3),  # 12
        ("conv", 4),
        ("pool", 2),  # 6
        ("conv", 5),
        ("conv", 6),
        ("pool", 2),  # 3
        ("conv0", 7),  # 1
    ),
    # this project's first layout; kept so that checkpoints trained with it load as they were trained
    "legacy": (
        ("conv", 0),
        ("pool", 2),  # 58 -> 29
        ("conv", 1),
        ("conv0", 2),  # 27
        ("pool", 3),  # 9
        ("conv", 3),
        ("conv", 4),
        ("pool", 3),  # 3
        ("conv", 5),
        ("conv", 6),
        ("pool", 3),  # 1
        ("conv1x1", 7),  # a 3³ kernel with padding 1 would only ever use its centre tap at 1³
    ),
}


@dataclass(frozen=True)
class PolicyPreset:
    name: str
    # Equivariant voxel encoder: regular fields of the 8 conv layers (channels = fields * group order).
    encoder_channels: tuple[int, ...] = (8, 16, 16, 32, 32, 64, 64, 128)
    group_order: int = 8  # C_N about the vertical axis
    # Non-equivariant baseline (DiffPo-C, Vo) encoder. baseline_width: the official CNNVoxelEncoder58's
    # n_hidden, channels n/16, n/8, n/8, n/4, n/4, n/2, n/2, n (pointW/equidiff's voxel config uses 256).
    # Without it, baseline_channels gives the 8 convolutions' channels, and without those they are matched
    # to the equivariant encoder's parameter count (the baselines trained before baseline_width existed;
    # see models.baseline.baseline_encoder_channels).
    baseline_width: int | None = None
    baseline_channels: tuple[int, ...] | None = None
    # How the baseline's convolutions start: "torch" (PyTorch's default, as the official code leaves them)
    # or "he" (He-normal weights, zero biases: what escnn gives EquiDiff's convolutions). docs/results/model.md
    # measures why it matters: with "torch" the block's signal fades ~2.5x per layer.
    baseline_init: str = "torch"
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
    encoder_layout: str = "official"  # key of ENCODER_LAYOUTS; 'legacy' adds a ReLU after the observation embedding

    def __post_init__(self):
        if len(self.encoder_channels) != 8:
            raise ValueError(
                f"encoder_channels must have 8 entries (one per conv layer), got {len(self.encoder_channels)}"
            )
        if self.baseline_channels is not None and len(self.baseline_channels) != 8:
            raise ValueError(f"baseline_channels must have 8 entries, got {len(self.baseline_channels)}")
        if self.baseline_width is not None and (self.baseline_width < 16 or self.baseline_width % 16):
            raise ValueError(
                f"baseline_width must be a multiple of 16 (its first layer has n/16), got {self.baseline_width}"
            )
        if self.baseline_init not in BASELINE_INITS:
            raise ValueError(f"baseline_init must be one of {BASELINE_INITS}, got {self.baseline_init!r}")
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
        if self.encoder_layout not in ENCODER_LAYOUTS:
            raise ValueError(f"encoder_layout must be one of {tuple(ENCODER_LAYOUTS)}, got {self.encoder_layout!r}")
        if encoder_output_size(self.crop, self.encoder_layout) != 1:
            raise ValueError(f"crop {self.crop} does not reduce to 1 voxel through the encoder (use 58)")
        for d in self.down_dims:
            if d % self.n_groups:
                raise ValueError(f"down_dims {self.down_dims} must be multiples of n_groups {self.n_groups}")

    def to_dict(self) -> dict:
        return to_dict(self)

    def replace(self, **changes) -> PolicyPreset:
        return dataclasses.replace(self, **changes)


def encoder_sizes(crop: int, layout: str) -> list[int]:
    """The grid's edge after each stage of ``ENCODER_LAYOUTS[layout]`` (-1 from a stage that cannot apply on)."""
    sizes, size = [], crop
    for kind, arg in ENCODER_LAYOUTS[layout]:
        if kind == "conv0":
            size = size - 2 if size > 2 else -1
        elif kind == "pool":
            size = size // arg if size > 0 and size % arg == 0 else -1
        sizes.append(size)
    return sizes


def encoder_output_size(crop: int, layout: str) -> int:
    return encoder_sizes(crop, layout)[-1]


# DiffPo-C (Vo)'s width per preset: paper the official voxel config's enc_n_hidden (256); compact 128,
# whose first layer has EquiDiff compact's 8 channels at 56³ (one C8 regular field) and whose training
# step costs about half EquiDiff's (docs/results/model.md); tiny the smallest with 2 first-layer channels. All start
# He-initialised, as escnn starts EquiDiff's convolutions (docs/results/model.md: with PyTorch's default the
# baseline's features did not respond to the block).
PRESETS: dict[str, PolicyPreset] = {
    "paper": PolicyPreset(name="paper", baseline_width=256, baseline_init="he"),
    # Measured cost on a CPU (docs/results/model.md, "Training"): the 56^3 and 28^3 convolutions
    # dominate, so the first fields are cut hardest; the 12^3 and 6^3 stages of the official layout
    # cost more than the legacy 9^3 and 3^3 ones, so they are halved against the legacy compact
    # (16, 32, 32): a training step then costs a little more than the legacy compact's.
    # The U-Net runs once per group element (8 rows).
    "compact": PolicyPreset(
        name="compact",
        encoder_channels=(1, 2, 4, 8, 8, 16, 16, 64),
        obs_hidden=32,
        action_hidden=16,
        down_dims=(32, 64, 128),
        kernel_size=5,
        diffusion_step_embed_dim=64,
        baseline_width=128,
        baseline_init="he",
    ),
    "tiny": PolicyPreset(
        name="tiny",
        encoder_channels=(1, 1, 2, 2, 2, 4, 4, 8),
        obs_hidden=16,
        action_hidden=8,
        down_dims=(32, 64),
        kernel_size=3,
        diffusion_step_embed_dim=32,
        baseline_width=32,
        baseline_init="he",
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
    """A saved preset; one saved before ``encoder_layout`` existed was trained with the legacy layout."""
    if isinstance(data, dict) and "encoder_layout" not in data:
        data = {**data, "encoder_layout": "legacy"}
    return from_dict(PolicyPreset, data, where="preset")
