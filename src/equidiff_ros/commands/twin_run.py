"""`equidiff twin run`: the main job. The whole stack end to end in the digital twin, no hardware.

    equidiff twin run --episodes 10                 # shipped checkpoint, new random scenes
    equidiff twin run --smoke                       # 1 short episode (CI): plumbing only
    equidiff twin run --checkpoint runs/x/policy.pt --episodes 20 --seed 5000

Brings up, as separate ROS 2 processes on a private ROS_DOMAIN_ID: twin_node (franky-sim +
scene), three camera_nodes (backend twin), voxel_node, policy_node, franka_node (connected to
the twin like to a real FR3) and recorder_node. Each episode: home the arm, reset the scene to a
new seed, record, let the policy act at 5 Hz until the block rests in the bowl or time runs out.
Writes one bag per episode and one rerun recording; prints a summary and, last, one JSON line
(episodes, success_rate, inference_p95_ms, end_to_end_p95_ms, dropped_cycles, clock,
latency_budget_ms, wall_s, ...). Ctrl-C or any node failure stops every process.

OUT keeps each episode's bag as it is written, numbered after any already there, so an interrupted
run keeps what it recorded. The run's summary files, OUT/summary.json and OUT/twin_run.rrd, are
written whole at the end (beside themselves, then renamed); an existing one is refused (exit 2)
before the twin starts, unless --force.

By default the twin runs on simulated time: twin_node publishes /clock, every node runs with
use_sim_time, and the sim waits for camera frames and for each observation's chunk, which
takes effect at the observation's time + --latency-ms (the budget of a lab machine; 100 ms).
The run then measures the policy, not this machine. --realtime runs on the wall clock instead
(only where the machine holds real time: a run whose sim fell below 0.9x is flagged).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from equidiff_core.runtime.machine import PRECISIONS
from equidiff_core.twin.config import EVALUATION_FIRST_SEED, TWIN_PRECISION
from equidiff_core.twin.shipped import SHIPPED_CHECKPOINT
from equidiff_ros.commands import add_force_argument
from equidiff_ros.twin.main_job import run_main_job


def add_precision_argument(parser: argparse.ArgumentParser) -> None:
    """The policy's arithmetic in the twin (``twin.config.TWIN_PRECISION`` unless asked otherwise)."""
    parser.add_argument(
        "--precision",
        choices=PRECISIONS,
        default=TWIN_PRECISION,
        help=f"policy arithmetic (default {TWIN_PRECISION} on every machine, so results do not depend on the "
        "machine; auto: bf16 on CUDA)",
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument(
        "--seed", type=int, default=EVALUATION_FIRST_SEED, help="first episode's scene seed (then +1 each)"
    )
    parser.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        help=f"exported policy file (default: the shipped {SHIPPED_CHECKPOINT.parent.name})",
    )
    parser.add_argument(
        "--standin",
        action="store_true",
        help="use an untrained stand-in policy (plumbing test; success is meaningless)",
    )
    parser.add_argument("--out", type=Path, default=None, help="output directory (default: runs/twin_run_<time>)")
    add_force_argument(
        parser,
        help="replace OUT's summary.json and twin_run.rrd (without it an existing one is refused before the run)",
    )
    parser.add_argument("--max-duration", type=float, default=None, help="seconds per episode (twin.yaml's default)")
    parser.add_argument("--smoke", action="store_true", help="1 episode of a few seconds (CI)")
    parser.add_argument("--domain", type=int, default=None, help="ROS_DOMAIN_ID (default: a random private one)")
    parser.add_argument("--device", default="cpu", help="policy device: cpu | cuda | auto")
    add_precision_argument(parser)
    parser.add_argument("--lab-config", type=Path, default=None)
    parser.add_argument("--twin-config", type=Path, default=None)
    parser.add_argument("--record-clouds", action="store_true", help="also record the three camera clouds")
    parser.add_argument("--no-rrd", action="store_true", help="skip the rerun recording")
    parser.add_argument(
        "--attach", action="store_true", help="run the episodes against nodes already running (launch/twin.launch.py)"
    )
    parser.add_argument(
        "--lenient",
        action="store_true",
        help="with --realtime: accept observations up to 4 s old (overloaded machines)",
    )
    parser.add_argument(
        "--clock",
        choices=("sim", "realtime"),
        default="sim",
        help="sim: simulated time, in lockstep with the pipeline (default); realtime: the wall clock",
    )
    parser.add_argument(
        "--realtime",
        dest="clock",
        action="store_const",
        const="realtime",
        help="the same as --clock realtime (machines that hold real time)",
    )
    parser.add_argument(
        "--latency-ms",
        type=float,
        default=100.0,
        help="simulated time: the latency budget L; a chunk takes effect at its observation + L",
    )
    parser.add_argument(
        "--stall-timeout",
        type=float,
        default=30.0,
        help="simulated time: wall seconds the sim waits for a camera or the policy before the episode ends as stalled",
    )
    parser.add_argument(
        "--composed",
        action="store_true",
        help="run every node but twin_node in one process (one MultiThreadedExecutor)",
    )


def run(args: argparse.Namespace) -> int:
    return run_main_job(args)
