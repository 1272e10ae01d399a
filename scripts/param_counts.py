"""Parameter counts of our EquiDiff presets beside the official EquiDiff voxel policy's (docs/model.md).

    PYTHONPATH=src python scripts/param_counts.py

Ours: ``count_parameters`` of ``make_policy("equidiff", preset)``'s encoder and of its whole noise
predictor, per preset and encoder layout. Official (pointW/equidiff, ``DiffusionEquiUNetPolicyVoxel``
with ``train_equi_diffusion_unet_voxel_abs.yaml``: enc_n_hidden 128, diffusion_step_embed_dim 128,
down_dims 256/512/1024, kernel 5, 8 groups, act_emb_dim 64, C8) counted from its layout, not its code:

* voxel encoder (``EquivariantVoxelEncoder58Cyclic``): the same stages, fields and escnn defaults as
  our ``paper`` preset's encoder (layout ``official``), so it is that module's count;
* ``enc_out``: an escnn Linear from 128 regular fields (voxels) + 128 trivial (wrist camera) + 4 rho1
  + 3 trivial (gripper pose, z, two finger positions) to 128 regular fields, built here with escnn;
* wrist camera (``InHandEncoder``): torchvision's ResNet-18 without its pooling and fc, norm layers
  replaced by Identity (bias-free convolutions only), and robomimic's SpatialSoftmax with 64
  keypoints (one 1x1 Conv2d 512 -> 64 with bias);
* ``EquiDiffusionUNet``: Diffusion Policy's ConditionalUnet1D (ours has its layout, see
  models/unet1d.py) with the sizes above, plus the equivariant action Linear in and out: our
  ``paper`` preset's U-Net and action layers with diffusion_step_embed_dim 128.
"""

from __future__ import annotations

import json

from escnn import nn as enn

from equidiff_core.config import Workspace
from equidiff_core.policy.diffusion import count_parameters, make_policy
from equidiff_core.policy.presets import PRESETS, get_preset


def resnet18_trunk_params() -> int:
    """torchvision resnet18's convolutions (bias-free) up to layer4, with norm_layer=Identity."""
    n = 3 * 64 * 7 * 7  # stem
    c_in = 64
    for c in (64, 128, 256, 512):
        first = 9 * c_in * c + 9 * c * c + (c_in * c if c != c_in else 0)  # two 3x3 convs + 1x1 downsample
        n += first + 2 * 9 * c * c  # second BasicBlock
        c_in = c
    return n


def official_counts() -> dict:
    ws = Workspace()
    ours = make_policy("equidiff", get_preset("paper", diffusion_step_embed_dim=128), ws).model
    voxel_encoder = count_parameters(ours.encoder)
    gp = ours.point_space
    G = gp.fibergroup
    enc_in = enn.FieldType(
        gp,
        128 * [G.regular_representation]
        + 128 * [G.trivial_representation]
        + 4 * [G.irrep(1)]
        + 3 * [G.trivial_representation],
    )
    enc_out = count_parameters(enn.Linear(enc_in, enn.FieldType(gp, 128 * [G.regular_representation])))
    wrist = resnet18_trunk_params() + 512 * 64 + 64
    unet = sum(count_parameters(m) for m in (ours.unet, ours.action_enc, ours.action_dec))
    return {
        "voxel_encoder": voxel_encoder,
        "enc_out": enc_out,
        "wrist_camera": wrist,
        "equi_unet": unet,
        "whole": voxel_encoder + enc_out + wrist + unet,
        "whole_without_wrist_camera": voxel_encoder + enc_out + unet,
    }


def our_counts() -> list[dict]:
    ws = Workspace()
    rows = []
    for name in PRESETS:
        for layout in ("official", "legacy"):
            model = make_policy("equidiff", get_preset(name, encoder_layout=layout), ws).model
            rows.append(
                {
                    "preset": name,
                    "encoder_layout": layout,
                    "encoder": count_parameters(model.encoder),
                    "obs_embedding": count_parameters(model.obs_linear),
                    "whole": count_parameters(model),
                }
            )
    return rows


if __name__ == "__main__":
    print(json.dumps({"official": official_counts(), "ours": our_counts()}))
