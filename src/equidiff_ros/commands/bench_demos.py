"""`equidiff bench demos`: sample efficiency, success against the number of demos (the paper's Table 2).

    equidiff bench demos --out demos_bench --demos-dir gen/demos          # 10/20/40 demos, both policies
    equidiff bench demos --out demos_bench --demos-dir gen/demos --policies equidiff --train-counts 10 20
    equidiff bench demos --trained checkpoints/demos --demos-dir gen/demos --out eval   # roll out only

EquiDiff (Vo) and DiffPo-C (Vo) train on the first 10, 20 and 40 (``--counts``) of the same narrow-yaw
demos (``--demos-dir``, or recorded into OUT/demos like ``bench generalization`` does; one recording
serves both benches), with one recipe and seed (defaults: compact, 6000 steps of batch 8 with 4 noise
draws, EMA, lr 5e-4, no rotation augmentation), each into OUT/<policy>_<count>. Each is rolled out
in closed loop (in-process, sim clock) on the same ``--eval-episodes`` scenes whose block yaw lies
inside the demos' range. Prints one JSON line: ``success`` per policy per demo count, the roll-outs'
stages, each run's DDIM action error on its training samples (``train_fit``, and ``under_fit``: runs
more than ``--max-fit-ratio`` times EquiDiff's at the same count, named, not stopped: too few demos
is what this bench varies), the recipe, and ``plot``, a PNG of success against demo count.

On a small CPU one run fills much of a working session: ``--policies`` / ``--train-counts`` train a
subset now (side by side, the cores shared out; an interrupted run resumes from its last.ckpt), and
the call after which OUT holds every run rolls them all out (roll-outs already done are kept in
OUT/<run>/rollouts.json and reused). The runs must share one recipe: their run.json files are
compared and policies trained differently are refused (exit 2).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from equidiff_core.benches.demo_sets import demos_off_range, ensure_demos, nested_subsets
from equidiff_core.benches.demos import DEMO_COUNTS, POLICIES, run_name
from equidiff_core.benches.training_runs import (
    MAX_FIT_RATIO,
    SLIM_CHECKPOINT,
    Recipe,
    TrainRunError,
    resolve_run,
    start_run,
    wait_for_runs,
)


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
    parser.add_argument("--lr", type=float, default=5e-4)
    parser.add_argument("--noise-repeats", type=int, default=4)
    parser.add_argument("--ema", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--preset", default="compact")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="auto", help="auto | cpu | cuda")
    parser.add_argument("--max-minutes", type=float, default=None, help="training time budget per run")
    parser.add_argument("--eval-episodes", type=int, default=20, help="in-range scenes per run")
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
    parser.add_argument("--plot", type=Path, default=None, help="also write the PNG here")
    parser.add_argument("--lab-config", type=Path, default=None)
    parser.add_argument("--twin-config", type=Path, default=None)


def run(args: argparse.Namespace) -> int:
    from equidiff_core.twin.config import load_twin_job_configs

    if args.eval_episodes < 1 or min(args.counts) < 1:
        print("equidiff bench demos: need --eval-episodes >= 1 and positive --counts", file=sys.stderr)
        return 2
    if args.device == "auto":
        import torch

        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    t_start = time.monotonic()
    configs = load_twin_job_configs(args.lab_config, args.twin_config)
    lab, cfg = configs.lab, configs.twin
    out = args.out or Path("runs") / time.strftime("bench_demos_%Y%m%d_%H%M%S")
    out.mkdir(parents=True, exist_ok=True)
    runs_dir = args.trained or out
    all_runs = [run_name(p, n) for p in POLICIES for n in args.counts]
    minutes = {}
    if args.trained is None:
        demos_dir, _ = ensure_demos(
            args.demos_dir,
            out,
            max(args.counts),
            cfg.with_yaw_range(tuple(args.train_yaw)),
            lab,
            args.seed,
            log=lambda s: print(s, flush=True),
        )
        wrong, _ = demos_off_range(demos_dir, tuple(args.train_yaw))
        if wrong:
            print(
                f"equidiff bench demos: {len(wrong)} demos in {demos_dir} were drawn from another block yaw "
                f"range than --train-yaw, e.g. {wrong[0]}",
                file=sys.stderr,
            )
            return 2
        try:
            subsets = nested_subsets(demos_dir, args.counts)
        except ValueError as err:
            print(f"equidiff bench demos: {err}", file=sys.stderr)
            return 2
        minutes["demos"] = round((time.monotonic() - t_start) / 60, 1)
        t_train = time.monotonic()
        try:
            trained_now = _train(args, out, subsets)
        except TrainRunError as err:
            print(f"equidiff bench demos: {err}\nrerun the same command to resume", file=sys.stderr)
            return 1
        minutes["train"] = round((time.monotonic() - t_train) / 60, 1)
        pending = [name for name in all_runs if not (resolve_run(out / name) / "policy.pt").is_file()]
        if pending:
            print(
                json.dumps(
                    {
                        "bench": "demos",
                        "trained": trained_now,
                        "pending": pending,
                        "out": str(out),
                        "next": f"equidiff bench demos --out {out} --demos-dir {demos_dir} --policies "
                        + " ".join(p for p in POLICIES if any(name.startswith(p + "_") for name in pending))
                        + " --train-counts "
                        + " ".join(str(n) for n in args.counts if any(name.endswith(f"_{n}") for name in pending))
                        + " with this call's recipe flags",
                        "minutes": minutes,
                    }
                )
            )
            return 0
    missing = [
        name
        for name in all_runs
        if not any((resolve_run(runs_dir / name) / f).is_file() for f in ("policy.pt", SLIM_CHECKPOINT))
    ]
    if missing:
        print(
            f"equidiff bench demos: no policy.pt or {SLIM_CHECKPOINT} for {', '.join(missing)} in {runs_dir}",
            file=sys.stderr,
        )
        return 2
    from equidiff_core.benches.demos import evaluate_runs

    try:
        result = evaluate_runs(
            runs_dir,
            out,
            args.counts,
            cfg,
            lab,
            args.eval_episodes,
            tuple(args.train_yaw),
            args.max_duration,
            args.latency_ms / 1000,
            args.max_fit_ratio,
            args.device,
            log=lambda s: print(s, flush=True),
        )
    except ValueError as err:  # the runs' recipes differ
        print(f"equidiff bench demos: {err}", file=sys.stderr)
        return 2
    result["minutes"] = {**minutes, **result["minutes"]}
    if args.plot is not None:
        import shutil

        args.plot.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(result["plot"], args.plot)
    (out / "result.json").write_text(json.dumps(result) + "\n")
    print(json.dumps(result))
    return 0


def _train(args, out: Path, subsets: dict[int, list[Path]]) -> list[str]:
    """Train the requested runs not trained yet, side by side; their names."""
    recipe = Recipe(
        preset=args.preset,
        steps=args.train_steps,
        batch_size=args.batch_size,
        lr=args.lr,
        seed=args.seed,
        device=args.device,
        noise_repeats=args.noise_repeats,
        ema=args.ema,
        max_minutes=args.max_minutes,
        lab_config=args.lab_config,
    )
    counts = args.train_counts or args.counts
    todo = [
        (policy, n)
        for policy in POLICIES
        if policy in args.policies
        for n in counts
        if n in subsets and not (resolve_run(out / run_name(policy, n)) / "policy.pt").is_file()
    ]
    if not todo:
        return []
    threads = max(1, (os.cpu_count() or 2) // len(todo))
    runs, outs = {}, {}
    for policy, n in todo:
        name = run_name(policy, n)
        outs[name] = out / name
        cmd = recipe.train_command(policy, "none", subsets[n], outs[name])
        print(f"[bench] training {name} on {n} demos: {' '.join(cmd[3:5])} ... {' '.join(cmd[3 + n :])}", flush=True)
        runs[name] = start_run(cmd, outs[name], threads)
    deadline = None if args.max_minutes is None else time.monotonic() + args.max_minutes * 60 + 600
    wait_for_runs(runs, outs, deadline)
    return list(runs)
