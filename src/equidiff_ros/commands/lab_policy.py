"""`equidiff lab policy ACTION`: enable, pause or resume the policy (policy_node's /policy/enable).

While paused the policy publishes no chunks (the arm holds its last target; the SpaceMouse
still drives it). A teleop takeover pauses it as well; it never resumes on its own.
"""

from __future__ import annotations

from equidiff_core.lab.operator_loop import Request
from equidiff_ros.lab_client import call_request

ENABLE = {"enable": True, "resume": True, "pause": False}


def add_arguments(parser) -> None:
    parser.add_argument("action", choices=list(ENABLE), help="enable | resume (the same) | pause")


def run(args) -> int:
    request = Request("enable" if ENABLE[args.action] else "pause")  # the screen's p and space
    return call_request(f"policy {args.action}", request, prefix="policy ")
