"""`equidiff lab record ACTION`: start, keep (success or failure) or discard the recorder's episode.

    equidiff lab record start        # a new episode (the recorder's task)
    equidiff lab record success      # keep it, marked a success (also: stop)
    equidiff lab record failure      # keep it, marked a failure
    equidiff lab record discard      # delete it

Calls recorder_node's services (std_srvs/Trigger), so it works under ``ros2 launch``.
"""

from __future__ import annotations

from equidiff_core.lab.operator_loop import Request
from equidiff_ros.lab_client import call_request

# action -> the operator loop's request (the service the screen's keys s, k, f and x call)
REQUESTS = {
    "start": Request("start"),
    "stop": Request("success"),
    "success": Request("success"),
    "failure": Request("failure"),
    "discard": Request("discard"),
}


def add_arguments(parser) -> None:
    parser.add_argument("action", choices=list(REQUESTS), help="start | stop = success | failure | discard")


def run(args) -> int:
    return call_request(f"record {args.action}", REQUESTS[args.action])
