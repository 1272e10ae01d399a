"""Kept for ``bench_safety``'s imports until it moves out of ``commands/``: the lab's ROS client is
``equidiff_ros.lab_client``."""

from equidiff_ros.lab_client import LabClient, LabError, call_request

__all__ = ["LabClient", "LabError", "call_request"]
