"""Few-step distillation: a trained policy's DDIM sampler compressed into fewer steps (``equidiff distill``).

The student starts as a copy of the teacher and learns, for each of its DDIM steps (from one of its
``timesteps`` to the next), to land where the teacher's own sampler lands in the steps it takes between the two,
from the same noisy sample: multi-step distillation in the manner of progressive distillation (Salimans & Ho,
ICLR 2022), in one stage. Only the denoiser learns:
the observation encoder is the teacher's, frozen, so its features are computed once per training frame (the
centred crop policy_node feeds it), and each distillation step costs U-Net passes only. EquiDiff's student is
the escnn model itself, so it stays C8-equivariant by construction (``equidiff check equivariance``).

The student is exported as a policy file of its own, whose ``sampler`` entry (its explicit timesteps,
``models.sampling.ListedDDIMScheduler``) makes policy_node and the twin run it with no flag.
docs/denoising_steps.md ("A distilled few-step policy") is the guide.
"""

from __future__ import annotations

import itertools
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from diffusers.optimization import get_cosine_schedule_with_warmup

from ..config import default_config_dir, load_lab_config
from ..data.dataset import DemoDataset, load_episodes
from ..data.episode_arrays import DatasetConfig
from ..data.segments import SourceWeights
from ..models.cpu_kernels import FastMish, swap_modules
from ..models.sampling import check_timesteps, ddim_step_between, make_inference_scheduler
from ..policy.file import CheckpointError, export_policy
from ..runtime.jobs import JobError
from ..runtime.output_files import refuse_existing
from ..wire.pointcloud import VoxelGridSpec
from .loop import Ema, adamw, load_policy_from_checkpoint

logger = logging.getLogger(__name__)


# The teacher answers at every frame, whoever drove the arm: a policy's own roll-outs (its frames, weight 0 in
# training's HG-DAgger default) teach the student at the states its closed loop reaches, DAgger with the
# teacher as the expert (docs/denoising_steps.md).
ROLLOUT_FRAMES_TOO = SourceWeights(intervention=1.0, policy=1.0)


# The student's default sampler: four steps, ending with the teacher's own last step from t = 0. Chosen by how
# near the teacher's weights land to their own DDIM-16 chunk at each four-step schedule (docs/denoising_steps.md,
# "Which four timesteps").
STUDENT_TIMESTEPS = (90, 60, 12, 0)


class DistillError(JobError):
    """A teacher, demos or settings distillation cannot run with (exit status 2), or a diverged run (1)."""


@dataclass(frozen=True)
class DistillSpec:
    """What ``equidiff distill`` is asked for (its flags, same names)."""

    teacher: Path  # the teacher's training checkpoint (last.ckpt): escnn weights, EMA where it kept one
    demos: tuple[Path, ...]  # the teacher's training demos, and any roll-outs (bags, packed episodes or folders)
    out: Path  # the student's policy file
    timesteps: tuple[int, ...] = STUDENT_TIMESTEPS  # the student's sampler, one DDIM step from each
    train_steps: int = 2500  # optimiser steps (0: the teacher's weights at the student's sampler, the baseline)
    batch_size: int = 32
    lr: float = 1e-4  # peak; cosine decay after a 100-step warm-up
    max_minutes: float | None = None  # stop (and export) after this long
    crops: int = 1  # encoder inputs per frame: the centred crop, and crops - 1 random ones
    seed: int = 0
    force: bool = False  # replace an existing ``out``
    lab_config: Path | None = None  # the lab whose grid the demos must have (None: config/lab.yaml)


@dataclass(frozen=True)
class StudentSampler:
    """The student's timesteps and, for each, the teacher's path to the next one (-1: the clean sample)."""

    timesteps: tuple[int, ...]
    teacher_paths: tuple[tuple[int, ...], ...]  # per student step: the timesteps the teacher steps through


def student_sampler(timesteps, teacher_timesteps, num_train_timesteps: int) -> StudentSampler:
    """The student steps from each of ``timesteps`` to the next (the last to the clean sample); the teacher covers
    each such step through its own sampler's ``teacher_timesteps`` that lie between the two ends, so where the
    student's timesteps are the teacher's too, every path is a stretch of the teacher's own DDIM trajectory.
    ValueError for timesteps that are not strictly decreasing within the schedule."""
    listed = check_timesteps(timesteps, num_train_timesteps)
    ends = (*listed[1:], -1)
    paths = tuple(
        (start, *(int(t) for t in teacher_timesteps if end < t < start), end) for start, end in zip(listed, ends)
    )
    return StudentSampler(listed, paths)


def _alpha_bar(alphas_cumprod: torch.Tensor, t: int) -> torch.Tensor:
    return alphas_cumprod[t] if t >= 0 else torch.ones((), dtype=alphas_cumprod.dtype)


class _Frames:
    """Every training frame's encoder features (the teacher's, frozen) and clean model-space action: the centred
    crop policy_node feeds it, and ``crops - 1`` random crops more per frame (training's augmentation)."""

    def __init__(self, policy, dataset: DemoDataset, crops: int = 1, generator=None, batch: int = 16):
        conds, targets = [], []
        policy.eval()
        with torch.no_grad():
            for start in range(0, len(dataset), batch):
                items = [dataset[i] for i in range(start, min(start + batch, len(dataset)))]
                voxels = torch.stack([s["voxels"] for s in items])
                ee = torch.stack([s["ee"] for s in items])
                clean = policy.codec.encode(torch.stack([s["action"] for s in items]).float(), ee[:, -1].float())
                for k in range(crops):
                    vox, ee_n = policy.prepare_input(voxels, ee, "center" if k == 0 else "random", generator)
                    cond = policy.model.encode_obs(vox, ee_n)
                    conds.append(cond.unflatten(0, (len(items), -1)))  # (B, rows per sample, features)
                    targets.append(clean)
        self.cond = torch.cat(conds)
        self.clean = torch.cat(targets)

    def __len__(self) -> int:
        return len(self.clean)


def distill_loss(student, teacher, frames: _Frames, sampler: StudentSampler, alphas_cumprod, index, step_i, noise):
    """The student's one DDIM step against the teacher's path, from the same noisy sample of the frames
    ``index`` at student step ``step_i``: the squared gap between the two landings, divided by how much the
    student's noise estimate moves its landing (so each step's loss is in noise units, as training's)."""
    cond = frames.cond[index].flatten(0, 1)
    clean = frames.clean[index]
    t = sampler.timesteps[step_i]
    a_t = _alpha_bar(alphas_cumprod, t)
    x = a_t.sqrt() * clean + (1 - a_t).sqrt() * noise
    B = x.shape[0]
    with torch.no_grad():
        z = x
        path = sampler.teacher_paths[step_i]
        for here, there in itertools.pairwise(path):
            eps = teacher.model.denoise(z, torch.full((B,), here, dtype=torch.long), cond)
            z = ddim_step_between(z, eps, _alpha_bar(alphas_cumprod, here), _alpha_bar(alphas_cumprod, there))
    a_next = _alpha_bar(alphas_cumprod, path[-1])
    eps = student.model.denoise(x, torch.full((B,), t, dtype=torch.long), cond)
    landed = ddim_step_between(x, eps, a_t, a_next)
    gain = (1 - a_next).sqrt() - a_next.sqrt() * (1 - a_t).sqrt() / a_t.sqrt()
    return ((landed - z) ** 2).mean() / gain**2


def check_loss(student, teacher, frames: _Frames, sampler: StudentSampler, alphas_cumprod, index, noise) -> float:
    """``distill_loss`` of the frames ``index`` with fixed ``noise``, averaged over every student step: the same
    batch before and after distillation tells whether the student learned the teacher's path."""
    with torch.no_grad():
        losses = [
            distill_loss(student, teacher, frames, sampler, alphas_cumprod, index, i, noise)
            for i in range(len(sampler.timesteps))
        ]
    return float(sum(losses) / len(losses))


def run_distillation(spec: DistillSpec, log=logger.info) -> dict:
    """Distil ``spec.teacher`` into ``spec.out``; returns the summary (also what ``equidiff distill`` prints)."""
    if spec.train_steps < 0 or spec.batch_size < 1 or not spec.lr > 0 or spec.crops < 1:
        raise DistillError(
            "--train-steps must be >= 0 (0: the teacher at the student's sampler), --batch-size, --lr and --crops "
            "positive",
            2,
        )
    refuse_existing(spec.out, spec.force)
    try:
        teacher = load_policy_from_checkpoint(spec.teacher, device="cpu", ema=True)
    except CheckpointError as err:
        raise DistillError(f"the teacher: {err}", 2) from err
    preset = teacher.preset
    teacher_timesteps = [int(t) for t in make_inference_scheduler(preset).timesteps]  # the teacher's own sampler
    try:
        sampler = student_sampler(spec.timesteps, teacher_timesteps, preset.num_train_timesteps)
    except ValueError as err:
        raise DistillError(f"--timesteps: {err}", 2) from err
    steps = len(sampler.timesteps)
    if steps >= len(teacher_timesteps):
        raise DistillError(
            f"--timesteps: {steps} steps, and the teacher already samples in {len(teacher_timesteps)}", 2
        )

    lab = load_lab_config(spec.lab_config or default_config_dir() / "lab.yaml")
    data_cfg = DatasetConfig.from_preset(
        preset, resolution=lab.workspace.resolution, grid=VoxelGridSpec.of(lab.workspace, lab.base_frame)
    )
    episodes, skipped = load_episodes(spec.demos, data_cfg, log=log)
    if not episodes:
        reasons = "; ".join(reason for _, reason in skipped[:3]) or "none found"
        raise DistillError(f"no usable demos in {', '.join(map(str, spec.demos))}: {reasons}", 2)
    dataset = DemoDataset(episodes, data_cfg, ROLLOUT_FRAMES_TOO)
    started = time.perf_counter()  # the cost reported: from encoding the frames to the exported student
    torch.manual_seed(spec.seed)
    frames = _Frames(teacher, dataset, spec.crops, torch.Generator().manual_seed(spec.seed + 1))
    swap_modules(teacher.model, torch.nn.Mish, lambda _: FastMish())  # the teacher only runs: the faster CPU Mish
    encode_s = time.perf_counter() - started
    log(
        f"[distill] {len(frames)} inputs ({spec.crops} per frame) of {len(episodes)} episodes read and encoded in "
        f"{encode_s:.0f} s; student timesteps {list(sampler.timesteps)}, teacher paths "
        f"{[list(p) for p in sampler.teacher_paths]}"
    )

    student = load_policy_from_checkpoint(spec.teacher, device="cpu", ema=True)  # escnn models refuse deepcopy
    student.train()
    # the encoder's features are precomputed: its parameters get no gradient, so AdamW leaves them as they are
    params = list(student.model.parameters())
    optimizer = adamw(params, lr=spec.lr, weight_decay=1e-6)
    schedule = get_cosine_schedule_with_warmup(optimizer, min(100, spec.train_steps // 10), spec.train_steps)
    ema = Ema(student, decay=0.999)
    alphas_cumprod = teacher.noise_scheduler.alphas_cumprod.float()
    generator = torch.Generator().manual_seed(spec.seed)
    check_index = torch.randperm(len(frames), generator=generator)[: min(len(frames), 64)]
    check_noise = torch.randn(frames.clean[check_index].shape, generator=generator)
    student.eval()  # (escnn caches its filters in eval mode; train mode expands them on every call)
    loss_before = check_loss(student, teacher, frames, sampler, alphas_cumprod, check_index, check_noise)
    student.train()
    losses: list[float] = []
    step = 0
    deadline = None if spec.max_minutes is None else started + 60 * spec.max_minutes
    while step < spec.train_steps and (deadline is None or time.perf_counter() < deadline):
        index = torch.randint(0, len(frames), (spec.batch_size,), generator=generator)
        step_i = int(torch.randint(0, steps, (), generator=generator))
        noise = torch.randn(frames.clean[index].shape, generator=generator)
        loss = distill_loss(student, teacher, frames, sampler, alphas_cumprod, index, step_i, noise)
        if not torch.isfinite(loss):
            raise DistillError(f"the distillation loss diverged at step {step}", 1)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        optimizer.step()
        schedule.step()
        ema.step()
        losses.append(loss.item())
        step += 1
        if step % 200 == 0:
            log(f"[distill] step {step}: loss {sum(losses[-200:]) / 200:.4g}")
    ema.copy_to_model()
    student.eval()
    loss_after = check_loss(student, teacher, frames, sampler, alphas_cumprod, check_index, check_noise)
    sampler_entry = {"steps": steps, "timesteps": list(sampler.timesteps)}
    refuse_existing(spec.out, spec.force)  # again: it may have appeared while the student trained
    export_policy(student, spec.out, sampler=sampler_entry)
    wall = time.perf_counter() - started
    tail = losses[-min(len(losses), 200) :]
    return {
        "out": str(spec.out),
        "teacher": str(spec.teacher),
        "sampler": sampler_entry,
        "timesteps": list(sampler.timesteps),
        "teacher_paths": [list(p) for p in sampler.teacher_paths],
        "frames": len(dataset),
        "inputs": len(frames),  # frames x crops
        "episodes": len(episodes),
        "skipped": len(skipped),
        "train_steps": step,
        "final_loss": float(f"{sum(tail) / len(tail):.4g}") if tail else None,
        # the same frames and noise, every student step, before (the teacher's weights) and after
        "check_loss_before": float(f"{loss_before:.4g}"),
        "check_loss_after": float(f"{loss_after:.4g}"),
        "encode_s": round(encode_s, 1),  # encoding the frames
        "wall_s": round(wall, 1),
        "threads": torch.get_num_threads(),
        "recipe": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(spec).items() if k != "demos"},
    }
