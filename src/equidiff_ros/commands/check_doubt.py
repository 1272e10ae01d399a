"""`equidiff check doubt`: the policy's doubt signal over its own training demos, the doubt gate's calibration.

    equidiff check doubt runs/pick/policy.pt --demos demos/ --write runs/pick/policy.pt --force

Each demo open loop: the frames policy_node would answer, the signal of each (``policy.doubt``;
docs/doubt.md). Prints one JSON line: ``signal``, ``samples``, ``episodes``, ``frames``, the signal's
``quantiles_m`` and ``written``. ``--write FILE`` stores the calibration (every frame's value) in a copy
of the policy file, weights untouched, where policy_node's gate (``doubt_gate``, ``doubt_quantile``)
reads it; naming the policy file itself needs ``--force``.
"""

from __future__ import annotations

from pathlib import Path

from equidiff_core.benches.doubt import DoubtCheckSettings, run_doubt_check
from equidiff_core.policy.doubt import DEFAULT_SAMPLES, DEFAULT_SIGNAL, SIGNALS
from equidiff_ros.commands import add_force_argument, print_result


def add_arguments(parser) -> None:
    parser.add_argument("policy", type=Path, help="exported policy.pt")
    parser.add_argument("--demos", type=Path, nargs="+", required=True, help="its training demos (bags or folders)")
    parser.add_argument("--episodes", type=int, default=0, help="at most this many demos (0: all)")
    parser.add_argument("--signal", default=DEFAULT_SIGNAL, choices=SIGNALS)
    parser.add_argument("--samples", type=int, default=DEFAULT_SAMPLES, help="DDIM samples per frame (spread: >= 2)")
    parser.add_argument("--write", type=Path, default=None, help="store the calibration in a copy of the policy here")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    add_force_argument(parser)


def run(args) -> int:
    settings = DoubtCheckSettings(
        policy=args.policy,
        demos=tuple(args.demos),
        episodes=args.episodes,
        signal=args.signal,
        samples=args.samples,
        write=args.write,
        force=args.force,
        threads=args.threads,
    )
    return print_result(run_doubt_check(settings), "check doubt")
