"""`equidiff bench twin`: what the twin main job costs this machine, and where the CPU goes.

    equidiff bench twin                         # 1 episode of 20 s sim, shipped checkpoint
    equidiff bench twin --standin --max-duration 10

Runs the main job (simulated time, all nodes as separate processes, or with ``--composed``
every node but twin_node in one process) for ``--episodes`` and
prints one JSON line: each process's CPU share during the episodes (CPU seconds per wall
second, 1.0 = one core: sim = twin_node, each camera, voxel, policy, franka, recorder, and
the supervisor = this process), the sim factor (sim seconds per wall second) and its
inverse ``wall_s_per_sim_s`` (the issue's cost: a 40 s episode takes that many times 40 s),
how the twin's wall time split between waiting for the cameras and for the policy, and the
CPU it ran on (name and whether it has AVX-512 / bf16: absolute numbers depend on it).
``--out DIR`` keeps the episodes' bags and the nodes' logs: written beside DIR and renamed to it when
the episodes have run (a run that fails leaves nothing); an existing DIR holding anything is refused
(exit 2) before the twin starts, unless ``--force``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from equidiff_core.twin.config import EVALUATION_FIRST_SEED
from equidiff_ros.benches.twin import run_twin_bench
from equidiff_ros.commands import add_force_argument
from equidiff_ros.commands.twin_run import add_precision_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--episodes", type=int, default=1)
    parser.add_argument("--max-duration", type=float, default=20.0, help="sim seconds per episode")
    parser.add_argument("--seed", type=int, default=EVALUATION_FIRST_SEED)
    parser.add_argument("--checkpoint", type=Path, default=None, help="policy (default: the shipped one)")
    parser.add_argument("--standin", action="store_true", help="an untrained tiny stand-in policy")
    parser.add_argument("--latency-ms", type=float, default=100.0)
    add_precision_argument(parser)
    parser.add_argument(
        "--max-speed", type=float, default=1.0, help="at most this many sim seconds per wall second (0: unbounded)"
    )
    parser.add_argument(
        "--torch-threads",
        type=int,
        default=1,
        help="policy_node's torch threads (default 1: beside other load two were slower)",
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="keep the bags and logs in this new folder (default: a temporary one)"
    )
    add_force_argument(parser)
    parser.add_argument(
        "--composed",
        action="store_true",
        help="every node but twin_node in one process (equidiff_ros.composed): its CPU share is reported as 'pipeline'",
    )


def run(args: argparse.Namespace) -> int:
    return run_twin_bench(args)
