"""What the lab's nodes publish, as the operator loop (``lab.operator_loop``) and ``equidiff lab status`` read it:
the recorder's and the policy's state, and franka_node's (``/franka/status``, else its ``/diagnostics``)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from ..wire import topics

ROBOT_STATES = ("moving", "holding", "homing", "awaiting_ack", "faulted")
FRANKA_DIAGNOSTICS_NAME = "franka_node"  # the name of franka_node's status on /diagnostics
DIAGNOSTICS_STALE_S = 5.0  # franka_node publishes them at 1 Hz: older than this, it is gone or stuck


@dataclass(frozen=True)
class RobotStatus:
    state: str  # one of ROBOT_STATES
    reason: str = ""  # why it holds or faulted
    last_fault: str = ""
    last_fault_ns: int = 0
    source: str = topics.TOPIC_FRANKA_STATUS  # or topics.TOPIC_DIAGNOSTICS: the fallback

    def describe(self) -> str:
        """One line: the state and why (``lab status`` prints it; the screen shows the same)."""
        text = self.state.replace("_", " ")
        return f"{text}: {self.reason}" if self.reason else text


def parse_franka_status(text: str) -> RobotStatus:
    """franka_node's ``/franka/status`` JSON; ValueError saying what is wrong with it."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"{topics.TOPIC_FRANKA_STATUS} is not JSON ({err}): {text[:80]!r}") from None
    if not isinstance(data, dict) or data.get("state") not in ROBOT_STATES:
        raise ValueError(f"{topics.TOPIC_FRANKA_STATUS}: 'state' must be one of {ROBOT_STATES}: {text[:80]!r}")
    try:
        last_fault_ns = int(data.get("last_fault_ns") or 0)
    except (TypeError, ValueError):
        raise ValueError(f"{topics.TOPIC_FRANKA_STATUS}: 'last_fault_ns' is not an integer: {text[:80]!r}") from None
    return RobotStatus(
        state=data["state"],
        reason=str(data.get("reason") or ""),
        last_fault=str(data.get("last_fault") or ""),
        last_fault_ns=last_fault_ns,
    )


def robot_status_from_diagnostics(message: str, values: Mapping[str, str]) -> RobotStatus:
    """The fallback where franka_node publishes no ``/franka/status``: its ``/diagnostics``
    (``faulted``, ``awaiting_ack``, the message ``holding`` / ``executing``). Homing shows as
    moving there, and the time of the last fault is unknown."""
    awaiting = values.get("awaiting_ack", "")
    last_fault = awaiting or values.get("last_divergence", "") or values.get("last_recovery_reason", "")
    if values.get("faulted") == "True":
        state, reason = "faulted", message
    elif awaiting:
        state, reason = "awaiting_ack", awaiting
    elif message.startswith("holding"):
        state, reason = "holding", ""
    else:
        state, reason = "moving", ""
    return RobotStatus(state, reason, last_fault, 0, source=topics.TOPIC_DIAGNOSTICS)


@dataclass
class NodeView:
    """The newest of what the nodes publish (None: no node publishes it)."""

    recorder: str | None = None  # /recorder/status: idle | recording <path>
    policy: str | None = None  # /policy/state: running | paused <reason>
    teleop_active: bool | None = None  # /teleop/active
    franka_status: str | None = None  # /franka/status JSON
    franka_diagnostics: tuple[str, dict] | None = None  # franka_node's newest /diagnostics: (message, values)
    franka_diagnostics_at: float = 0.0  # when it arrived (the loop's clock)

    def robot(self, now: float) -> tuple[RobotStatus | None, str]:
        """franka_node's state (``/franka/status``, else its ``/diagnostics``) and a note on where it
        came from or why it is missing."""
        note = ""
        if self.franka_status is not None:
            try:
                return parse_franka_status(self.franka_status), ""
            except ValueError as err:
                note = f"{err}; "
        else:
            note = f"(no status) no {topics.TOPIC_FRANKA_STATUS}; "
        if self.franka_diagnostics is None:
            return None, f"{note}no franka_node {topics.TOPIC_DIAGNOSTICS} either"
        age = now - self.franka_diagnostics_at
        if age > DIAGNOSTICS_STALE_S:
            return None, f"{note}franka_node's {topics.TOPIC_DIAGNOSTICS} are {age:.0f} s old"
        return robot_status_from_diagnostics(*self.franka_diagnostics), f"{note}from {topics.TOPIC_DIAGNOSTICS}"

    @property
    def recording(self) -> Path | None:
        """The episode being recorded, if the recorder says so."""
        if self.recorder and self.recorder.startswith("recording "):
            return Path(self.recorder.removeprefix("recording ").strip())
        return None

    @property
    def policy_running(self) -> bool:
        return self.policy == "running"
