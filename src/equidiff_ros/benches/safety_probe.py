"""The ROS side of ``equidiff bench safety``: what its campaign (``equidiff_core.benches.fault_campaign``, ROS-free)
needs of the live graph, passed in as a ``SafetyProbe``: the rclpy client that drives franka_node and
records what comes back, a watch on /franka/status and the measured pose, and the operator's service calls
(acknowledge, home, recorder start/stop) as ``equidiff lab`` makes them.
"""

from __future__ import annotations

import json
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

import numpy as np
from geometry_msgs.msg import PoseStamped
from std_msgs.msg import String

from equidiff_core.twin.shipped import SHIPPED_CHECKPOINT, SHIPPED_NAME
from equidiff_core.wire.rosmsg import MessageError, pose_from_msg
from equidiff_core.wire.topics import SERVICE_FRANKA_ACKNOWLEDGE, TOPIC_EE_POSE, TOPIC_FRANKA_STATUS
from equidiff_ros.benches.control import approach
from equidiff_ros.common import LATCHED_QOS, RELIABLE_QOS
from equidiff_ros.control_client import ControlClient
from equidiff_ros.lab_client import LabClient, LabError


class StatusWatch:
    """franka_node's /franka/status (latched JSON) as it arrives, to wait on its state; and the
    newest measured TCP pose, orientation included (``ee_pose``, 4x4)."""

    def __init__(self, client: ControlClient):
        self.client = client
        self.history: deque = deque(maxlen=2000)  # (receive wall s, status dict)
        self.ee_pose: np.ndarray | None = None
        client.node.create_subscription(
            String, TOPIC_FRANKA_STATUS, lambda m: self.history.append((time.time(), json.loads(m.data))), LATCHED_QOS
        )
        client.node.create_subscription(PoseStamped, TOPIC_EE_POSE, self._on_pose, RELIABLE_QOS)

    def _on_pose(self, msg) -> None:
        try:
            self.ee_pose = pose_from_msg(msg)
        except MessageError:
            pass  # the newest usable pose stays; raising would end the client's spin thread

    @property
    def latest(self) -> dict:
        return self.history[-1][1] if self.history else {}

    def wait(self, predicate: Callable[[dict], bool], timeout: float, what: str, proc=None) -> dict:
        """The first status (from now on, or the latest) for which ``predicate`` holds."""
        self.client.wait_for(lambda: bool(self.history) and predicate(self.latest), timeout, what, proc)
        return self.latest

    def states_since(self, t: float) -> list[str]:
        return [status["state"] for when, status in list(self.history) if when >= t]


def acknowledge() -> tuple[bool, str]:
    """Call franka_node's /franka/acknowledge as `equidiff lab ack` does: (granted, its message)."""
    with LabClient() as lab:
        try:
            return True, lab.call("std_srvs/srv/Trigger", SERVICE_FRANKA_ACKNOWLEDGE)
        except LabError as err:
            return False, str(err)


def trigger(service: str) -> str:
    """Call a std_srvs/Trigger ``service`` as `equidiff lab` does: its message, or LabError (a RuntimeError)."""
    with LabClient() as lab:
        return lab.call("std_srvs/srv/Trigger", service)


class SafetyProbe:
    """What the campaign needs of the ROS side; each member is named for its use there."""

    ServiceError = LabError
    acknowledge = staticmethod(acknowledge)
    trigger = staticmethod(trigger)
    approach = staticmethod(approach)  # a straight line to a target, streamed as chunks (bench control's)
    watch_status = StatusWatch

    @staticmethod
    def shipped_policy() -> tuple[Path, str] | None:
        """(checkpoint, label) of the twin's trained policy, when the source tree or the install holds it."""
        return (SHIPPED_CHECKPOINT, f"shipped {SHIPPED_NAME}") if SHIPPED_CHECKPOINT.is_file() else None

    @staticmethod
    def open_client(lab, lab_path: str) -> ControlClient:
        """The rclpy client (a node spinning in a background thread) that publishes chunks and records replies."""
        return ControlClient(lab, lab_path)
