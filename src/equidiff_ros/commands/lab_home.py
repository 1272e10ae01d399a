"""`equidiff lab home`: glide the arm slowly to the configured home pose (franka_node's /franka/home).

Between episodes, with the policy paused (`equidiff lab policy pause`): chunks are refused
until the arm arrives. Refused while a stop awaits acknowledgement (`equidiff lab ack` first,
after looking at the arm). Speed and pose: control.yaml `home_*`.
"""

from __future__ import annotations

from equidiff_core.lab.operator_loop import Request
from equidiff_ros.lab_client import call_request


def add_arguments(parser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]


def run(args) -> int:
    return call_request("home", Request("home"), prefix="franka_node ")
