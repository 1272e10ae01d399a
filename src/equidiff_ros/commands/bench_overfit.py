"""`equidiff bench overfit`: can a policy fit two demonstrations? Training and conditioning, checked.

    equidiff bench overfit                          # EquiDiff, tiny preset, 1200 steps
    equidiff bench overfit --policy baseline        # 4800 steps: the baseline starts to read its voxels later

Two synthetic cube demos, trained on for ``--steps``; DDIM-16 samples for each demo's observation
must land within 1.5 cm of its own trajectory, 3x closer than to the other demo's, the width within
3 cm, and the loss must fall 10-fold (``equidiff_core.benches.overfit``). Prints one JSON line
(``errors`` per demo, ``untrained_errors`` for the same policy before training, the loss, the
training's wall and CPU seconds, the CPU); exits 3 when the check fails, saying what failed.
``--out DIR`` keeps the run (``untrained.pt``, ``run/``): written beside DIR and renamed to it once
trained; an existing DIR holding anything is refused (exit 2) before training, unless ``--force``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from equidiff_core.benches.overfit import STEPS, OverfitSettings, run_overfit_bench
from equidiff_ros.commands import add_force_argument, print_result


def add_arguments(parser) -> None:
    parser.add_argument("--policy", default="equidiff", choices=["equidiff", "baseline"])
    parser.add_argument("--preset", default="tiny", help="paper | compact | tiny")
    parser.add_argument(
        "--steps",
        type=int,
        default=None,
        help="optimiser steps (batch 2 x --noise-repeats draws; default the policy's own: "
        + ", ".join(f"{policy} {steps}" for policy, steps in STEPS.items())
        + ")",
    )
    parser.add_argument("--lr", type=float, default=2e-3)
    parser.add_argument("--noise-repeats", type=int, default=16, help="(noise, step) draws per encoder pass")
    parser.add_argument("--seed", type=int, default=0, help="the demos, the weights and the training's noise")
    parser.add_argument(
        "--out", type=Path, default=None, help="keep the run here, a new folder (default: a temporary folder)"
    )
    add_force_argument(parser)


def run(args) -> int:
    settings = OverfitSettings(
        policy=args.policy,
        preset=args.preset,
        steps=args.steps,
        lr=args.lr,
        noise_repeats=args.noise_repeats,
        seed=args.seed,
        out=args.out,
        force=args.force,
    )
    outcome = run_overfit_bench(settings)
    print_result(outcome.line)
    for line in outcome.failures:
        print(f"equidiff bench overfit: {line}", file=sys.stderr)
    return 3 if outcome.failures else 0
