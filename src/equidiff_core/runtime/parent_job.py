"""Which job started this process, and whether it is still there: how a node outlives no orchestrator.

``twin.processes.ProcessGroup`` gives each node it starts its own pid in ``PARENT_PID_ENV``; every
node's spin loop (``equidiff_ros.runner``) asks ``job_gone`` and shuts down once that job died.
"""

from __future__ import annotations

import os

# A ProcessGroup's pid, given to each node it starts (see job_gone)
PARENT_PID_ENV = "EQUIDIFF_PARENT_PID"


def job_gone() -> bool:
    """In a node started by a ProcessGroup: whether that job's process has died (we were re-parented).

    The nodes run in sessions of their own, so a job killed with SIGKILL can neither stop them
    nor pass on a terminal's Ctrl-C: without this check they ran on for ever (a twin_node
    stepping the sim, cameras rendering) on the user's machine. Always False outside a job.
    """
    parent = int(os.environ.get(PARENT_PID_ENV, "0") or 0)
    return parent > 0 and os.getppid() != parent
