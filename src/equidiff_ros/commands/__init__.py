"""The ``equidiff`` subcommands, one module each (``add_arguments`` + ``run``), and what they share: options, the
training benches' recipe, a job's result printed as its JSON line."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

FORCE_HELP = "replace an existing output (only once the new one is complete; without it an existing one is refused)"


def add_force_argument(parser: argparse.ArgumentParser, help: str = FORCE_HELP) -> None:
    """``--force``: every command that writes refuses an existing output (``OutputExistsError``) without it."""
    parser.add_argument("--force", action="store_true", help=help)


def bench_recipe(args: argparse.Namespace):
    """The training recipe of ``bench generalization`` / ``bench demos``'s flags (they share these)."""
    from equidiff_core.benches.training_runs import Recipe  # torch: only for the commands that train

    return Recipe(
        preset=args.preset,
        steps=args.train_steps,
        batch_size=args.batch_size,
        lr=args.lr,
        seed=args.seed,
        device=args.device,
        noise_repeats=args.noise_repeats,
        ema=args.ema,
        max_minutes=args.max_minutes,
        lab_config=None if args.lab_config is None else Path(args.lab_config),
        baseline_lr=args.baseline_lr,
    )


def print_result(result: dict, command: str = "", exit_status: int = 0) -> int:
    """Print a job's result as its JSON line; a non-zero ``exit_status`` (a gate that stopped it) also prints
    its ``verdict`` on stderr as ``equidiff <command>: <verdict>``. Returns ``exit_status``."""
    print(json.dumps(result))
    if exit_status:
        print(f"equidiff {command}: {result['verdict']}", file=sys.stderr)
    return exit_status
