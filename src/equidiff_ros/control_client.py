"""A client of the live graph for benches and tests: an rclpy node in a background thread that
publishes chunks and voxel grids the way policy_node does and records what the nodes send back
(poses, executed targets, chunks, diagnostics). ``equidiff bench control`` and the node tests
drive franka_node and policy_node through it.

Its clock is the graph's: the wall clock, or with ``use_sim_time`` the twin's simulated time
(``now``, ``sleep``), so chunks are stamped, paced and measured in the time franka_node runs on.
"""

from __future__ import annotations

import subprocess
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState, PointCloud2
from trajectory_msgs.msg import MultiDOFJointTrajectory

from equidiff_core.geometry import down_pose
from equidiff_core.wire.chunk import PoseChunk, chunk_to_msg
from equidiff_core.wire.rosmsg import MessageError, RclpyFactory, diagnostic_entries, position_from_msg, stamp_to_ns
from equidiff_core.wire.topics import (
    TOPIC_COMMAND_CHUNK,
    TOPIC_DIAGNOSTICS,
    TOPIC_EE_POSE,
    TOPIC_EXECUTED_TARGET,
    TOPIC_JOINT_STATES,
    TOPIC_VOXELS,
)
from equidiff_ros.common import RELIABLE_QOS, VOXEL_QOS, node_clock

MS = 1_000_000
# Wall seconds the simulated clock may stand still inside one of the client's sleeps by default: far
# longer than any pause of a loaded sim (it publishes /clock every step), short enough that a dead
# twin_node ends a test or bench with a clear error instead of a hang.
CLOCK_STALL_S = 30.0


@dataclass
class Recorded:
    poses: deque = field(default_factory=lambda: deque(maxlen=20000))  # (t_s, position)
    targets: deque = field(default_factory=lambda: deque(maxlen=20000))
    chunks: deque = field(default_factory=lambda: deque(maxlen=2000))  # (receive_s, stamp_s)
    diagnostics: dict = field(default_factory=dict)  # status name -> latest values
    joint_states: int = 0
    last_joint_state: object = None
    last_chunk: object = None
    unusable: Counter = field(default_factory=Counter)  # messages rosmsg refused, by kind


class ControlClient:
    """An rclpy node in a background thread: publishes chunks/voxels, records what comes back."""

    def __init__(self, lab, lab_path: str, use_sim_time: bool = False, clock_stall_s: float = CLOCK_STALL_S):
        self.lab = lab
        self.lab_path = lab_path
        self.factory = RclpyFactory()
        self.data = Recorded()
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(
            "control_bench",
            context=self.context,
            parameter_overrides=[Parameter("use_sim_time", Parameter.Type.BOOL, use_sim_time)],
        )
        self.clock = node_clock(self.node, stall_s=clock_stall_s)
        self._stop = threading.Event()  # ends a sleep on simulated time when the client closes
        self.pub_chunk = self.node.create_publisher(MultiDOFJointTrajectory, TOPIC_COMMAND_CHUNK, RELIABLE_QOS)
        self.pub_voxels = self.node.create_publisher(PointCloud2, TOPIC_VOXELS, VOXEL_QOS)
        self.node.create_subscription(PoseStamped, TOPIC_EE_POSE, self._on_pose, RELIABLE_QOS)
        self.node.create_subscription(PoseStamped, TOPIC_EXECUTED_TARGET, self._on_target, RELIABLE_QOS)
        self.node.create_subscription(MultiDOFJointTrajectory, TOPIC_COMMAND_CHUNK, self._on_chunk, RELIABLE_QOS)
        self.node.create_subscription(DiagnosticArray, TOPIC_DIAGNOSTICS, self._on_diag, RELIABLE_QOS)
        self.node.create_subscription(JointState, TOPIC_JOINT_STATES, self._on_joints, RELIABLE_QOS)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self):
        while self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - context shut down under us
                break

    # An unusable message is left out here, never raised: an exception would end the spin thread.
    def _on_pose(self, msg):
        try:
            self.data.poses.append((stamp_to_ns(msg.header.stamp) / 1e9, position_from_msg(msg)))
        except MessageError:
            self.data.unusable["ee_pose"] += 1

    def _on_target(self, msg):
        try:
            self.data.targets.append((stamp_to_ns(msg.header.stamp) / 1e9, position_from_msg(msg)))
        except MessageError:
            self.data.unusable["executed_target"] += 1

    def _on_chunk(self, msg):
        self.data.chunks.append((self.now(), stamp_to_ns(msg.header.stamp) / 1e9))
        self.data.last_chunk = msg

    def _on_joints(self, msg):
        self.data.joint_states += 1
        self.data.last_joint_state = msg

    def _on_diag(self, msg):
        try:
            entries = diagnostic_entries(msg)
        except MessageError:
            self.data.unusable["diagnostics"] += 1
            return
        for entry in entries:
            self.data.diagnostics[entry.name] = entry.values

    def close(self):
        self._stop.set()
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.context.try_shutdown()
        self._thread.join(timeout=2)

    # --- helpers -------------------------------------------------------------------------
    def now_ns(self) -> int:
        """The graph's time: the wall clock, or simulated time (0 until the first /clock)."""
        return self.clock.now_ns()

    def now(self) -> float:
        return self.now_ns() / 1e9

    def sleep_until(self, t: float) -> None:
        """Until ``t`` (s) of the graph's time, or the client closes. On simulated time a clock that
        stands still for ``clock_stall_s`` wall seconds (the sim gone) raises TimeoutError."""
        self.clock.sleep_until(int(t * 1e9), self._stop)

    def sleep(self, seconds: float) -> None:
        """``seconds`` of the graph's time (longer on the wall clock while a loaded sim runs slow)."""
        self.sleep_until(self.now() + seconds)

    def wait_for(self, predicate, timeout: float, what: str, proc: subprocess.Popen | None = None):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return
            if proc is not None and proc.poll() is not None:
                raise RuntimeError(f"{what}: the node exited with code {proc.returncode}")
            time.sleep(0.05)
        raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what}")

    def latest_position(self) -> np.ndarray:
        return self.data.poses[-1][1]

    def publish_chunk(self, chunk) -> None:
        self.pub_chunk.publish(chunk_to_msg(chunk, self.factory, self.lab.base_frame))

    def stream(
        self,
        path,
        duration: float,
        obs_latency: float = 0.1,
        steps: int = 16,
        dt: float = 0.2,
        period: float = 0.2,
        width: float = 0.08,
    ) -> tuple[float, float]:
        """Publish chunks sampled from ``path(t) -> position`` every ``period`` s; returns the last
        send time and the time the last chunk's final step is due (the client's clock, s)."""

        end = self.now() + duration
        next_send = self.now()
        last = last_step = self.now()
        while self.now() < end:
            obs = self.now_ns() - int(obs_latency * 1e9)
            times = obs + np.arange(steps, dtype=np.int64) * int(dt * 1e9)
            poses = np.stack([down_pose(path(t / 1e9)) for t in times])
            self.publish_chunk(PoseChunk(obs, times, poses, np.full(steps, width)))
            last, last_step = self.now(), float(times[-1]) / 1e9
            next_send += period
            self.sleep_until(next_send)
        return last, last_step

    def samples(self, which: str, t_from: float, t_to: float) -> tuple[np.ndarray, np.ndarray]:
        rows = [(t, p) for t, p in list(getattr(self.data, which)) if t_from <= t <= t_to]
        if not rows:
            return np.zeros(0), np.zeros((0, 3))
        return np.array([t for t, _ in rows]), np.stack([p for _, p in rows])

    def diag_value(self, name: str, key: str, default=None):
        values = self.data.diagnostics.get(name) or {}
        return values.get(key, default)

    def record_pose_stamps(self, topic: str | None = None, depth: int = 5000) -> deque:
        """From now on also record the stamp (s) of every PoseStamped on ``topic`` (default
        /franka/ee_pose) in ``self.pose_stamps``, through a subscription of its own with a deep
        queue: the 10-deep queues above drop messages while this process is starved of CPU, this
        one keeps them, so a gap in these stamps is the publisher's own. Returns that deque."""

        self.pose_stamps: deque = deque(maxlen=200000)
        self.node.create_subscription(
            PoseStamped,
            topic or TOPIC_EE_POSE,
            lambda msg: self.pose_stamps.append(stamp_to_ns(msg.header.stamp) / 1e9),
            QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE),
        )
        return self.pose_stamps


# --- scenarios -------------------------------------------------------------------------------
