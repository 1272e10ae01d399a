"""`equidiff distill TEACHER --demos DIR --out FILE`: a trained EquiDiff policy distilled into a few-step sampler.

    equidiff distill checkpoints/twin_compact/last.ckpt --demos demos/ --out runs/policy_ddim4.pt

The student learns to take in one DDIM step what the teacher takes in several (``training.distill``), on the
teacher's own training demos, with the teacher's encoder frozen; it stays equivariant. FILE is a policy file
of its own whose sampler (its timesteps) policy_node, ``twin run`` and ``twin evaluate`` use
with no flag. Prints one JSON line: the sampler, the frames, the steps trained, the final loss and the wall
time. An existing FILE is refused unless ``--force``. docs/denoising_steps.md, "A distilled few-step policy".
"""

from __future__ import annotations

from pathlib import Path

from equidiff_core.runtime.jobs import progress_lines
from equidiff_core.training.distill import DistillSpec, run_distillation
from equidiff_ros.commands import add_force_argument, print_result

DEFAULT = DistillSpec(teacher=Path(), demos=(), out=Path())


def add_arguments(parser) -> None:
    parser.add_argument("teacher", type=Path, help="the teacher's training checkpoint (its run's last.ckpt)")
    parser.add_argument(
        "--demos",
        type=Path,
        nargs="+",
        required=True,
        help="its training demos, and any recorded roll-outs (bags or folders)",
    )
    parser.add_argument("--out", type=Path, required=True, help="the student's policy file")
    parser.add_argument(
        "--timesteps",
        type=int,
        nargs="+",
        default=list(DEFAULT.timesteps),
        help="the student's sampler: one DDIM step from each timestep to the next, the last to the clean sample "
        f"(default: {' '.join(map(str, DEFAULT.timesteps))})",
    )
    parser.add_argument("--train-steps", type=int, default=DEFAULT.train_steps, help="optimiser steps")
    parser.add_argument("--batch-size", type=int, default=DEFAULT.batch_size)
    parser.add_argument("--lr", type=float, default=DEFAULT.lr, help="peak learning rate (cosine decay)")
    parser.add_argument("--max-minutes", type=float, default=None, help="stop and export after this long")
    parser.add_argument(
        "--crops", type=int, default=DEFAULT.crops, help="encoder inputs per frame: the centred crop and CROPS-1 random"
    )
    parser.add_argument("--seed", type=int, default=DEFAULT.seed)
    parser.add_argument("--lab-config", type=Path, default=None, help="lab.yaml whose grid the demos have")
    add_force_argument(parser)


def run(args) -> int:
    spec = DistillSpec(
        teacher=args.teacher,
        demos=tuple(args.demos),
        out=args.out,
        timesteps=tuple(args.timesteps),
        train_steps=args.train_steps,
        batch_size=args.batch_size,
        lr=args.lr,
        max_minutes=args.max_minutes,
        crops=args.crops,
        seed=args.seed,
        force=args.force,
        lab_config=args.lab_config,
    )
    with progress_lines("stderr", "equidiff distill: "):
        return print_result(run_distillation(spec))
