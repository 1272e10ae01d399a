"""What a policy costs per sample, counted rather than timed: parameters and FLOPs (torch's FlopCounterMode,
which counts the convolutions' and matrix products' multiply-adds as 2 FLOPs each; elementwise work is not
counted).

* ``encoder_flops``, ``denoise_step_flops``: the exported plain-torch network (what a robot runs) on one
  observation, its voxel encoder and one denoising step (the whole U-Net: EquiDiff runs it once per
  group element); ``ddim16_flops`` = encoder + 16 steps (the FiLM split saves a little of that);
  ``encoder_flops`` is also what ``equidiff bench policy`` divides by the encoder's time;
* ``train_step_flops``: one training step's forward and backward (``compute_loss`` with ``noise_repeats``
  draws per encoder pass, escnn's filter expansion included for EquiDiff), per sample of a batch.
"""

from __future__ import annotations

import torch
from torch.utils.flop_counter import FlopCounterMode

from ..models.equivariance import random_observation
from ..policy.augment import voxel_input
from ..policy.diffusion import count_parameters


def _flops(fn) -> int:
    counter = FlopCounterMode(display=False)
    with counter:
        fn()
    return int(counter.get_total_flops())


def encoder_flops(net, preset) -> int:
    """FLOPs of ``net.encode_obs`` (a plain-torch network as exported, ``policy.file.build_plain_network``,
    before any CPU kernel swap) on one observation: the voxel encoder and the observation embedding."""
    vox = torch.zeros(1, preset.n_obs_steps, preset.voxel_channels, *(preset.crop,) * 3)
    ee = torch.zeros(1, preset.n_obs_steps, 10)
    with torch.no_grad():
        return _flops(lambda: net.encode_obs(vox, ee))


def policy_cost(policy, batch: int = 4, noise_repeats: int = 1) -> dict:
    """Parameters and FLOPs per sample of ``policy`` (a ``policy.diffusion.DiffusionPolicy`` with its normaliser set)."""
    preset = policy.preset
    net = policy.model.export_plain().eval()
    vox, ee = random_observation(policy, batch=batch, seed=0)
    x = voxel_input(vox, preset.crop, "center")
    ee_n = policy.normalizer.normalize(ee.float())
    with torch.no_grad():
        cond = net.encode_obs(x[:1], ee_n[:1])
        sample = torch.zeros(1, preset.horizon, policy.codec.dim)
        encoder = encoder_flops(net, preset)
        step = _flops(lambda: net.denoise(sample, torch.tensor([10]), cond))
    action = policy.predict_action({"voxels": vox, "ee": ee})["action_pred"].float()
    batch_dict = {"voxels": vox, "ee": ee, "action": action}
    policy.train()

    def train_step():
        loss = policy.compute_loss(batch_dict, generator=torch.Generator().manual_seed(0), noise_repeats=noise_repeats)
        loss.backward()

    train = _flops(train_step)
    policy.model.zero_grad(set_to_none=True)
    policy.eval()
    return {
        "params": count_parameters(policy.model),
        "encoder_params": count_parameters(policy.model.encoder),
        "encoder_flops": encoder,
        "denoise_step_flops": step,
        "ddim16_flops": encoder + 16 * step,
        "train_step_flops_per_sample": train // batch,
        "noise_repeats": noise_repeats,
    }
