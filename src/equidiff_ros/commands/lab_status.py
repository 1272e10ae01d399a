"""`equidiff lab status`: the robot's state, the recorder's episode, the policy's state and whether the operator drives.

The robot's state is franka_node's latched /franka/status (moving, holding, homing, awaiting_ack,
faulted, with the reason and the last fault); where franka_node publishes none, its /diagnostics
(`faulted`, `awaiting_ack`, holding or executing) stand in, and the line says so.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict

from equidiff_core.operator_loop import NodeView


def add_arguments(parser) -> None:
    parser.add_argument("--json", action="store_true", help="one JSON line instead of text")


def run(args) -> int:
    from equidiff_ros.commands.lab_client import LabClient

    with LabClient() as lab:
        got = lab.snapshot()
    now = time.monotonic()
    view = NodeView(
        franka_status=got.get("franka_status"),
        franka_diagnostics=got.get("franka_diagnostics"),
        franka_diagnostics_at=now,
    )
    robot, note = view.robot(now)
    state = {
        "robot": None if robot is None else {**asdict(robot), "note": note},
        "recorder": got.get("recorder"),
        "policy": got.get("policy"),
        "teleop_active": got.get("teleop_active"),
    }
    if args.json:
        print(json.dumps(state))
        return 0
    if robot is None:
        print(f"robot: (no status) {note}")
    else:
        fault = f"; last fault: {robot.last_fault}" if robot.last_fault else ""
        print(f"robot: {robot.describe()}{fault} [{note or robot.source}]")
    for key in ("recorder", "policy", "teleop_active"):
        print(f"{key}: {'(no node)' if state[key] is None else state[key]}")
    return 0
