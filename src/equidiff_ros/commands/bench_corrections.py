"""`equidiff bench corrections`: one round of the corrections loop, measured in the twin.

    equidiff bench corrections --out corr_bench --demos-dir gen/demos --demos-result demos_eval/result.json

The start policy (``--start``, bench demos' 10-demo EquiDiff) is rolled out on ``--rollouts`` in-range scenes
(seeds from 30000000 on: neither held-out nor demo scenes); when the scripted expert judges an episode lost
(the block knocked away or dropped, the TCP stalled, no lift after 15 s, not done after 25 s) it takes the arm
to the end, planning from where the arm and the block are. Every episode is recorded with /policy/state and
/teleop/active, so its frames are labelled the policy's or the operator's (docs/corrections.md). The start
policy is then fine-tuned on its demos plus the round (``equidiff train --init-from``: ``--fine-tune-steps``
on one thread, at most ``--max-minutes``; the operator's frames weigh ``--intervention-weight``, the policy's
``--policy-frame-weight``), and the start, corrected and reference (``--reference``, the 20-demo EquiDiff)
policies are rolled out on the same ``--eval-episodes`` held-out in-range scenes as ``bench demos``.

Prints one JSON line: each policy's success with n and its Wilson 95 % interval, the corrected policy paired
against the start and the reference on the same scenes, the expert-labelled frames each trained on (demo frames
+ operator frames), the round (takeovers and their triggers), the fine-tuning's wall time, the gate's figures
(null until the policy has a doubt gate in-process), and ``plot``: success against expert frames, with bench
demos' curve when ``--demos-result`` names its result.json.

OUT is a work folder that resumes: the round's episodes (OUT/round, listed in OUT/round.json), the fine-tuning
(OUT/corrected, from its last checkpoint) and the roll-outs (OUT/<name>/rollouts.json, scene by scene) are
kept; a ``bench demos`` rollouts.json of the same policy and scenes copied to OUT/start or OUT/reference is
reused. ``--plot FILE`` is refused if it exists, unless ``--force``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from equidiff_core.runtime.jobs import progress_lines
from equidiff_ros.commands import add_force_argument, print_result


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from equidiff_core.benches.corrections import FineTune  # torch: only once the command runs

    recipe = FineTune()  # the fine-tuning flags' defaults are the measured recipe's
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--out", type=Path, required=True, help="work folder (resumes)")
    parser.add_argument("--start", type=Path, default=Path("checkpoints/demos/equidiff_10"), help="the start run")
    parser.add_argument(
        "--reference", type=Path, default=Path("checkpoints/demos/equidiff_20"), help="the run with more demos"
    )
    parser.add_argument("--demos-dir", type=Path, default=None, help="the demos, name order = seed order")
    parser.add_argument("--start-demos", type=int, default=10, help="the start run's demos: the first N")
    parser.add_argument("--reference-demos", type=int, default=20, help="the reference run's demos: the first N")
    parser.add_argument("--rollouts", type=int, default=12, help="scenes of the round")
    parser.add_argument("--eval-episodes", type=int, default=50, help="held-out in-range scenes per policy")
    parser.add_argument("--fine-tune-steps", type=int, default=recipe.steps)
    parser.add_argument("--lr", type=float, default=recipe.lr, help="the fine-tuning's peak learning rate")
    parser.add_argument("--batch-size", type=int, default=recipe.batch_size)
    parser.add_argument("--max-minutes", type=float, default=recipe.max_minutes, help="the fine-tuning's time budget")
    parser.add_argument("--intervention-weight", type=float, default=recipe.intervention_weight)
    parser.add_argument("--policy-frame-weight", type=float, default=recipe.policy_frame_weight)
    parser.add_argument("--lift-by", type=float, default=15.0, help="takeover: the block not lifted after this, s")
    parser.add_argument("--give-up", type=float, default=25.0, help="takeover: not done after this, s")
    parser.add_argument("--max-duration", type=float, default=30.0, help="sim seconds per roll-out")
    parser.add_argument("--latency-ms", type=float, default=100.0)
    parser.add_argument(
        "--train-yaw", type=float, nargs=2, default=(-15.0, 15.0), metavar=("LO", "HI"), help="the demos' yaw range"
    )
    parser.add_argument("--demos-result", type=Path, default=None, help="bench demos' result.json: its curve")
    parser.add_argument("--plot", type=Path, default=None, help="also write the PNG here (refused if it exists)")
    add_force_argument(parser, help="replace an existing --plot FILE (OUT is a work folder: never refused)")
    parser.add_argument("--lab-config", type=Path, default=None)
    parser.add_argument("--twin-config", type=Path, default=None)
    parser.add_argument(
        "--gate-quantile",
        type=float,
        default=None,
        help="count the doubt gate's alarms at this quantile of the start policy's demos (its calibration, "
        "else calibrated here on its demos); reported as the gate's quality (docs/corrections.md)",
    )
    parser.add_argument(
        "--gate-takes-over", action="store_true", help="the gate's first alarm hands the arm to the expert"
    )
    parser.add_argument(
        "--round-only", action="store_true", help="stop after the round: its takeovers and the gate's quality"
    )


def corrections_settings(args: argparse.Namespace):
    """The bench the parsed flags ask for."""
    from equidiff_core.benches.corrections import CorrectionsSettings, FineTune
    from equidiff_core.twin.corrections import LostRule

    return CorrectionsSettings(
        out=args.out,
        start=args.start,
        reference=args.reference,
        demos_dir=args.demos_dir,
        start_demos=args.start_demos,
        reference_demos=args.reference_demos,
        rollouts=args.rollouts,
        eval_episodes=args.eval_episodes,
        fine_tune=FineTune(
            steps=args.fine_tune_steps,
            batch_size=args.batch_size,
            lr=args.lr,
            max_minutes=args.max_minutes,
            intervention_weight=args.intervention_weight,
            policy_frame_weight=args.policy_frame_weight,
        ),
        rule=LostRule(lift_by_s=args.lift_by, give_up_s=args.give_up),
        train_yaw=tuple(args.train_yaw),
        max_duration=args.max_duration,
        latency_ms=args.latency_ms,
        demos_result=args.demos_result,
        plot=args.plot,
        lab_config=args.lab_config,
        twin_config=args.twin_config,
        force=args.force,
        gate_quantile=args.gate_quantile,
        gate_takes_over=args.gate_takes_over,
        round_only=args.round_only,
    )


def run(args: argparse.Namespace) -> int:
    from equidiff_core.benches.corrections import run_corrections_bench

    with progress_lines():
        result = run_corrections_bench(corrections_settings(args))
    return print_result(result, "bench corrections")
