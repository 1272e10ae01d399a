"""`equidiff bench demos`: sample efficiency, success against the number of demos (the paper's Table 2).

    equidiff bench demos --out demos_bench --demos-dir gen/demos          # 10/20/40 demos, both policies
    equidiff bench demos --out demos_bench --demos-dir gen/demos --policies equidiff --train-counts 10 20
    equidiff bench demos --trained checkpoints/demos --demos-dir gen/demos --out eval   # roll out only

EquiDiff (Vo) and DiffPo-C (Vo) train on the first 10, 20 and 40 (``--counts``) of the same narrow-yaw
demos (``--demos-dir``, or recorded into OUT/demos like ``bench generalization`` does; one recording
serves both benches), with one recipe and seed (defaults: compact, 6000 steps of batch 8 with 4 noise
draws, EMA, peak lr 5e-4 for EquiDiff and 1e-3 for the baseline, no rotation augmentation), each into
OUT/<policy>_<count>. Each is rolled out
in closed loop (in-process, sim clock) on the same ``--eval-episodes`` scenes whose block yaw lies
inside the demos' range. Prints one JSON line: ``success`` per policy per demo count with ``success_ci95``
(Wilson 95 % intervals) and ``paired`` (EquiDiff against the baseline on the same scenes), the roll-outs'
stages, each run's DDIM action error on its training samples (``train_fit``, and ``under_fit``: runs
more than ``--max-fit-ratio`` times EquiDiff's at the same count, named, not stopped: too few demos
is what this bench varies), the recipe, and ``plot``, a PNG of success against demo count.

On a small CPU one run fills much of a working session: ``--policies`` / ``--train-counts`` train a
subset now (side by side, the cores shared out; an interrupted run resumes from its last.ckpt), and
the call after which OUT holds every run rolls them all out (roll-outs already done are kept in
OUT/<run>/rollouts.json and reused). The runs must share one recipe: their run.json files are
compared and policies trained differently are refused (exit 2).

OUT is a work folder, filled over several calls, so it is never refused; every file the bench writes
there (result.json, success_vs_demos.png, OUT/<run>/rollouts.json) is written whole, beside itself, and
renamed into place. ``--plot FILE`` is a file you name: an existing one is refused (exit 2) before
anything runs, unless ``--force``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from equidiff_core.benches.sample_efficiency import DEMO_COUNTS, POLICIES, DemosSettings, run_demos_bench
from equidiff_core.benches.stats import SCENES_PER_CELL
from equidiff_core.benches.training_runs import BASELINE_LR, EQUIDIFF_LR, MAX_FIT_RATIO
from equidiff_core.runtime.jobs import progress_lines
from equidiff_ros.commands import add_force_argument, bench_recipe, print_result


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--counts", type=int, nargs="+", default=list(DEMO_COUNTS), help="demo counts compared")
    parser.add_argument("--policies", nargs="+", choices=POLICIES, default=list(POLICIES), help="train only these now")
    parser.add_argument(
        "--train-counts", type=int, nargs="+", default=None, help="train only these demo counts now (default --counts)"
    )
    parser.add_argument("--train-steps", type=int, default=6000)
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--lr", type=float, default=EQUIDIFF_LR, help="peak learning rate (EquiDiff's)")
    parser.add_argument(
        "--baseline-lr",
        type=float,
        default=BASELINE_LR,
        help="the baseline's peak learning rate (default 1e-3: at 5e-4 it under-fits this budget; docs/model.md)",
    )
    parser.add_argument("--noise-repeats", type=int, default=4)
    parser.add_argument("--ema", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--preset", default="compact")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="auto", help="auto | cpu | cuda")
    parser.add_argument("--max-minutes", type=float, default=None, help="training time budget per run")
    parser.add_argument(
        "--eval-episodes",
        type=int,
        default=SCENES_PER_CELL,
        help=f"in-range scenes per run (default {SCENES_PER_CELL}: docs/evaluation_scheme.md)",
    )
    parser.add_argument("--max-duration", type=float, default=30.0, help="sim seconds per episode")
    parser.add_argument(
        "--latency-ms", type=float, default=100.0, help="each chunk takes effect this long after its observation"
    )
    parser.add_argument(
        "--train-yaw",
        type=float,
        nargs=2,
        default=(-15.0, 15.0),
        metavar=("LO", "HI"),
        help="the demos' block yaw range",
    )
    parser.add_argument(
        "--max-fit-ratio",
        type=float,
        default=MAX_FIT_RATIO,
        help="under-fit: training-sample action error above this times EquiDiff's",
    )
    parser.add_argument("--out", type=Path, default=None, help="work directory (default runs/bench_demos_<time>)")
    parser.add_argument(
        "--demos-dir", type=Path, default=None, help="narrow-yaw demos recorded earlier (name order = seed order)"
    )
    parser.add_argument(
        "--trained",
        type=Path,
        default=None,
        metavar="DIR",
        help="roll out DIR/<policy>_<count>/policy.pt (or weights.ckpt; a folder with only same_as names another "
        "bench's run); train nothing",
    )
    parser.add_argument("--plot", type=Path, default=None, help="also write the PNG here (refused if it exists)")
    add_force_argument(parser, help="replace an existing --plot FILE (OUT is a work folder: never refused)")
    parser.add_argument("--lab-config", type=Path, default=None)
    parser.add_argument("--twin-config", type=Path, default=None)


def demos_settings(args: argparse.Namespace) -> DemosSettings:
    """The bench the parsed flags ask for."""
    return DemosSettings(
        recipe=bench_recipe(args),
        counts=tuple(args.counts),
        policies=tuple(args.policies),
        train_counts=None if args.train_counts is None else tuple(args.train_counts),
        eval_episodes=args.eval_episodes,
        max_duration=args.max_duration,
        latency_ms=args.latency_ms,
        train_yaw=tuple(args.train_yaw),
        max_fit_ratio=args.max_fit_ratio,
        out=args.out,
        demos_dir=args.demos_dir,
        trained=args.trained,
        plot=args.plot,
        twin_config=args.twin_config,
        force=args.force,
    )


def run(args: argparse.Namespace) -> int:
    with progress_lines():
        result = run_demos_bench(demos_settings(args))
    return print_result(result, "bench demos")
