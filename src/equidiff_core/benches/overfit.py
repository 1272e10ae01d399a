"""Can a policy fit two demonstrations? The standard check that training works and that the policy
reads its observation (``equidiff bench overfit``; the suite's ``test_overfits_tiny_dataset`` runs a
shorter version of it).

Two synthetic cube demos (``data.synthetic.CubeDataset``: different cubes and start poses, the gripper
reaching from its start to above the cube) are trained on for ``steps``; then DDIM-16 samples from 4
seeds, for each demo's observation, are compared with that demo's own trajectory (``own_m``, the
mean position error) and with the other demo's (``other_m``: a policy that ignores its voxels lands
between the two), and the width with the demos' open 80 mm (``width_m``). The untrained policy,
measured the same way in the same run, is the baseline.

With epsilon prediction the observation dependence of x0 at high noise is learned last, so samples
lag the loss: half the steps leave them centimetres off (docs/results/model.md, "The over-fit check"). The
baseline needs longer (``STEPS``).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from ..config import Workspace
from ..data.synthetic import OPEN_WIDTH_M, CubeDataset
from ..policy.diffusion import make_policy
from ..policy.file import export_policy
from ..policy.inference import load_inference_policy
from ..policy.presets import get_preset
from ..runtime.machine import cpu_description
from ..runtime.output_files import staged_dir
from ..training.config import TrainConfig
from ..training.loop import fit_normalizer, train
from . import BenchError

__all__ = ["STEPS", "OverfitGate", "OverfitResult", "run_overfit", "sample_errors"]

# Optimiser steps per policy at the recipe's lr of 2e-3. The baseline's loss sits on the average-motion
# plateau for about a thousand steps and leaves it only while the learning rate is still high: at
# EquiDiff's steps the cosine schedule ends first and it fails; at four times as many it fits
# (docs/results/model.md, "The baseline passes it too": `equidiff bench overfit --policy baseline`).
STEPS = {"equidiff": 1200, "baseline": 4800}


@dataclass(frozen=True)
class OverfitGate:
    """What fitting two demos means: the loss fell ``loss_fall``-fold, samples land within ``own_m``
    of their own demo and ``other_ratio`` times closer to it than to the other, the width within ``width_m``."""

    loss_fall: float = 10.0
    own_m: float = 0.015
    other_ratio: float = 3.0
    width_m: float = 0.03

    def failures(self, result: OverfitResult) -> list[str]:
        out = []
        if not result.loss_last < result.loss_first / self.loss_fall:
            out.append(f"the loss fell {result.loss_first / result.loss_last:.1f}-fold, not {self.loss_fall:g}")
        for i, e in enumerate(result.errors):
            if not (e["own_m"] < self.own_m and e["own_m"] < e["other_m"] / self.other_ratio):
                out.append(
                    f"demo {i}: samples {100 * e['own_m']:.1f} cm from their own trajectory and "
                    f"{100 * e['other_m']:.1f} cm from the other's (need < {100 * self.own_m:g} cm and "
                    f"{self.other_ratio:g}x closer)"
                )
            if not e["width_m"] < self.width_m:
                out.append(f"demo {i}: width {1000 * e['width_m']:.0f} mm off (need < {1000 * self.width_m:g})")
        return out


@dataclass
class OverfitResult:
    steps: int
    loss_first: float  # the mean of the first logged interval
    loss_last: float  # the mean of the last three logged intervals
    errors: list[dict]  # per demo: own_m, other_m, width_m
    untrained_errors: list[dict]  # the same, before training: the baseline
    train_wall_s: float
    train_cpu_s: float
    device: dict  # the CPU: its name, cores and instruction sets

    def as_dict(self) -> dict:
        return asdict(self)


def sample_errors(inference_policy, ds: CubeDataset, seeds: int = 4) -> list[dict]:
    """Per demo of ``ds``: mean position error (m) of ``seeds`` seeded DDIM samples against its own and
    the other demo's actions, and mean width error against the open width."""
    out = []
    for i in range(len(ds)):
        obs = ds[i]
        preds = np.stack(
            [inference_policy.predict(obs["voxels"][0].numpy(), obs["ee"][0].numpy(), seed=s) for s in range(seeds)]
        )
        own = np.linalg.norm(preds[..., :3] - obs["action"][..., :3].numpy(), axis=-1).mean()
        others = [
            np.linalg.norm(preds[..., :3] - ds[j]["action"][..., :3].numpy(), axis=-1).mean()
            for j in range(len(ds))
            if j != i
        ]
        width = np.abs(preds[..., 9] - OPEN_WIDTH_M).mean()
        out.append({"own_m": float(own), "other_m": float(min(others)), "width_m": float(width)})
    return out


def policy_steps(policy: str, steps: int | None) -> int:
    """``steps``, or the policy's own (``STEPS``) where it is None."""
    return STEPS[policy] if steps is None else steps


def overfit_train_config(steps: int, lr: float, noise_repeats: int) -> TrainConfig:
    """The over-fit recipe: batch 2 (both demos) x ``noise_repeats`` draws, EMA, no evaluation;
    ValueError for a setting out of range."""
    if steps < 1:  # TrainConfig allows 0 (a resume with nothing left): here there would be no loss to read
        raise ValueError(f"steps must be >= 1, got {steps}")
    return TrainConfig(
        steps=steps,
        batch_size=2,
        lr=lr,
        warmup_steps=20,
        eval_every=0,
        checkpoint_every=0,
        noise_repeats=noise_repeats,
        log_every=max(1, min(50, steps // 4)),
        ema=True,
        device="cpu",
    )


def run_overfit(
    out: Path,
    steps: int | None = None,
    policy: str = "equidiff",
    preset: str = "tiny",
    lr: float = 2e-3,
    noise_repeats: int = 16,
    seed: int = 0,
) -> OverfitResult:
    """Train ``policy`` on two cube demos for ``steps`` (None: the policy's own, ``STEPS``; batch 2 x
    ``noise_repeats`` draws, EMA, no rotation augmentation: both demos point the gripper the same
    way) and measure its samples."""
    # a bad setting fails here, before any work
    cfg = overfit_train_config(policy_steps(policy, steps), lr, noise_repeats)
    preset_config = get_preset(preset, rotation_aug="none")
    out = Path(out)
    ws = Workspace()
    torch.manual_seed(seed)
    ds = CubeDataset(2, ws, seed=seed, random_yaw=False)
    model = make_policy(policy, preset_config, ws)
    model.set_normalizer(fit_normalizer(ds, ws))  # what train() fits: the untrained export needs it
    untrained = export_policy(model, out / "untrained.pt")
    wall, cpu = time.monotonic(), time.process_time()
    result = train(model, ds, None, cfg, out / "run")
    wall, cpu = time.monotonic() - wall, time.process_time() - cpu
    losses = [h["loss"] for h in result.history if "loss" in h]
    return OverfitResult(
        steps=result.steps,
        loss_first=float(losses[0]),
        loss_last=float(np.mean(losses[-3:])),
        errors=sample_errors(load_inference_policy(result.exported), ds),
        untrained_errors=sample_errors(load_inference_policy(untrained), ds),
        train_wall_s=round(wall, 1),
        train_cpu_s=round(cpu, 1),
        device=cpu_description(),
    )


@dataclass(frozen=True)
class OverfitSettings:
    """``equidiff bench overfit``'s settings: its flags, same names (the command's help says more)."""

    policy: str  # equidiff or baseline
    preset: str
    steps: int | None  # training steps (None: the policy's STEPS)
    lr: float  # peak learning rate
    noise_repeats: int  # (noise, step) draws per encoder pass
    seed: int  # the demos, the weights and the training's noise
    out: Path | None  # keep the run here (None: a temporary folder)
    force: bool = False  # replace an existing ``out``


@dataclass(frozen=True)
class OverfitOutcome:
    """The bench's JSON line and what the gate found wrong (``failures`` empty: it held; the command exits 3
    otherwise, each failure a line on stderr)."""

    line: dict
    failures: list[str]


def run_overfit_bench(settings: OverfitSettings) -> OverfitOutcome:
    """Train, sample, judge; BenchError (exit status 2) for a setting out of range or an unknown preset,
    before anything is trained."""
    try:
        overfit_train_config(policy_steps(settings.policy, settings.steps), settings.lr, settings.noise_repeats)
        get_preset(settings.preset)
    except ValueError as err:  # ConfigError included
        raise BenchError(str(err), 2) from err
    with staged_dir(settings.out, force=settings.force, prefix="bench_overfit_") as staged:  # lands when trained
        result = run_overfit(
            staged.path,
            steps=settings.steps,
            policy=settings.policy,
            preset=settings.preset,
            lr=settings.lr,
            noise_repeats=settings.noise_repeats,
            seed=settings.seed,
        )
    failures = OverfitGate().failures(result)
    line = {**result.as_dict(), "policy": settings.policy, "preset": settings.preset, "passed": not failures}
    return OverfitOutcome(line, failures)
