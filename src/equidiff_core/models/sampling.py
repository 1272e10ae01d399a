"""Shared by training and the exported policy (no escnn): diffusers schedulers, DDIM sampling,
and the codec between absolute 10-D actions and the model-space vectors the network denoises."""

from __future__ import annotations

import itertools

import numpy as np
import torch
from diffusers import DDIMScheduler, DDPMScheduler
from diffusers.schedulers.scheduling_ddim import DDIMSchedulerOutput

from .. import geometry
from ..policy.normalizer import Normalizer
from ..policy.presets import PolicyPreset
from . import action_space


def make_train_scheduler(preset: PolicyPreset) -> DDPMScheduler:
    return DDPMScheduler(
        num_train_timesteps=preset.num_train_timesteps,
        beta_schedule=preset.beta_schedule,
        prediction_type="epsilon",
        clip_sample=True,
    )


# How DDIM spaces its timesteps over the training schedule (diffusers' ``timestep_spacing``). "leading", the
# policies' own, starts k steps at T - T/k (one step: at t = 0, the noise returned as it is); "trailing"
# always starts at T - 1, as few-step samplers do (docs/denoising_steps.md).
TIMESTEP_SPACINGS = ("leading", "trailing")


def uniform_timesteps(num_train_timesteps: int, steps: int, first: int) -> list[int]:
    """``steps`` timesteps from ``first`` down, ``num_train_timesteps // steps`` apart, the last step landing on
    the clean sample: the sampler the first distilled policy files name by their ``first_timestep`` (read as
    these timesteps, ``sampler_timesteps``). ValueError where the steps do not fit in the schedule or would end
    before t = 0."""
    stride = num_train_timesteps // steps if steps >= 1 else 0
    if stride < 1:
        raise ValueError(f"steps must be in 1..{num_train_timesteps}, got {steps}")
    if not (steps - 1) * stride <= first < min(steps * stride, num_train_timesteps):
        raise ValueError(
            f"{steps} steps {stride} apart must start in {(steps - 1) * stride}.."
            f"{min(steps * stride, num_train_timesteps) - 1} to end on the clean sample, got {first}"
        )
    return [first - i * stride for i in range(steps)]


def check_timesteps(timesteps, num_train_timesteps: int) -> tuple[int, ...]:
    """``timesteps`` as a tuple of ints, checked: at least one, strictly decreasing, each in
    0..num_train_timesteps - 1 (ValueError otherwise)."""
    listed = tuple(int(t) for t in timesteps)
    if not listed or any(t != u for t, u in zip(listed, timesteps)):
        raise ValueError(f"timesteps must be a non-empty list of integers, got {list(timesteps)}")
    if not all(0 <= t < num_train_timesteps for t in listed) or any(a <= b for a, b in itertools.pairwise(listed)):
        raise ValueError(f"timesteps must decrease strictly within 0..{num_train_timesteps - 1}, got {list(listed)}")
    return listed


def sampler_timesteps(sampler: dict, num_train_timesteps: int) -> tuple[int, ...] | None:
    """The explicit timesteps a policy file's ``sampler`` entry names (its ``timesteps``, or the evenly spaced
    ones of an older entry's ``first_timestep``), checked; None where it names only a step count and spacing."""
    if "timesteps" in sampler:
        listed = check_timesteps(sampler["timesteps"], num_train_timesteps)
        if sampler.get("steps", len(listed)) != len(listed):
            raise ValueError(f"sampler: steps {sampler['steps']} but {len(listed)} timesteps {list(listed)}")
        return listed
    if sampler.get("first_timestep") is not None:
        steps = sampler.get("steps")
        if steps is None:
            raise ValueError("sampler: first_timestep without steps")
        return tuple(uniform_timesteps(num_train_timesteps, int(steps), int(sampler["first_timestep"])))
    return None


def check_sampler_entry(preset: PolicyPreset, sampler: dict) -> tuple[int, ...] | None:
    """A policy file's ``sampler`` entry checked by making the scheduler it names (ValueError or TypeError where
    it cannot); returns its explicit timesteps, None where it names a step count and spacing. The one check that
    export (nothing written that would not load) and loading share."""
    listed = sampler_timesteps(sampler, preset.num_train_timesteps)
    make_inference_scheduler(preset, sampler.get("steps"), sampler.get("timestep_spacing", "leading"), listed)
    return listed


class ListedDDIMScheduler(DDIMScheduler):
    """DDIM through an explicit list of timesteps: each step lands on the next one in the list, the last on the
    clean sample. Why a subclass: diffusers' own step always lands ``num_train_timesteps // steps`` lower, which
    fits only evenly spaced lists, while a few-step sampler's best steps are not evenly spaced (their choice:
    docs/denoising_steps.md). Deterministic (eta 0), as every sampler here."""

    def use_timesteps(self, timesteps: tuple[int, ...]) -> None:
        self.set_timesteps(len(timesteps))
        self.timesteps = torch.tensor(timesteps, dtype=self.timesteps.dtype)
        self._next = dict(zip(timesteps, (*timesteps[1:], -1)))  # -1: the clean sample

    def step(self, model_output, timestep, sample, eta: float = 0.0, return_dict: bool = True, **unused):
        if eta != 0.0:
            raise ValueError("ListedDDIMScheduler steps deterministically (eta 0)")
        t = int(timestep)
        after = self._next[t]
        alpha_after = self.alphas_cumprod[after] if after >= 0 else self.final_alpha_cumprod
        prev = ddim_step_between(sample, model_output, self.alphas_cumprod[t], alpha_after)
        return DDIMSchedulerOutput(prev_sample=prev) if return_dict else (prev,)


def make_inference_scheduler(
    preset: PolicyPreset,
    steps: int | None = None,
    spacing: str = "leading",
    timesteps: tuple[int, ...] | None = None,
) -> DDIMScheduler:
    """The DDIM scheduler at ``steps`` denoising steps (None: the preset's ``num_inference_steps``) spaced by
    ``spacing`` (of TIMESTEP_SPACINGS), or through the explicit ``timesteps`` (a distilled policy's own sampler,
    ``ListedDDIMScheduler``; ``steps`` then None or their count); ValueError outside 1..num_train_timesteps or
    for another spacing."""
    config = {
        "num_train_timesteps": preset.num_train_timesteps,
        "beta_schedule": preset.beta_schedule,
        "prediction_type": "epsilon",
        "clip_sample": True,
        "set_alpha_to_one": True,
        "steps_offset": 0,
        "timestep_spacing": spacing,
    }
    if spacing not in TIMESTEP_SPACINGS:
        raise ValueError(f"timestep spacing must be one of {TIMESTEP_SPACINGS}, got {spacing!r}")
    if timesteps is not None:
        listed = check_timesteps(timesteps, preset.num_train_timesteps)
        if steps is not None and int(steps) != len(listed):
            raise ValueError(f"{steps} inference steps but {len(listed)} timesteps {list(listed)}")
        sched = ListedDDIMScheduler(**config)
        sched.use_timesteps(listed)
        return sched
    steps = preset.num_inference_steps if steps is None else int(steps)
    if not 1 <= steps <= preset.num_train_timesteps:
        raise ValueError(f"inference steps must be in 1..{preset.num_train_timesteps}, got {steps}")
    # Same betas as training; eta = 0 (deterministic given the initial noise), as diffusion_policy's DDIM.
    sched = DDIMScheduler(**config)
    sched.set_timesteps(steps)
    return sched


def ddim_step_between(
    x: torch.Tensor, eps: torch.Tensor, alpha_bar: torch.Tensor, alpha_bar_next: torch.Tensor
) -> torch.Tensor:
    """One deterministic DDIM step from ``x`` at ᾱ = ``alpha_bar`` to ᾱ = ``alpha_bar_next`` (1: the clean
    sample), the clean estimate clipped to [-1, 1]: what ``make_inference_scheduler``'s step computes
    (tested equal), written out because distillation needs it between any two timesteps and differentiable."""
    clean = ((x - (1 - alpha_bar).sqrt() * eps) / alpha_bar.sqrt()).clamp(-1.0, 1.0)
    return alpha_bar_next.sqrt() * clean + (1 - alpha_bar_next).sqrt() * eps


@torch.no_grad()
def ddim_sample(
    denoise,
    cond,
    shape: tuple[int, int, int],
    scheduler: DDIMScheduler,
    *,
    generator: torch.Generator | None = None,
    noise: torch.Tensor | None = None,
    device="cpu",
    guide: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """Run the reverse process from ``noise`` (or fresh Gaussian noise) with ``denoise(x, t, cond)``.

    ``guide = (target (B, T, D), weights (T,) in [0, 1])`` inpaints: at every step the predicted
    clean sample is pulled towards ``target`` by each step's weight (1: replaced by it, 0: left
    free) and the noise is re-derived from it, so the DDIM update continues from the guided
    estimate (real-time chunking, ``wire.chunk.RealTimeChunking``). The weights scale whole steps,
    never single dimensions, so an equivariant denoiser stays equivariant. None: plain DDIM,
    the same operations as without the argument."""
    x = (
        noise.to(device=device, dtype=torch.float32)
        if noise is not None
        else torch.randn(shape, generator=generator, device=device, dtype=torch.float32)
    )
    B = x.shape[0]
    if guide is not None:
        target = guide[0].to(device=device, dtype=torch.float32)
        weights = guide[1].to(device=device, dtype=torch.float32)[None, :, None]
        if target.shape != x.shape or weights.shape[1] != x.shape[1]:
            raise ValueError(
                f"guide target {tuple(target.shape)} / weights {tuple(guide[1].shape)} do not match "
                f"the sample {tuple(x.shape)}"
            )
    for t in scheduler.timesteps:
        eps = denoise(x, t.to(device).expand(B), cond).float()
        if guide is not None:
            eps = _guided_noise(scheduler, t, x, eps, target, weights)
        x = scheduler.step(eps, t, x).prev_sample
    return x


def _guided_noise(
    scheduler: DDIMScheduler, t, x: torch.Tensor, eps: torch.Tensor, target: torch.Tensor, weights: torch.Tensor
) -> torch.Tensor:
    """The noise that makes epsilon-DDIM's clean estimate at ``t`` the guided one (x0 + w (target - x0))."""
    # a 0-dim CPU tensor multiplies device tensors as a scalar: no copy to the GPU, so a CUDA graph can capture this
    alpha = scheduler.alphas_cumprod[int(t)].to(torch.float32)
    a, b = alpha.sqrt(), (1 - alpha).sqrt()
    x0 = (x - b * eps) / a
    x0 = x0 + weights * (target - x0)
    return (x - a * x0) / b


class ActionCodec:
    """Absolute actions (..., T, 10) + current gripper state (..., 10) <-> model vectors (..., T, D)."""

    REL_ROT_SCALE = 0.5  # P vec_r(dR) entries reach +-2; halve them so clip_sample's [-1, 1] keeps them

    def __init__(self, control: str, normalizer: Normalizer):
        self.control = control
        self.normalizer = normalizer
        self.freqs = action_space.freqs_for(control)
        self.dim = action_space.dim_of(self.freqs)
        self._order = list(action_space.ABS_ORDER)
        self._inverse = list(action_space.ABS_INVERSE)

    def encode(self, actions: torch.Tensor, ee: torch.Tensor) -> torch.Tensor:
        if self.control == "absolute":
            return self.normalizer.normalize(actions)[..., self._order]
        return self._encode_relative(actions, ee)

    def decode(self, x: torch.Tensor, ee: torch.Tensor) -> torch.Tensor:
        if self.control == "absolute":
            return self.normalizer.unnormalize(x[..., self._inverse])
        return self._decode_relative(x, ee)

    def _center(self, ref: torch.Tensor) -> torch.Tensor:
        n = self.normalizer
        z = (n.z_max + n.z_min) / 2  # any fixed point on the rotation axis works; keep values small
        return torch.tensor([n.center_xy[0], n.center_xy[1], z], dtype=ref.dtype, device=ref.device)

    def _encode_relative(self, actions, ee):
        c = self._center(actions)
        R_now = geometry.matrix_from_rot6d(ee[..., geometry.ROT6D])[..., None, :, :]  # (..., 1, 3, 3)
        p_now = (ee[..., geometry.POS] - c)[..., None, :]
        R = geometry.matrix_from_rot6d(actions[..., geometry.ROT6D])
        p = actions[..., geometry.POS] - c
        dR = R @ R_now.transpose(-1, -2)
        t = p - (dR @ p_now[..., None])[..., 0]
        P = torch.as_tensor(geometry.P_REL_ROT, dtype=actions.dtype, device=actions.device)
        rot = (dR.flatten(-2) @ P.T) * self.REL_ROT_SCALE
        s = self.normalizer.rel_translation_scale
        return torch.cat([t / s, rot, actions[..., geometry.WIDTH :]], dim=-1)

    def _decode_relative(self, x, ee):
        c = self._center(x)
        s = self.normalizer.rel_translation_scale
        t = x[..., :3] * s
        P_inv = torch.as_tensor(np.linalg.inv(geometry.P_REL_ROT), dtype=x.dtype, device=x.device)
        dR = ((x[..., 3:12] / self.REL_ROT_SCALE) @ P_inv.T).unflatten(-1, (3, 3))
        R_now = geometry.matrix_from_rot6d(ee[..., geometry.ROT6D])[..., None, :, :]
        p_now = (ee[..., geometry.POS] - c)[..., None, :]
        R = dR @ R_now
        p = t + (dR @ p_now[..., None])[..., 0] + c
        return torch.cat([p, R[..., :2, :].flatten(-2), x[..., 12:]], dim=-1)
