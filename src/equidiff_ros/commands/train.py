"""`equidiff train BAGS... --out DIR`: train EquiDiff or the baseline from recorded episodes.

Bags -> ``DemoDataset`` (decoded once, cached under ``--cache-dir``), whole episodes held out
for validation (``--val-fraction``, split saved in ``DIR/split.json`` and reused on resume),
then ``equidiff_core.training.loop.train`` (AdamW + cosine, periodic checkpoints, resume from
``DIR/last.ckpt``); ``DIR/run.json`` keeps the summary and the recipe (device, batch, lr, ...).
On every evaluation the held-out episodes are sampled with DDIM and
scored by action MSE (absolute targets, metres/rot6d/metres); ``DIR/training.png`` plots the
loss and the evaluation curves. Deterministic for a given ``--seed`` on the same device.

Data-parallel on several GPUs (or CPU processes) with torchrun, e.g.
``torchrun --nproc-per-node 4 -m equidiff_ros.cli train bags/ --out runs/ddp --device cuda``:
every rank decodes the same episodes and split, rank 0 alone writes files and prints
(``equidiff_core.training.distributed``). ``--batch-size`` is per rank.

An existing DIR that holds files is refused (exit 2) unless ``--resume`` continues its run or
``--force`` replaces it: the new run then trains in a folder beside DIR and replaces DIR only once
it completed. A new run trains in DIR itself (a killed one is continued with ``--resume``); one
that stops before its first checkpoint leaves no DIR behind.
"""

from __future__ import annotations

import json
from pathlib import Path

from equidiff_core.policy.presets import BASELINE_INITS, ROTATION_AUGS
from equidiff_core.runtime.jobs import progress_lines
from equidiff_core.runtime.machine import PRECISIONS
from equidiff_core.training.job import TrainingSpec, run_training
from equidiff_ros.commands import add_force_argument

# the flags' defaults are the spec's
DEFAULT = TrainingSpec(bags=(), out=Path())


def add_arguments(parser) -> None:
    parser.add_argument("bags", nargs="+", help="bag directories, or folders holding bag directories")
    parser.add_argument("--out", required=True, help="output directory (checkpoints, policy.pt, plots)")
    parser.add_argument(
        "--policy", choices=("equidiff", "baseline"), default=DEFAULT.policy, help="default equidiff (or --init-from's)"
    )
    parser.add_argument(
        "--preset",
        default=DEFAULT.preset,
        help="model preset: paper, compact or tiny (default compact, or --init-from's)",
    )
    parser.add_argument(
        "--rotation-aug",
        choices=ROTATION_AUGS,
        default=DEFAULT.rotation_aug,
        help="random yaw rotation of voxels, state and actions while training (default: the preset's)",
    )
    parser.add_argument(
        "--baseline-width",
        type=int,
        default=DEFAULT.baseline_width,
        help="the baseline encoder's n_hidden (official channels n/16 ... n; default: the preset's; 0: channels "
        "matched to EquiDiff's parameter count, the baselines trained before the width existed)",
    )
    parser.add_argument(
        "--baseline-init",
        choices=BASELINE_INITS,
        default=DEFAULT.baseline_init,
        help="the baseline encoder's initialisation: torch (PyTorch's default) or he (default: the preset's)",
    )
    parser.add_argument("--steps", type=int, default=DEFAULT.steps)
    parser.add_argument("--batch-size", type=int, default=DEFAULT.batch_size)
    parser.add_argument("--lr", type=float, default=DEFAULT.lr)
    parser.add_argument("--warmup-steps", type=int, default=DEFAULT.warmup_steps)
    parser.add_argument(
        "--ema", action="store_true", help="keep an EMA of the weights (the paper's real-robot runs do not)"
    )
    parser.add_argument(
        "--noise-repeats",
        type=int,
        default=DEFAULT.noise_repeats,
        help="(noise, step) draws per observation per step, one encoder pass for all (default 1, the paper's)",
    )
    parser.add_argument("--seed", type=int, default=DEFAULT.seed)
    parser.add_argument("--device", default=DEFAULT.device, help="auto, cpu, cuda or cuda:N")
    parser.add_argument(
        "--val-fraction", type=float, default=DEFAULT.val_fraction, help="fraction of episodes held out (default 0.1)"
    )
    parser.add_argument("--eval-every", type=int, default=DEFAULT.eval_every)
    parser.add_argument(
        "--eval-max-samples",
        type=int,
        default=DEFAULT.eval_max_samples,
        help="held-out samples scored by action MSE at each evaluation (DDIM sampling)",
    )
    parser.add_argument("--checkpoint-every", type=int, default=DEFAULT.checkpoint_every)
    parser.add_argument(
        "--max-minutes",
        type=float,
        default=DEFAULT.max_minutes,
        help="stop after this much training time, then checkpoint and export as at the end",
    )
    parser.add_argument("--num-workers", type=int, default=DEFAULT.num_workers)
    parser.add_argument(
        "--precision",
        choices=PRECISIONS,
        default=DEFAULT.precision,
        help="auto: bf16 autocast on CUDA, fp32 on the CPU",
    )
    parser.add_argument(
        "--data",
        choices=("auto", "device", "loader"),
        default=DEFAULT.data,
        help="auto: the whole training set on the GPU when it fits in half its free memory, a DataLoader on the CPU",
    )
    parser.add_argument("--resume", action="store_true", help="continue from OUT/last.ckpt (a new run when none)")
    add_force_argument(
        parser,
        "replace an existing OUT: the new run trains beside it and replaces it once complete (not with --resume)",
    )
    parser.add_argument("--lab-config", help="lab.yaml (workspace); default: the installed one")
    parser.add_argument("--cache-dir", help="decoded-episode cache (default OUT/dataset_cache)")
    parser.add_argument("--tolerance", type=float, default=DEFAULT.tolerance, help="state/voxel stamp tolerance, s")
    parser.add_argument("--rerun", metavar="FILE.rrd|spawn|HOST:PORT", help="also log training to rerun")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar (logs every eval instead)")
    corrections = parser.add_argument_group(
        'fine-tuning on corrections (docs/lab.md, "Improving a policy with corrections")'
    )
    corrections.add_argument(
        "--init-from",
        metavar="CKPT",
        help="start from this run's weights (its last.ckpt or weights.ckpt): its policy, preset and normaliser",
    )
    corrections.add_argument(
        "--intervention-weight",
        type=float,
        default=DEFAULT.intervention_weight,
        help="how much a frame the operator drove in a policy's roll-out counts, against a demonstration's 1 "
        "(default %(default)s)",
    )
    corrections.add_argument(
        "--policy-frame-weight",
        type=float,
        default=DEFAULT.policy_frame_weight,
        help="how much a frame the policy drove counts (default %(default)s: left out)",
    )


def training_spec(args) -> TrainingSpec:
    """The run the parsed flags ask for."""
    return TrainingSpec(
        bags=tuple(Path(bag) for bag in args.bags),
        out=Path(args.out),
        policy=args.policy,
        preset=args.preset,
        rotation_aug=args.rotation_aug,
        baseline_width=args.baseline_width,
        baseline_init=args.baseline_init,
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        warmup_steps=args.warmup_steps,
        ema=args.ema,
        noise_repeats=args.noise_repeats,
        seed=args.seed,
        device=args.device,
        val_fraction=args.val_fraction,
        eval_every=args.eval_every,
        eval_max_samples=args.eval_max_samples,
        checkpoint_every=args.checkpoint_every,
        max_minutes=args.max_minutes,
        num_workers=args.num_workers,
        precision=args.precision,
        data=args.data,
        resume=args.resume,
        force=args.force,
        lab_config=None if args.lab_config is None else Path(args.lab_config),
        cache_dir=None if args.cache_dir is None else Path(args.cache_dir),
        tolerance=args.tolerance,
        rerun=args.rerun,
        progress=not args.no_progress,
        init_from=None if args.init_from is None else Path(args.init_from),
        intervention_weight=args.intervention_weight,
        policy_frame_weight=args.policy_frame_weight,
    )


def run(args) -> int:
    spec = training_spec(args)
    with progress_lines("stderr", "equidiff train: "):
        summary = run_training(spec)  # TrainJobError: its message and exit status (equidiff_ros.cli)
    if summary is not None:  # rank 0 alone reports
        print(json.dumps(summary))
    return 0
