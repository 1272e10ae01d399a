"""The ROS side of ``equidiff lab``: one node that calls the operator services and reads the latched state.

Used by ``lab_screen`` (the terminal UI) and the one-shot ``equidiff lab`` commands (``print_status`` is
``lab status``).

Everything goes through services and latched topics, not a node's stdin, so it works the
same under ``ros2 launch`` (where no node has a terminal), over ssh, and in the twin. The
one-shot commands (``lab record``, ``lab status``...) spin it in the caller's thread; the
terminal UI (``equidiff lab``) lets it spin in the background (``watch``) and calls services
from its worker thread.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

from equidiff_core.lab.node_view import FRANKA_DIAGNOSTICS_NAME, NodeView
from equidiff_core.lab.operator_loop import Request
from equidiff_core.wire import topics
from equidiff_core.wire.rosmsg import MessageError, RclpyFactory, diagnostic_entries
from equidiff_ros.common import LATCHED_QOS, RELIABLE_QOS

SERVICE_WAIT_S = 5.0
CALL_TIMEOUT_S = 15.0
# NodeView field -> its latched topic and type
WATCHED_TOPICS = {
    "recorder": (topics.TOPIC_RECORDER_STATUS, "std_msgs/msg/String"),
    "policy": (topics.TOPIC_POLICY_STATE, "std_msgs/msg/String"),
    "teleop_active": (topics.TOPIC_TELEOP_ACTIVE, "std_msgs/msg/Bool"),
    "franka_status": (topics.TOPIC_FRANKA_STATUS, "std_msgs/msg/String"),
}


class LabError(RuntimeError):
    """A service is missing or refused the request."""


def call_service(command: str, srv_type: str, name: str, prefix: str = "", **request) -> int:
    """One ``equidiff lab`` action: call the service, print its answer (``prefix`` first), or
    print why it failed to stderr under ``command``'s name; the exit code."""
    with LabClient() as lab:
        try:
            print(f"{prefix}{lab.call(srv_type, name, **request)}")
        except LabError as err:
            print(f"equidiff lab {command}: {err}", file=sys.stderr)
            return 1
    return 0


def call_request(command: str, request: Request, prefix: str = "") -> int:
    """``call_service`` for one of the operator loop's requests (the same service the screen's key calls)."""
    return call_service(command, request.srv_type, request.service, prefix=prefix, **request.fields)


class LabClient:
    def __init__(self):
        self.rclpy = rclpy
        self.factory = RclpyFactory()
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        # A short-lived client: without the parameter services and rosout it brings 13 fewer endpoints for
        # every running node to discover before its call or snapshot goes through.
        self.node = rclpy.create_node(
            "equidiff_lab", context=self.context, start_parameter_services=False, enable_rosout=False
        )
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._clients: dict[tuple[str, str], object] = {}
        self._spinner: threading.Thread | None = None

    def call(self, srv_type: str, name: str, **request) -> str:
        """Call service ``name``; its message, or LabError with the reason. Safe from any thread
        once ``watch`` spins the node in the background."""
        cls = self.factory.cls(srv_type)
        client = self._clients.get((srv_type, name))
        if client is None:
            client = self._clients[(srv_type, name)] = self.node.create_client(cls, name)
        if not client.wait_for_service(timeout_sec=SERVICE_WAIT_S):
            raise LabError(
                f"no {name} service after {SERVICE_WAIT_S:.0f} s: is its node running on "
                f"ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')}?"
            )
        future = client.call_async(cls.Request(**request))
        if self._spinner is None:
            self.executor.spin_until_future_complete(future, timeout_sec=CALL_TIMEOUT_S)
        else:  # the background spinner completes it
            answered = threading.Event()
            future.add_done_callback(lambda _f: answered.set())
            answered.wait(CALL_TIMEOUT_S)
        if not future.done():
            client.remove_pending_request(future)
            raise LabError(f"{name} did not answer within {CALL_TIMEOUT_S:.0f} s")
        response = future.result()
        if not response.success:
            raise LabError(f"{name}: {response.message}")
        return response.message

    def latched(self, topic: str, msg_type: str, wait_s: float = 5.0):
        """The latched value on ``topic`` (None if nobody publishes it; ``wait_s`` covers discovery on a
        loaded machine, where 2 s once missed a running recorder)."""
        got = []
        sub = self.node.create_subscription(self.factory.cls(msg_type), topic, got.append, LATCHED_QOS)
        try:
            deadline = time.monotonic() + wait_s
            while not got and time.monotonic() < deadline:
                self.executor.spin_once(timeout_sec=0.1)
            return got[-1].data if got else None
        finally:
            self.node.destroy_subscription(sub)

    def subscribe_operator_state(self, on_value: Callable[[str, object], None]) -> None:
        """Everything the operator loop shows (``lab.node_view.NodeView``'s fields): ``on_value(field,
        value)`` for each latched value and each franka_node ``/diagnostics`` (message, values); and,
        once a second, ``on_value(field, None)`` for each latched topic that no node publishes any more."""
        for name, (topic, msg_type) in WATCHED_TOPICS.items():
            self.node.create_subscription(
                self.factory.cls(msg_type), topic, lambda msg, name=name: on_value(name, msg.data), LATCHED_QOS
            )

        def on_diagnostics(msg):
            try:
                entries = diagnostic_entries(msg)
            except MessageError:
                return  # a malformed array from some node: the franka_node entry comes in the next
            for entry in entries:
                if entry.name == FRANKA_DIAGNOSTICS_NAME:
                    on_value("franka_diagnostics", (entry.message, entry.values))

        self.node.create_subscription(
            self.factory.cls("diagnostic_msgs/msg/DiagnosticArray"),
            topics.TOPIC_DIAGNOSTICS,
            on_diagnostics,
            RELIABLE_QOS,
        )

        unpublished = dict.fromkeys(WATCHED_TOPICS, 0)  # seconds in a row without a publisher

        def forget_the_gone():  # a latched value outlives its node in our cache: a dead node shows as none
            for name, (topic, _type) in WATCHED_TOPICS.items():
                unpublished[name] = unpublished[name] + 1 if self.node.count_publishers(topic) == 0 else 0
                if unpublished[name] >= 2:  # twice: not a value that arrived just before its publisher's discovery
                    on_value(name, None)

        self.node.create_timer(1.0, forget_the_gone)

    def snapshot(self, wait_s: float = 5.0) -> dict:
        """What ``lab status`` prints: the latched values (None where no node publishes one) and franka_node's
        newest ``/diagnostics`` where it publishes no ``/franka/status``; waits up to ``wait_s`` for discovery."""
        got: dict = {}
        self.subscribe_operator_state(lambda name, value: got.__setitem__(name, value) if value is not None else None)

        def complete() -> bool:
            if not all(got.get(name) is not None for name in WATCHED_TOPICS if name != "franka_status"):
                return False
            if "franka_status" in got:
                return True
            return "franka_diagnostics" in got and self.node.count_publishers(topics.TOPIC_FRANKA_STATUS) == 0

        deadline = time.monotonic() + wait_s
        while not complete() and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.1)
        return got

    def watch(self, on_value: Callable[[str, object], None]) -> None:
        """``subscribe_operator_state``, spun in a background thread until ``close``."""
        self.subscribe_operator_state(on_value)
        self._spinner = threading.Thread(target=self._spin, name="lab-ros", daemon=True)
        self._spinner.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def close(self):
        self.executor.shutdown()
        if self._spinner is not None:
            self._spinner.join(timeout=5.0)
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def print_status(as_json: bool) -> int:
    """What ``equidiff lab status`` prints: one line per node's state, or one JSON line; the exit code."""
    with LabClient() as lab:
        got = lab.snapshot()
    now = time.monotonic()
    view = NodeView(
        franka_status=got.get("franka_status"),
        franka_diagnostics=got.get("franka_diagnostics"),
        franka_diagnostics_at=now,
    )
    robot, note = view.robot(now)
    state = {
        "robot": None if robot is None else {**asdict(robot), "note": note},
        "recorder": got.get("recorder"),
        "policy": got.get("policy"),
        "teleop_active": got.get("teleop_active"),
    }
    if as_json:
        print(json.dumps(state))
        return 0
    if robot is None:
        print(f"robot: (no status) {note}")
    else:
        fault = f"; last fault: {robot.last_fault}" if robot.last_fault else ""
        print(f"robot: {robot.describe()}{fault} [{note or robot.source}]")
    for key in ("recorder", "policy", "teleop_active"):
        print(f"{key}: {'(no node)' if state[key] is None else state[key]}")
    return 0
