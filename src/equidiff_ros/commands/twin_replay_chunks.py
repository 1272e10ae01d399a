"""`equidiff twin replay-chunks`: a live twin episode's policy chunks, replayed in-process (no ROS).

    equidiff twin replay-chunks runs/twin_run_x/bags              # every episode of a main-job run
    equidiff twin replay-chunks runs/twin_run_x/bags/twin_eval_0003

Does the in-process evaluation's arm do what the live one did? Each bag's scene (its seed) is set
up in-process and the bag's /franka/command_chunk policy chunks reach franka_node's own Controller
over DirectSim at their observation's time + the latency budget, open loop: the commands the
live arm (franky's impedance tracker in franky-sim) executed, now driving DirectSim's IK + joint
PD (``twin.evaluate.replay_chunks``). Prints one line per episode and, last, one JSON line:
episodes, recorded_success, replayed_success, same_outcome, tcp_gap_mean_mm (over all
episodes), tcp_gap_p95_mm_worst (the worst episode's 95th percentile), wall_s.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from equidiff_core.runtime.jobs import progress_lines
from equidiff_core.twin.inprocess_jobs import ChunkReplaySettings, run_chunk_replay
from equidiff_ros.commands import print_result


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("bags", nargs="+", type=Path, help="twin episode bags, or folders of them")
    parser.add_argument(
        "--latency-ms", type=float, default=100.0, help="the live run's latency budget L (twin run's default)"
    )
    parser.add_argument("--max-duration", type=float, default=None, help="seconds per episode (twin.yaml's default)")
    parser.add_argument("--lab-config", type=Path, default=None)
    parser.add_argument("--twin-config", type=Path, default=None)


def run(args: argparse.Namespace) -> int:
    settings = ChunkReplaySettings(
        bags=tuple(args.bags),
        latency_ms=args.latency_ms,
        max_duration=args.max_duration,
        lab_config=args.lab_config,
        twin_config=args.twin_config,
    )
    with progress_lines():
        result = run_chunk_replay(settings)
    return print_result(result, "twin replay-chunks")
