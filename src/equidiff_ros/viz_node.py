"""Live rerun view of the ROS graph: subscribe to the contract's topics, hand each message to a logger.

Used by ``equidiff viz`` (not one of the console-script nodes). The node never imports rerun:
it is given a ``RerunLogger`` (or anything with ``log_message(topic, msg, receive_ns)``)
built by the command. Time in rerun is each message's header stamp; the arrival time on
this node's clock is passed along for the observation-age series and for unstamped messages.

QoS: high-rate state and clouds are read best-effort (matches reliable and best-effort
publishers alike, e.g. franka_ros2's best-effort pose); voxels, chunks, executed targets and
diagnostics reliably, so none of the few per second is missed.
"""

from __future__ import annotations

import signal
import threading
import time
from typing import Any

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from equidiff_core.config import LabConfig
from equidiff_core.wire.topics import (
    TOPIC_COMMAND_CHUNK,
    TOPIC_DIAGNOSTICS,
    TOPIC_EE_POSE,
    TOPIC_EXECUTED_TARGET,
    TOPIC_JOINT_STATES,
    TOPIC_POLICY_DOUBT,
    TOPIC_VOXELS,
    camera_color_topic,
)
from equidiff_ros.common import RELIABLE_QOS, SENSOR_QOS, VOXEL_READER_QOS, now_ns, wait_for_clock


class VizNode(Node):
    def __init__(self, logger: Any, lab: LabConfig, clouds: bool = False, status_period_s: float = 10.0):
        super().__init__("equidiff_viz")
        wait_for_clock(self)  # simulated time (the twin): nothing is timed before /clock
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped, Vector3Stamped
        from sensor_msgs.msg import CompressedImage, JointState, PointCloud2
        from trajectory_msgs.msg import MultiDOFJointTrajectory

        self.viz = logger
        self.received: dict[str, int] = {}
        self.failures = 0
        # set-time + log must stay one step should this node ever be spun by a multi-threaded executor
        self._lock = threading.Lock()
        topics = [
            (TOPIC_VOXELS, PointCloud2, VOXEL_READER_QOS),  # a frozen viewer must not hold the grids back
            (TOPIC_EE_POSE, PoseStamped, SENSOR_QOS),
            (TOPIC_JOINT_STATES, JointState, SENSOR_QOS),
            (TOPIC_COMMAND_CHUNK, MultiDOFJointTrajectory, RELIABLE_QOS),
            (TOPIC_EXECUTED_TARGET, PoseStamped, RELIABLE_QOS),
            (TOPIC_DIAGNOSTICS, DiagnosticArray, RELIABLE_QOS),
            (TOPIC_POLICY_DOUBT, Vector3Stamped, RELIABLE_QOS),
        ]
        if clouds:
            topics += [(cam.topic, PointCloud2, SENSOR_QOS) for cam in lab.cameras]
        if logger.config.images:  # viz.yaml's `images` (on by default): the cameras' JPEGs
            topics += [(camera_color_topic(cam.name), CompressedImage, SENSOR_QOS) for cam in lab.cameras]
        # Camera frames come from the lab config, the same file camera_node publishes /tf_static from
        # (tf2_msgs is not even installable from PyPI, architecture.md note 1).
        for topic, msg_type, qos in topics:
            self.create_subscription(msg_type, topic, self._callback(topic), qos)
        self.create_timer(status_period_s, self._report)
        self.get_logger().info(f"visualising {len(topics)} topics: {', '.join(t for t, _, _ in topics)}")

    def _callback(self, topic: str):
        def on_message(msg: Any) -> None:
            receive_ns = now_ns(self)
            self.received[topic] = self.received.get(topic, 0) + 1
            try:
                with self._lock:
                    self.viz.log_message(topic, msg, receive_ns)
            except Exception as err:  # noqa: BLE001 - a viewer must never take the graph down; say why, keep going
                self.failures += 1
                self.get_logger().error(
                    f"could not log {topic}: {type(err).__name__}: {err}", throttle_duration_sec=5.0
                )

        return on_message

    def _report(self) -> None:
        dropped = dict(getattr(self.viz, "errors", {}))
        last = getattr(self.viz, "last_error", None)
        self.get_logger().info(
            f"received {self.received}; dropped {dropped or 'none'}" + (f" (last: {last})" if dropped else "")
        )


def run_live(
    logger: Any, lab: LabConfig, clouds: bool = False, duration_s: float | None = None, args: list[str] | None = None
) -> dict[str, int]:
    """Spin a VizNode until Ctrl-C / SIGTERM (or ``duration_s``); returns messages received per topic."""
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    node = None
    try:
        node = VizNode(logger, lab, clouds=clouds)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        deadline = None if duration_s is None else time.monotonic() + duration_s
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            executor.spin_once(timeout_sec=0.1)
        return dict(node.received)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if node is not None:
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
