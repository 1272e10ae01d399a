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
import json
import math
import time
from pathlib import Path


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


def _finite_or_none(reduce, values: list[float]) -> float | None:
    """``reduce`` over the episodes that had recorded TCP poses to compare with (None: none had)."""
    finite = [v for v in values if math.isfinite(v)]
    return round(float(reduce(finite)), 1) if finite else None


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from equidiff_core.bags import BagError, find_bags
    from equidiff_core.config import default_config_dir, load_lab_config
    from equidiff_core.twin.config import load_twin_config
    from equidiff_core.twin.evaluate import replay_chunks

    bags = find_bags(args.bags)
    if not bags:
        raise SystemExit(f"no bags in {', '.join(map(str, args.bags))}")
    lab = load_lab_config(args.lab_config or default_config_dir() / "lab.yaml")
    cfg = load_twin_config(args.twin_config)
    t0 = time.monotonic()
    try:
        episodes = replay_chunks(
            bags, cfg, lab, args.latency_ms / 1000, args.max_duration, log=lambda s: print(s, flush=True)
        )
    except BagError as err:
        raise SystemExit(str(err)) from None
    print(
        json.dumps(
            {
                "episodes": len(episodes),
                "recorded_success": sum(e.recorded_success is True for e in episodes),
                "replayed_success": sum(e.success for e in episodes),
                "same_outcome": sum(e.recorded_success == e.success for e in episodes),
                "tcp_gap_mean_mm": _finite_or_none(np.mean, [e.tcp_gap_mean_mm for e in episodes]),
                "tcp_gap_p95_mm_worst": _finite_or_none(np.max, [e.tcp_gap_p95_mm for e in episodes]),
                "wall_s": round(time.monotonic() - t0, 1),
            }
        )
    )
    return 0
