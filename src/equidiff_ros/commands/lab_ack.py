"""`equidiff lab ack`: let the arm go on after a robot error or a divergence stop.

franka_node never resumes on its own: after a reflex or a divergence stop it holds where the
arm is and refuses every chunk until an operator acknowledges (its /franka/acknowledge
service). Look at the arm and at franka_node's /diagnostics (`equidiff lab status`) first.
"""

from __future__ import annotations

from equidiff_core.lab.operator_loop import Request
from equidiff_ros.lab_client import call_request


def add_arguments(parser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]


def run(args) -> int:
    return call_request("ack", Request("ack"), prefix="franka_node ")
