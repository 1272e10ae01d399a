"""`equidiff bench generalization`: EquiDiff against two non-equivariant baselines on unseen object yaw.

    equidiff bench generalization                       # 40 demos, yaw in [-15, 15] deg, compact, 6000 steps
    equidiff bench generalization --train-steps 20000 --batch-size 64 --lr 1e-4 --device cuda
    equidiff bench generalization --quick               # minutes-scale plumbing check (tiny preset)
    equidiff bench generalization --trained gpu_run/ --demos-dir packed/   # policies trained elsewhere
    equidiff bench generalization --out gen --policies equidiff      # in parts, one policy per session

The paper's central claim on our twin, measured the way its appendix compares equivariance by
construction with equivariance by data augmentation: (1) record ``--demos`` scripted-expert
demos whose block and bowl yaw are drawn from the narrow ``--train-yaw`` range (twin collect
--direct); (2) train three policies with ``equidiff train`` on exactly those bags, same preset,
steps, batch and seed: ``equidiff`` (EquiDiff, Vo) and ``baseline`` (DiffPo-C, Vo) with
``--rotation-aug`` (default none), and ``baseline_aug`` (DiffPo-C with ``--baseline-aug``,
default continuous rotation about z: the paper's "CNN + Aug"); (3) roll each out in closed loop
(in-process, sim clock, same seeds). Two gates come before the claim is measured. First, before
any roll-out, every policy's DDIM action error on its training samples (what ``equidiff train``
records at its end) must be within ``--max-fit-ratio`` (1.5) times EquiDiff's: a policy above it
has not fit its own demos, and the bench reports it *under-fit* and exits 4 (a verdict of the
network or its training, not of the budget for generalisation). Then each is rolled out on
``--in-range-episodes`` scenes inside the training range; a policy that solves fewer than
``--min-in-range`` of those has not learned the task at this budget, and its unseen-yaw score
would say nothing: the bench names it, says the budget is too small, skips the unseen-yaw
rollouts and exits 3. Otherwise (4) all three are rolled out on scenes whose block yaw lies at
least 15 deg outside the training range, modulo the box's half-turn symmetry (the round bowl's
yaw does not matter). Prints one JSON line: equidiff_success, baseline_success,
baseline_aug_success, their *_in_range_success, each with *_ci95 (n and Wilson 95 % interval),
paired (each baseline against EquiDiff on the same scenes: difference, its 95 % interval, McNemar p), under_fit, failed_in_range, verdict,
equidiff_minus_baseline_points, goal_met (EquiDiff >= 80 % at unseen yaw and >= 30 points above
the non-augmented baseline), unseen_by_yaw (each policy's unseen-yaw episodes by whether C4 --
offset modulo 90 deg -- or C8 -- modulo 45 deg -- maps the block into the training range),
train_fit, demos, train_steps, ...

The three must share one recipe (preset, steps, batch, warm-up, seed, noise repeats, EMA,
precision; rotation augmentation differs by design, and the baselines train at ``--baseline-lr``):
the bench compares their ``equidiff train`` run.json recipes and refuses to roll out policies
trained differently. On a small CPU
one policy can take a whole working session, so ``--policies`` trains a subset into ``--out``
(demos recorded there by the first call are reused) and prints a ``pending`` line; once
``--out`` holds all three, the next call rolls them out. Reused demos (``--demos-dir`` or an
earlier call's) whose metadata records another block yaw range than ``--train-yaw`` are refused.

The default recipe (compact, 6000 steps of batch 8 with 4 noise draws per encoder pass, EMA, peak
lr 5e-4, the baselines' 1e-3) is the one ``bench demos`` uses too, so one EquiDiff run on the 40 demos serves both. On a
CPU the training dominates (hours for the default recipe); ``--max-minutes`` gives each policy a training budget
(``equidiff train`` stops, checkpoints and exports; the steps each trained are reported).
The measured results and how long each part took, with the commands and machines, are in docs/results/twin.md
("The paper's claims, measured"; numbers live there only, so this text cannot go stale).

``--out`` is a work folder, filled over several calls, so it is never refused; every file the bench
writes there (result.json, <policy>/rollouts_*.json) is written whole, beside itself, and renamed
into place.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from equidiff_core.benches.generalization import POLICIES, GeneralizationSettings, run_generalization
from equidiff_core.benches.stats import SCENES_PER_CELL
from equidiff_core.benches.training_runs import BASELINE_LR, EQUIDIFF_LR, MAX_FIT_RATIO
from equidiff_core.policy.presets import ROTATION_AUGS
from equidiff_core.runtime.jobs import progress_lines
from equidiff_ros.commands import bench_recipe, print_result


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--demos", type=int, default=40)
    parser.add_argument("--train-steps", type=int, default=6000)
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument(
        "--lr",
        type=float,
        default=EQUIDIFF_LR,
        help="EquiDiff's peak learning rate (default 5e-4: the shipped twin checkpoint's recipe for a few "
        "thousand steps of batch 8; equidiff train's 1e-4 suits long runs)",
    )
    parser.add_argument(
        "--baseline-lr",
        type=float,
        default=BASELINE_LR,
        help="peak learning rate of baseline and baseline_aug (default 1e-3: at 5e-4 the baseline under-fits "
        "this budget, docs/model.md; pass --lr's value for one rate for all)",
    )
    parser.add_argument(
        "--eval-episodes",
        type=int,
        default=SCENES_PER_CELL,
        help=f"unseen-yaw episodes per policy (default {SCENES_PER_CELL}: what tells a 20-point difference from "
        "chance, docs/evaluation_scheme.md)",
    )
    parser.add_argument(
        "--in-range-episodes",
        type=int,
        default=SCENES_PER_CELL,
        help="episodes per policy with block yaw inside the training range, rolled out first (0: none)",
    )
    parser.add_argument(
        "--train-yaw",
        type=float,
        nargs=2,
        default=(-15.0, 15.0),
        metavar=("LO", "HI"),
        help="object yaw range of the demos, degrees",
    )
    parser.add_argument("--preset", default="compact")
    parser.add_argument(
        "--rotation-aug",
        choices=ROTATION_AUGS,
        default="none",
        help="training rotation augmentation of equidiff and baseline (default none: the claim is "
        "equivariance by construction; with continuous the baseline sees every yaw too)",
    )
    parser.add_argument(
        "--baseline-aug",
        choices=[a for a in ROTATION_AUGS if a != "none"],
        default="continuous",
        help="rotation augmentation of the third policy, baseline_aug (the paper's CNN + Aug)",
    )
    parser.add_argument(
        "--min-in-range",
        type=float,
        default=0.6,
        help="fraction of the in-range scenes every policy must solve before any is rolled out at "
        "unseen yaw (0: no gate)",
    )
    parser.add_argument(
        "--max-fit-ratio",
        type=float,
        default=MAX_FIT_RATIO,
        help="before any roll-out, every policy's DDIM action error on its training samples must be within "
        "this factor of EquiDiff's, else the bench reports it under-fit and exits 4 (0: no gate; runs that "
        "recorded no such error are not judged)",
    )
    parser.add_argument(
        "--noise-repeats",
        type=int,
        default=4,
        help="(noise, step) draws per observation and encoder pass (equidiff train --noise-repeats)",
    )
    parser.add_argument(
        "--ema",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="train with an EMA of the weights (equidiff train --ema; default on)",
    )
    parser.add_argument(
        "--policies",
        nargs="+",
        choices=POLICIES,
        default=list(POLICIES),
        metavar="NAME",
        help="train only these now, into --out/NAME (default all three); the others must be in --out "
        "from an earlier call with the same recipe before anything is rolled out",
    )
    parser.add_argument("--device", default="auto", help="auto | cpu | cuda")
    parser.add_argument(
        "--out", type=Path, default=None, help="work directory (default runs/bench_generalization_<time>)"
    )
    parser.add_argument("--demos-dir", type=Path, default=None, help="reuse demos recorded earlier (narrow yaw)")
    parser.add_argument(
        "--trained",
        type=Path,
        default=None,
        metavar="DIR",
        help="evaluate DIR/equidiff, DIR/baseline and DIR/baseline_aug (policy.pt + history.json, e.g. "
        "trained on a GPU machine from `equidiff dataset pack`ed demos) instead of recording and training",
    )
    parser.add_argument("--max-duration", type=float, default=30.0, help="sim seconds per evaluation episode")
    parser.add_argument(
        "--latency-ms",
        type=float,
        default=100.0,
        help="latency budget: each chunk takes effect this long after its observation, as in "
        "`equidiff twin run --latency-ms`",
    )
    parser.add_argument(
        "--max-minutes",
        type=float,
        default=None,
        help="training time budget per policy (equidiff train --max-minutes: stops and exports)",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="plumbing check: 4 demos, 30 steps, tiny preset, 1 + 1 episodes of 6 s, no gate",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--lab-config", type=Path, default=None)
    parser.add_argument("--twin-config", type=Path, default=None)


def generalization_settings(args: argparse.Namespace) -> GeneralizationSettings:
    """The bench the parsed flags ask for (``--quick``: its plumbing check)."""
    settings = GeneralizationSettings(
        recipe=bench_recipe(args),
        demos=args.demos,
        eval_episodes=args.eval_episodes,
        in_range_episodes=args.in_range_episodes,
        train_yaw=tuple(args.train_yaw),
        rotation_aug=args.rotation_aug,
        baseline_aug=args.baseline_aug,
        min_in_range=args.min_in_range,
        max_fit_ratio=args.max_fit_ratio,
        policies=tuple(args.policies),
        out=args.out,
        demos_dir=args.demos_dir,
        trained=args.trained,
        max_duration=args.max_duration,
        latency_ms=args.latency_ms,
        twin_config=args.twin_config,
    )
    return settings.quick() if args.quick else settings


def run(args: argparse.Namespace) -> int:
    with progress_lines():
        result = run_generalization(generalization_settings(args))
    # exit status 4: the training-fit gate stopped the bench; 3: the in-range gate did
    status = 4 if result.get("under_fit") else 3 if result.get("failed_in_range") else 0
    return print_result(result, "bench generalization", status)
