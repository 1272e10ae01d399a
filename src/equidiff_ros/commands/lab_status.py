"""`equidiff lab status`: the recorder's episode, the policy's state and whether the operator drives."""

from __future__ import annotations

import json

from equidiff_core import topics


def add_arguments(parser) -> None:
    parser.add_argument("--json", action="store_true", help="one JSON line instead of text")


def run(args) -> int:
    from equidiff_ros.commands.lab_client import LabClient
    from equidiff_ros.common import TOPIC_POLICY_STATE, TOPIC_TELEOP_ACTIVE

    with LabClient() as lab:
        state = {
            "recorder": lab.latched(topics.TOPIC_RECORDER_STATUS, "std_msgs/msg/String"),
            "policy": lab.latched(TOPIC_POLICY_STATE, "std_msgs/msg/String"),
            "teleop_active": lab.latched(TOPIC_TELEOP_ACTIVE, "std_msgs/msg/Bool"),
        }
    if args.json:
        print(json.dumps(state))
    else:
        for key, value in state.items():
            print(f"{key}: {'(no node)' if value is None else value}")
    return 0
