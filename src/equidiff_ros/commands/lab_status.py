"""`equidiff lab status`: the robot's state, the recorder's episode, the policy's state and whether the operator drives.

The robot's state is franka_node's latched /franka/status (moving, holding, homing, awaiting_ack,
faulted, with the reason and the last fault); where franka_node publishes none, its /diagnostics
(`faulted`, `awaiting_ack`, holding or executing) stand in, and the line says so.
"""

from __future__ import annotations

from equidiff_ros.lab_client import print_status


def add_arguments(parser) -> None:
    parser.add_argument("--json", action="store_true", help="one JSON line instead of text")


def run(args) -> int:
    return print_status(args.json)
