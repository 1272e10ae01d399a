"""`equidiff twin evaluate`: the main job's episodes in-process, on the sim clock, no ROS.

    equidiff twin evaluate --episodes 20              # shipped checkpoint, seeds 100000.. (twin run's)
    equidiff twin evaluate --checkpoint runs/x/policy.pt --seed 5000 --latency-ms 300

The same scenes, seeds, episode length, latency budget and execution scheme as
`equidiff twin run` (policy_node's answering rule, franka_node's own Controller), stepped
synchronously in one process (``twin.evaluate.evaluate_policy``): what the main job should
score, without its processes. The arm is the one thing not the same: DirectSim's IK + joint PD
instead of franky's impedance tracker in franky-sim (docs/evaluation_scheme.md); `twin
replay-chunks` replays a live run's chunks on it to measure what that changes. The policy's
noise is seeded per scene and answered observation (``wire.chunk.SamplingSeeds``), as policy_node's in
`twin run`, and both default to fp32: a run is repeatable, and a scene gets the same noise in
both. Prints one line per episode
and, last, one JSON line: episodes, success, reached, lifted, successful_seeds, latency_budget_ms,
max_duration_s, wall_s.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from equidiff_core.runtime.jobs import progress_lines
from equidiff_core.twin.config import EVALUATION_FIRST_SEED
from equidiff_core.twin.inprocess_jobs import EvaluationSettings, run_evaluation
from equidiff_ros.commands import print_result
from equidiff_ros.commands.twin_run import add_precision_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument(
        "--seed", type=int, default=EVALUATION_FIRST_SEED, help="first episode's scene seed (then +1 each)"
    )
    parser.add_argument("--checkpoint", type=Path, default=None, help="policy.pt (default: the shipped checkpoint)")
    parser.add_argument("--max-duration", type=float, default=None, help="seconds per episode (twin.yaml's default)")
    parser.add_argument(
        "--latency-ms",
        type=float,
        default=100.0,
        help="each chunk reaches franka_node this long after its observation (twin run's budget)",
    )
    parser.add_argument(
        "--execute-steps",
        type=int,
        default=0,
        help="answer every N-th observation (0: one per chunk, policy_node's default)",
    )
    parser.add_argument("--device", default="cpu", help="policy device: cpu | cuda | auto")
    add_precision_argument(parser)
    parser.add_argument("--lab-config", type=Path, default=None)
    parser.add_argument("--twin-config", type=Path, default=None)


def run(args: argparse.Namespace) -> int:
    settings = EvaluationSettings(
        episodes=args.episodes,
        seed=args.seed,
        checkpoint=args.checkpoint,
        max_duration=args.max_duration,
        latency_ms=args.latency_ms,
        execute_steps=args.execute_steps,
        device=args.device,
        precision=args.precision,
        lab_config=args.lab_config,
        twin_config=args.twin_config,
    )
    with progress_lines():
        result = run_evaluation(settings)
    return print_result(result, "twin evaluate")
