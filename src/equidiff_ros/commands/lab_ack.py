"""`equidiff lab ack`: let the arm go on after a robot error or a divergence stop.

franka_node never resumes on its own: after a reflex or a divergence stop it holds where the
arm is and refuses every chunk until an operator acknowledges (its /franka/acknowledge
service). Look at the arm and at franka_node's /diagnostics (`equidiff lab status`) first.
"""

from __future__ import annotations


def add_arguments(parser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]


def run(args) -> int:
    from equidiff_core.topics import SERVICE_FRANKA_ACKNOWLEDGE
    from equidiff_ros.commands.lab_client import call_service

    return call_service("ack", "std_srvs/srv/Trigger", SERVICE_FRANKA_ACKNOWLEDGE, prefix="franka_node ")
