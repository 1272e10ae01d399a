"""`equidiff lab record ACTION`: start, keep (success or failure) or discard the recorder's episode.

    equidiff lab record start        # a new episode (the recorder's task)
    equidiff lab record success      # keep it, marked a success (also: stop)
    equidiff lab record failure      # keep it, marked a failure
    equidiff lab record discard      # delete it

Calls recorder_node's services (std_srvs/Trigger), so it works under ``ros2 launch``.
"""

from __future__ import annotations

from equidiff_core import topics

SERVICES = {
    "start": topics.SERVICE_RECORDER_START,
    "stop": topics.SERVICE_RECORDER_STOP,
    "success": topics.SERVICE_RECORDER_STOP,
    "failure": topics.SERVICE_RECORDER_STOP_FAILURE,
    "discard": topics.SERVICE_RECORDER_DISCARD,
}


def add_arguments(parser) -> None:
    parser.add_argument("action", choices=list(SERVICES), help="start | stop = success | failure | discard")


def run(args) -> int:
    from equidiff_ros.commands.lab_client import call_service

    return call_service(f"record {args.action}", "std_srvs/srv/Trigger", SERVICES[args.action])
