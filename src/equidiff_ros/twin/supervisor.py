"""The twin jobs' in-process ROS node: episode gate, homing, scripted expert, recorder control, metrics.

Used by ``equidiff twin run`` and ``equidiff twin collect`` (not a standalone executable). Wiring:
  /twin/policy_chunk (policy_node's /franka/command_chunk, remapped) -> forwarded to
      /franka/command_chunk only while an episode is running (the gate, ``twin.gate.PolicyGate``),
      so the policy stays loaded and warm between episodes while the arm is homed and the scene
      reset; on simulated time each chunk is held until its observation's stamp + L (the latency
      budget), so it takes effect when it would on a lab machine with that latency
  /clock -> (simulated time) releases held chunks; the node's own clock follows it
  /twin/await_policy <- the episode's start (sim ns; -1 after it): twin_node waits for the chunk
      of each frame from then on
  /policy/episode <- {"seed", "start_ns"} as the gate opens: policy_node samples the episode's
      observations with ``wire.chunk.SamplingSeeds`` for its seed, as the in-process evaluation does
  /franka/command_chunk <- one-point targets at 20 Hz, stamped now, reached 50 ms later: the
      same messages teleop_node publishes (homing and the scripted expert)
  /twin/reset <- seed; /twin/scene, /twin/state -> episode set-up and success
  /recorder/command <- start / stop success|failure / discard
  /diagnostics (policy_node: inference_ms), /franka/ee_pose, /franka/joint_states -> state, metrics
"""

from __future__ import annotations

import collections
import json
import threading
import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Int64, String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import MultiDOFJointTrajectory

from equidiff_core.twin.expert import LinePath
from equidiff_core.twin.gate import GateRecord, PolicyGate
from equidiff_core.wire.chunk import PoseChunk, chunk_to_msg
from equidiff_core.wire.rosmsg import (
    NS_PER_S,
    MessageError,
    RclpyFactory,
    diagnostic_entries,
    gripper_width_from_joint_state,
    pose_from_msg,
    stamp_to_ns,
)
from equidiff_core.wire.topics import (
    SERVICE_FRANKA_ACKNOWLEDGE,
    TOPIC_CLOCK,
    TOPIC_COMMAND_CHUNK,
    TOPIC_DIAGNOSTICS,
    TOPIC_EE_POSE,
    TOPIC_JOINT_STATES,
    TOPIC_POLICY_EPISODE,
    TOPIC_POLICY_SKIPPED,
    TOPIC_RECORDER_COMMAND,
    TOPIC_RECORDER_STATUS,
    TOPIC_TWIN_AWAIT_POLICY,
    TOPIC_TWIN_POLICY_CHUNK,
    TOPIC_TWIN_RESET,
    TOPIC_TWIN_SCENE,
    TOPIC_TWIN_STATE,
)
from equidiff_ros.common import LATCHED_QOS, RELIABLE_QOS

NS = NS_PER_S
# How far ahead of this node's clock an episode starts on simulated time: one frame period of the
# 5 Hz cameras, at the default max_speed (1x real time) at least 0.2 s of wall time for messages
# that take milliseconds. A start announced after its first frame would leave that frame outside
# the lockstep (twin_node warns when it happens).
EPISODE_LEAD_NS = 200_000_000
# what a homing error quotes of franka_node's diagnostics (control.controller.ControllerStats):
# whether the chunks arrived, were refused, and moved the gripper
FRANKA_COUNTS_REPORTED = ("state", "accepted_chunks", "rejected_chunks", "gripper_commands")


class SupervisorError(RuntimeError):
    """The twin did not respond as expected (no state, no scene, robot not moving)."""


class Supervisor:
    """The job's node. ``sim_time``: its clock is the twin's /clock and chunks are held for ``latency_s``."""

    def __init__(
        self,
        base_frame: str = "fr3_link0",
        command_lead_s: float = 0.05,
        name: str = "twin_supervisor",
        sim_time: bool = False,
        latency_s: float = 0.0,
        stall_timeout_s: float = 30.0,
    ):
        if not rclpy.ok():
            # No rclpy signal handlers: Ctrl-C must raise KeyboardInterrupt in the job's main thread
            # (rclpy's would only shut the context down under it) so every node gets stopped.
            rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        self.node = Node(name, parameter_overrides=[Parameter("use_sim_time", value=bool(sim_time))])
        self.factory = RclpyFactory()
        self.frame = base_frame
        self.lead_ns = int(command_lead_s * NS)
        self.sim_time = bool(sim_time)
        self.stall_timeout_s = stall_timeout_s
        self.lock = threading.RLock()  # wait_for's predicates may call the locked accessors
        self.gate = PolicyGate(round(latency_s * NS) if sim_time else 0)  # used under self.lock
        self._clock_seen = (0, time.monotonic())  # (sim ns, wall s when it last advanced)
        self.ee_pose: np.ndarray | None = None
        self.width: float | None = None
        self._last_state_monotonic_s: float | None = None  # when the newest /franka/joint_states came, for errors
        self.franka_diagnostics = ""  # franka_node's newest diagnostics, for error messages
        self.twin_state: dict | None = None
        self.scene: dict | None = None
        self.recorder_status = ""
        self.unusable: collections.Counter[str] = collections.Counter()  # messages rosmsg refused, by topic
        n = self.node
        self.pub_chunk = n.create_publisher(MultiDOFJointTrajectory, TOPIC_COMMAND_CHUNK, RELIABLE_QOS)
        self.pub_reset = n.create_publisher(Int64, TOPIC_TWIN_RESET, RELIABLE_QOS)
        self.pub_recorder = n.create_publisher(String, TOPIC_RECORDER_COMMAND, RELIABLE_QOS)
        self.pub_await = n.create_publisher(Int64, TOPIC_TWIN_AWAIT_POLICY, LATCHED_QOS)
        self.pub_episode = n.create_publisher(String, TOPIC_POLICY_EPISODE, LATCHED_QOS)
        if self.sim_time:  # best effort: the publisher's QoS (a reliable subscription would not match it)
            n.create_subscription(
                Clock, TOPIC_CLOCK, self._on_clock, QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
            )
        n.create_subscription(MultiDOFJointTrajectory, TOPIC_TWIN_POLICY_CHUNK, self._on_policy_chunk, RELIABLE_QOS)
        n.create_subscription(PoseStamped, TOPIC_EE_POSE, self._on_pose, RELIABLE_QOS)
        n.create_subscription(JointState, TOPIC_JOINT_STATES, self._on_joints, RELIABLE_QOS)
        n.create_subscription(String, TOPIC_TWIN_STATE, self._on_state, RELIABLE_QOS)
        n.create_subscription(String, TOPIC_TWIN_SCENE, self._on_scene, LATCHED_QOS)
        n.create_subscription(String, TOPIC_RECORDER_STATUS, self._on_recorder, LATCHED_QOS)
        n.create_subscription(DiagnosticArray, TOPIC_DIAGNOSTICS, self._on_diag, RELIABLE_QOS)
        n.create_subscription(String, TOPIC_POLICY_SKIPPED, self._on_skipped, RELIABLE_QOS)
        self.ack_client = n.create_client(Trigger, SERVICE_FRANKA_ACKNOWLEDGE)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(n)
        self._spin = threading.Thread(target=self._spin_loop, daemon=True, name="supervisor-spin")
        self._running = True
        self._spin.start()

    def _spin_loop(self):
        while self._running:
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except ExternalShutdownException:
                return
            except Exception:  # context shut down under us at exit
                if self._running:
                    raise
                return

    def close(self):
        self._running = False
        self._spin.join(timeout=2.0)
        self.executor.shutdown()
        self.node.destroy_node()
        if rclpy.ok():
            rclpy.try_shutdown()

    # -- the gate's figures (read under self.lock, e.g. in wait_for's predicates) ----------------------
    @property
    def chunk_arrivals(self) -> list[float]:
        """Node-clock seconds at which this episode's chunks were forwarded."""
        return self.gate.record.arrivals

    @property
    def policy_chunks_seen(self) -> int:
        """Chunks from policy_node, gate or not: the policy is loaded and answering."""
        return self.gate.chunks_seen

    # -- time ----------------------------------------------------------------------------------------
    def now_ns(self) -> int:
        """The node's clock: simulated time on the sim clock, else the wall clock."""
        return self.node.get_clock().now().nanoseconds

    def time_scale(self) -> float:
        """Arm-speed seconds per clock second: 1 on simulated time; on real time, how fast the sim runs
        against the wall clock (0.05-1): timeouts and plan clocks scale by it."""
        return 1.0 if self.sim_time else min(1.0, max(0.05, self.twin().get("steps_per_s", 1000.0) / 1000.0))

    def check_clock(self) -> None:
        """Raise if simulated time has stood still for longer than any lockstep wait may last."""
        if not self.sim_time:
            return
        now, (seen, since) = self.now_ns(), self._clock_seen
        if now != seen:
            self._clock_seen = (now, time.monotonic())
        elif time.monotonic() - since > self.stall_timeout_s + 10.0:
            raise SupervisorError(
                f"the sim clock has stood at t={now / NS:.3f} s for {time.monotonic() - since:.0f} s "
                f"of wall time: twin_node is hung ({self.twin().get('last_stall') or 'no stall reported'})"
            )

    # -- callbacks ------------------------------------------------------------------------------
    def _on_policy_chunk(self, msg):
        stamp = stamp_to_ns(msg.header.stamp)
        with self.lock:
            now = self.now_ns()
            forward_now = self.gate.offer(msg, stamp, now)  # or held until stamp + latency (released by /clock)
        if forward_now:
            self._forward(msg, stamp, now)

    def _on_clock(self, msg):
        t = stamp_to_ns(msg.clock)
        with self.lock:
            due = self.gate.due(t)
        for stamp, m in due:
            self._forward(m, stamp, t)

    def _forward(self, msg, stamp_ns: int, now_ns: int) -> None:
        with self.lock:
            if not self.gate.forwarded(stamp_ns, now_ns):
                return
        self.pub_chunk.publish(msg)

    def _on_skipped(self, msg):
        skipped = json.loads(msg.data)
        with self.lock:
            self.gate.skipped(skipped["stamp_ns"], skipped["reason"])

    # A message rosmsg refuses is left out (counted in ``unusable``): the newest usable state stays.
    def _on_pose(self, msg):
        try:
            pose = pose_from_msg(msg, self.frame)
        except MessageError:
            self.unusable["ee_pose"] += 1
            return
        with self.lock:
            self.ee_pose = pose

    def _on_joints(self, msg):
        try:
            width = gripper_width_from_joint_state(msg)
        except MessageError:
            self.unusable["joint_states"] += 1
            return
        if width is None:
            return
        with self.lock:
            self.width = width
            self._last_state_monotonic_s = time.monotonic()

    def _on_state(self, msg):
        with self.lock:
            self.twin_state = json.loads(msg.data)

    def _on_scene(self, msg):
        with self.lock:
            self.scene = json.loads(msg.data)

    def _on_recorder(self, msg):
        with self.lock:
            self.recorder_status = msg.data

    def _on_diag(self, msg):
        try:
            entries = diagnostic_entries(msg)
        except MessageError:
            self.unusable["diagnostics"] += 1
            return
        for entry in entries:
            inference_ms = entry.number("inference_ms") if entry.name == "policy_node" else None
            with self.lock:
                if entry.name == "franka_node":
                    self.franka_diagnostics = entry.quote(FRANKA_COUNTS_REPORTED)
                elif inference_ms is not None and inference_ms >= 0:
                    self.gate.inference(inference_ms)

    # -- waiting ---------------------------------------------------------------------------------
    def wait_for(self, predicate, timeout_s: float, what: str, check=None):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self.lock:
                value = predicate()
            if value:
                return value
            if check is not None:
                check()
            time.sleep(0.02)
        raise SupervisorError(f"timed out after {timeout_s:.0f} s waiting for {what}")

    def wait_ready(self, timeout_s: float, check=None) -> None:
        self.wait_for(lambda: self.twin_state is not None, timeout_s, "twin_node's /twin/state", check)
        if self.sim_time:
            self.wait_for(lambda: self.now_ns() > 0, timeout_s, "twin_node's /clock (simulated time)", check)
        self.wait_for(
            lambda: self.ee_pose is not None and self.width is not None,
            timeout_s,
            "franka_node's /franka/ee_pose and joint states",
            check,
        )

    # -- commanding --------------------------------------------------------------------------------
    def sim_sleep(self, seconds: float, check=None) -> None:
        """Let ``seconds`` of the node's clock pass (simulated time when the twin runs on it)."""
        end = self.now_ns() + int(seconds * NS)
        while self.now_ns() < end:
            if check is not None:
                check()
            self.check_clock()
            time.sleep(0.01)

    def send_target(self, pose: np.ndarray, width: float) -> None:
        now = self.now_ns()
        chunk = PoseChunk(
            now, np.array([now + self.lead_ns], dtype=np.int64), np.asarray(pose)[None].copy(), np.array([float(width)])
        )
        self.pub_chunk.publish(chunk_to_msg(chunk, self.factory, self.frame))

    def current(self) -> tuple[np.ndarray, float]:
        with self.lock:
            return self.ee_pose.copy(), float(self.width)

    def move_to(
        self,
        target: np.ndarray,
        width: float,
        speed: float = 0.12,
        angular_speed: float = 1.0,
        timeout_s: float = 20.0,
        tol_m: float = 0.01,
        hz: float = 20.0,
        max_lag_m: float = 0.03,
        check=None,
    ) -> None:
        """Stream teleop-like targets along a straight line to ``target`` (never a jump the safety
        filter would reject; ``expert.LinePath`` waits for the arm and restarts from it), then hold
        until the TCP is within ``tol_m`` and the gripper settled."""

        path = LinePath(self.current()[0], target, speed=speed, angular_speed=angular_speed, hz=hz, max_lag_m=max_lag_m)
        p1 = path.target[:3, 3]
        # timeout_s is the arm's time: on real time a twin at 0.45x moves the arm (speed-limited in
        # its own clock) at 0.45x wall-clock speed, as LiveExpert's plan clock assumes too
        rate = self.time_scale()
        deadline = self.now_ns() + int(timeout_s / rate * NS)
        while self.now_ns() < deadline:
            self.send_target(path.next(self.current()[0]), width)
            if check is not None:
                check()
            self.check_clock()
            if path.done:
                now, w = self.current()
                if np.linalg.norm(now[:3, 3] - p1) < tol_m and (abs(w - width) < 0.01 or width < 0.01):
                    return
            time.sleep(1.0 / hz)
        now, w = self.current()
        seen = self._last_state_monotonic_s
        age = "none yet" if seen is None else f"{time.monotonic() - seen:.1f} s ago"
        raise SupervisorError(
            f"the arm did not reach {np.round(p1, 3).tolist()} within {timeout_s:.0f} s of sim time "
            f"({timeout_s / rate:.0f} s of the node's clock at {rate:.2f}x; TCP at "
            f"{np.round(now[:3, 3], 3).tolist()}, {100 * path.s:.0f} % along the path "
            f"after {path.restarts} restart(s) from the arm, "
            f"gripper {w * 1000:.0f} mm for {width * 1000:.0f} mm; joint states: {age}; franka_node's diagnostics: "
            f"{self.franka_diagnostics or 'none yet'})"
        )

    def reset_scene(self, seed: int, timeout_s: float = 10.0, check=None) -> dict:
        self.pub_reset.publish(Int64(data=int(seed)))
        return self.wait_for(
            lambda: self.scene if self.scene and self.scene.get("seed") == seed else None,
            timeout_s,
            f"{TOPIC_TWIN_SCENE} for seed {seed}",
            check,
        )

    def twin(self) -> dict:
        with self.lock:
            return dict(self.twin_state or {})

    def acknowledge_stop(self, timeout_s: float = 10.0, check=None) -> str:
        """Act as the operator between episodes: acknowledge a stop franka_node holds for (a robot
        error or a divergence stop in the last episode) so the next episode can home; returns what
        was acknowledged ("" when nothing). The caller says so: it is never silent."""
        if not self.ack_client.wait_for_service(timeout_sec=timeout_s):
            raise SupervisorError(f"no {SERVICE_FRANKA_ACKNOWLEDGE} service: is franka_node running?")
        future = self.ack_client.call_async(Trigger.Request())
        response = self.wait_for(
            lambda: future.result() if future.done() else None,
            timeout_s,
            f"{SERVICE_FRANKA_ACKNOWLEDGE}'s answer",
            check,
        )
        if not response.success:
            raise SupervisorError(f"franka_node refused the acknowledgement: {response.message}")
        return response.message.removeprefix("acknowledged: ") if response.message.startswith("acknowledged") else ""

    def recorder(self, command: str, expect_prefix: str, timeout_s: float = 10.0, check=None) -> str:
        self.pub_recorder.publish(String(data=command))
        return self.wait_for(
            lambda: self.recorder_status if self.recorder_status.startswith(expect_prefix) else None,
            timeout_s,
            f"recorder status '{expect_prefix}…' after '{command}'",
            check,
        )

    def open_gate(self, episode_seed: int | None = None) -> None:
        """Start forwarding policy chunks answering observations from now on (and, on simulated
        time, have twin_node wait for each frame's chunk). With ``episode_seed``, policy_node
        answers the first observation from now on at once and samples the episode's observations
        with that seed's noise (``wire.chunk.SamplingSeeds``).

        On simulated time the episode starts ``EPISODE_LEAD_NS`` ahead of this node's clock, so that
        twin_node and policy_node have its start before the sim takes its first frame: the frames
        twin_node waits for are then exactly those whose chunks the gate passes."""
        with self.lock:
            start_ns = self.now_ns() + (EPISODE_LEAD_NS if self.sim_time else 0)
            if self.sim_time:
                self.pub_await.publish(Int64(data=start_ns))
            if episode_seed is not None:
                self.pub_episode.publish(String(data=json.dumps({"seed": int(episode_seed), "start_ns": start_ns})))
            self.gate.open(start_ns)

    def close_gate(self) -> GateRecord:
        """Stop forwarding; what passed: forward times, reasons of dropped observations, end-to-end and inference ms."""
        if self.sim_time:
            self.pub_await.publish(Int64(data=-1))
        with self.lock:
            return self.gate.close()
