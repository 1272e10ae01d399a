"""`equidiff twin evaluate`: the main job's episodes in-process, on the sim clock, no ROS.

    equidiff twin evaluate --episodes 20              # shipped checkpoint, seeds 100000.. (twin run's)
    equidiff twin evaluate --checkpoint runs/x/policy.pt --seed 5000 --latency-ms 300

The same scenes, seeds, episode length, latency budget and execution scheme as
`equidiff twin run` (policy_node's answering rule, franka_node's own Controller), stepped
synchronously in one process (``twin.evaluate.evaluate_policy``): what the main job should
score, without its processes. The arm is the one thing not the same: DirectSim's IK + joint PD
instead of franky's impedance tracker in franky-sim (docs/evaluation_scheme.md); `twin
replay-chunks` replays a live run's chunks on it to measure what that changes. The policy's
noise is seeded per scene and answered observation (``chunk.SamplingSeeds``), as policy_node's in
`twin run`, and both default to fp32: a run is repeatable, and a scene gets the same noise in
both. Prints one line per episode
and, last, one JSON line: episodes, success, reached, lifted, successful_seeds, latency_budget_ms,
max_duration_s, wall_s.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from equidiff_core.twin.config import EVALUATION_FIRST_SEED
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
    from equidiff_core.config import default_config_dir, load_lab_config
    from equidiff_core.inference import load_inference_policy
    from equidiff_core.twin.config import load_twin_config
    from equidiff_core.twin.demos import DirectRecorder
    from equidiff_core.twin.evaluate import evaluate_policy
    from equidiff_ros.commands.twin_run import SHIPPED_CHECKPOINT

    if args.episodes < 1:
        raise SystemExit("--episodes must be at least 1")
    checkpoint = args.checkpoint or SHIPPED_CHECKPOINT
    if not checkpoint.is_file():
        raise SystemExit(f"no checkpoint at {checkpoint}")
    lab = load_lab_config(args.lab_config or default_config_dir() / "lab.yaml")
    cfg = load_twin_config(args.twin_config)
    max_duration = args.max_duration or cfg.episode.max_duration_s
    policy = load_inference_policy(checkpoint, device=args.device, precision=args.precision)
    seeds = range(args.seed, args.seed + args.episodes)
    rec = DirectRecorder(cfg, lab)
    try:
        policy.warmup()  # first-call costs (seconds of compilation) out of the wall time
        t0 = time.monotonic()
        episodes = evaluate_policy(
            policy,
            cfg,
            lab,
            seeds,
            max_duration,
            recorder=rec,
            latency_s=args.latency_ms / 1000,
            execute_steps=args.execute_steps,
            log=lambda s: print(s, flush=True),
        )
        wall_s = time.monotonic() - t0
    finally:
        rec.close()
    print(
        json.dumps(
            {
                "episodes": len(episodes),
                "success": sum(e.success for e in episodes),
                "reached": sum(e.reached for e in episodes),
                "lifted": sum(e.lifted for e in episodes),
                "successful_seeds": [e.seed for e in episodes if e.success],
                "checkpoint": str(checkpoint),
                "latency_budget_ms": args.latency_ms,
                "max_duration_s": max_duration,
                "execute_steps": args.execute_steps,
                "wall_s": round(wall_s, 1),
            }
        ),
        flush=True,
    )
    return 0
