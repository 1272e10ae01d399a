"""`equidiff bench chunking`: whole chunks vs replace vs execution horizon vs real-time chunking, by latency, in the twin.

    equidiff bench chunking                                  # shipped checkpoint, 4 seeds, 20 s episodes
    equidiff bench chunking --seeds 1 --duration 2 --latencies 0 400 --checkpoint stand-in.pt

The in-process evaluation (``twin.evaluate.evaluate_policy``: the twin's scenes, cameras,
voxeliser, franka_node's own Controller, on simulated time, latency a parameter) rolls the same
seeds out under each execution mode and latency L:

* ``whole``: ``--execute-steps`` k steps of each chunk run before the next observation is
  answered, and each chunk carries only ``n_action_steps`` (8) steps, whatever L (policy_node
  ``latency_s:=-1``, its default before ``auto``): the command stands at each chunk's last step
  until the next chunk arrives, the stop-and-go baseline;
* ``replace``: a chunk for every observation (policy_node ``execute_steps:=1``), each replacing
  the rest of the previous one;
* ``horizon``: ``--execute-steps`` k steps of each chunk run before the next observation is
  answered, and each chunk carries k + ceil(L/dt) + 1 steps so it lasts until the next one
  arrives (policy_node ``execute_steps:=k latency_s:=L``);
* ``rtc``: the horizon's schedule, and each chunk denoised towards the previous one (hard on the
  steps due before it arrives, decaying over the rest of the overlap; policy_node ``rtc:=true``).

Prints one JSON line with ``<mode>_<L>ms_success`` (fraction of episodes),
``_boundary_dv_p95_mps`` (velocity change of the command at chunk switches, p95),
``_jerk_p95_mps3`` (commanded jerk, p95), ``_standstill_mean_ms`` / ``_standstill_p95_ms`` /
``_standstill_total_s`` / ``_standstill_fraction`` (how long the commanded TCP stands still at
each chunk switch, and the sum over the run and its share of the time), ``_mode_switch_rate`` (consecutive chunks whose
remaining steps lie more than 3 cm apart) and ``_mode_switches`` for every mode and latency
(definitions: ``twin.chunking``), with the seeds, episode length, k and wall time.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from equidiff_core.benches.chunk_modes import MODES, ChunkingSettings, run_chunking_bench
from equidiff_core.runtime.jobs import progress_lines
from equidiff_core.twin.config import EVALUATION_FIRST_SEED
from equidiff_ros.commands import print_result


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--checkpoint", type=Path, default=None, help="policy.pt (default: the shipped checkpoint)")
    parser.add_argument("--seeds", type=int, default=4, help="episodes per mode and latency (same scenes for all)")
    parser.add_argument("--seed", type=int, default=EVALUATION_FIRST_SEED, help="first scene seed (twin run's)")
    parser.add_argument("--duration", type=float, default=20.0, help="sim seconds per episode")
    parser.add_argument("--latencies", type=float, nargs="+", default=(0.0, 100.0, 200.0, 400.0), metavar="MS")
    parser.add_argument("--modes", nargs="+", choices=MODES, default=MODES)
    parser.add_argument(
        "--execute-steps", type=int, default=0, help="k for horizon and rtc (0: n_action_steps, policy_node's default)"
    )
    parser.add_argument("--device", default="cpu", help="policy device: cpu | cuda | auto")
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch intra-op threads (default 1, policy_node's torch_threads: on a shared CPU more "
        "threads spin against each other; 0: one per core idle at the start, as every equidiff command)",
    )
    parser.add_argument("--lab-config", type=Path, default=None)
    parser.add_argument("--twin-config", type=Path, default=None)


def run(args: argparse.Namespace) -> int:
    settings = ChunkingSettings(
        checkpoint=args.checkpoint,
        seeds=args.seeds,
        seed=args.seed,
        duration=args.duration,
        latencies=tuple(args.latencies),
        modes=tuple(args.modes),
        execute_steps=args.execute_steps,
        device=args.device,
        threads=args.threads,
        lab_config=args.lab_config,
        twin_config=args.twin_config,
    )
    with progress_lines():
        result = run_chunking_bench(settings)
    return print_result(result, "bench chunking")
