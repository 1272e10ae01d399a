"""The twin jobs' in-process ROS node: episode gate, homing, scripted expert, recorder control, metrics.

Used by ``equidiff twin run`` and ``equidiff twin collect`` (not a standalone executable).

Wiring:
  /twin/policy_chunk (policy_node's /franka/command_chunk, remapped) -> forwarded to
      /franka/command_chunk only while an episode is running (the "gate"), so the policy stays
      loaded and warm between episodes while the arm is homed and the scene reset; on simulated
      time each chunk is held until its observation's stamp + L (the latency budget), so it
      takes effect when it would on a lab machine with that latency
  /clock -> (simulated time) releases held chunks; the node's own clock follows it
  /twin/await_policy <- true while the gate is open: twin_node then waits for each frame's chunk
  /policy/episode <- {"seed", "start_ns"} as the gate opens: policy_node samples the episode's
      observations with ``chunk.SamplingSeeds`` for its seed, as the in-process evaluation does
  /franka/command_chunk <- one-point targets at 20 Hz, stamped now, reached 50 ms later: the
      same messages teleop_node publishes (homing and the scripted expert)
  /twin/reset <- seed; /twin/scene, /twin/state -> episode set-up and success
  /recorder/command <- start / stop success|failure / discard
  /diagnostics (policy_node: inference_ms), /franka/ee_pose, /franka/joint_states -> state, metrics
"""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path
from typing import Self

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
from std_msgs.msg import Bool, Int64, String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import MultiDOFJointTrajectory

from equidiff_core import geometry
from equidiff_core.chunk import PoseChunk, chunk_to_msg
from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.control import load_control_config
from equidiff_core.episode import run_episode
from equidiff_core.robots.franky.sim import free_loopback_host
from equidiff_core.rosmsg import RclpyFactory, stamp_to_ns
from equidiff_core.topics import (
    SERVICE_FRANKA_ACKNOWLEDGE,
    TOPIC_CLOCK,
    TOPIC_COMMAND_CHUNK,
    TOPIC_POLICY_EPISODE,
    TOPIC_RECORDER_STATUS,
    TOPIC_TWIN_AWAIT_POLICY,
    TOPIC_TWIN_POLICY_CHUNK,
    TOPIC_TWIN_RESET,
    TOPIC_TWIN_SCENE,
    TOPIC_TWIN_STATE,
)
from equidiff_core.twin.config import TWIN_PRECISION, load_twin_config
from equidiff_core.twin.expert import LinePath, plan_pick_place, tcp_pose
from equidiff_core.twin.metrics import EpisodeRecord
from equidiff_core.twin.processes import (
    ProcessGroup,
    composed_command,
    node_command,
    private_ros_env,
)
from equidiff_core.twin.scene import ScenePoses, scene_record
from equidiff_ros.common import (
    LATCHED_QOS,
    RELIABLE_QOS,
    TOPIC_DIAGNOSTICS,
    TOPIC_EE_POSE,
    TOPIC_JOINT_STATES,
    TOPIC_POLICY_SKIPPED,
    TOPIC_RECORDER_COMMAND,
)

NS = 1_000_000_000


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
        self.latency_ns = round(latency_s * NS) if sim_time else 0
        self.stall_timeout_s = stall_timeout_s
        self.lock = threading.RLock()  # wait_for's predicates may call the locked accessors
        self._held: list = []  # policy chunks waiting for stamp + latency (simulated time)
        self._gate_open_ns = 0
        self._clock_seen = (0, time.monotonic())  # (sim ns, wall s when it last advanced)
        self.ee_pose: np.ndarray | None = None
        self.width: float | None = None
        self.twin_state: dict | None = None
        self.scene: dict | None = None
        self.recorder_status = ""
        self.gate_open = False
        self.policy_chunks_seen = 0  # gate or not: the policy is loaded and answering
        self.chunk_arrivals: list[float] = []  # node-clock seconds at which chunks were forwarded
        self.end_to_end_ms: list[float] = []
        self.dropped: list[str] = []  # reasons of observations the policy skipped (not its execution schedule)
        self.inference_ms: list[float] = []
        self._String, self._Int64 = String, Int64
        n = self.node
        self.pub_chunk = n.create_publisher(MultiDOFJointTrajectory, TOPIC_COMMAND_CHUNK, RELIABLE_QOS)
        self.pub_reset = n.create_publisher(Int64, TOPIC_TWIN_RESET, RELIABLE_QOS)
        self.pub_recorder = n.create_publisher(String, TOPIC_RECORDER_COMMAND, RELIABLE_QOS)
        self.pub_await = n.create_publisher(Bool, TOPIC_TWIN_AWAIT_POLICY, LATCHED_QOS)
        self.pub_episode = n.create_publisher(String, TOPIC_POLICY_EPISODE, LATCHED_QOS)
        self._Bool = Bool
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
        self._Trigger = Trigger
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

    # -- time ----------------------------------------------------------------------------------------
    def now_ns(self) -> int:
        """The node's clock: simulated time on the sim clock, else the wall clock."""
        return self.node.get_clock().now().nanoseconds

    def time_scale(self) -> float:
        """Arm-speed seconds per clock second: 1 on simulated time; on real time, how fast the sim runs."""
        return 1.0 if self.sim_time else self.sim_rate()

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
            self.policy_chunks_seen += 1
            if not self.gate_open or stamp < self._gate_open_ns:
                return  # between episodes, or answering an observation from before this episode
            now = self.now_ns()
            if stamp + self.latency_ns > now:
                self._held.append(msg)  # released by /clock at stamp + latency
                return
        self._forward(msg, now)

    def _on_clock(self, msg):
        t = msg.clock.sec * NS + msg.clock.nanosec
        with self.lock:
            due = [m for m in self._held if stamp_to_ns(m.header.stamp) + self.latency_ns <= t]
            self._held = [m for m in self._held if m not in due]
        for m in due:
            self._forward(m, t)

    def _forward(self, msg, now_ns: int) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        with self.lock:
            if not self.gate_open:
                return
            self.chunk_arrivals.append(now_ns / NS)
            self.end_to_end_ms.append((now_ns - stamp) / 1e6)
        self.pub_chunk.publish(msg)

    def _on_skipped(self, msg):
        skipped = json.loads(msg.data)
        with self.lock:
            if self.gate_open and skipped["stamp_ns"] >= self._gate_open_ns and skipped["reason"] != "executing":
                self.dropped.append(skipped["reason"])

    def _on_pose(self, msg):
        p, q = msg.pose.position, msg.pose.orientation
        pose = geometry.pose_from_pos_quat([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
        with self.lock:
            self.ee_pose = pose

    def _on_joints(self, msg):
        names = list(msg.name)
        try:
            w = sum(msg.position[names.index(j)] for j in ("fr3_finger_joint1", "fr3_finger_joint2"))
        except ValueError:
            return
        with self.lock:
            self.width = float(w)

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
        for status in msg.status:
            if status.name != "policy_node":
                continue
            for kv in status.values:
                if kv.key == "inference_ms":
                    try:
                        v = float(kv.value)
                    except ValueError:
                        continue
                    if v >= 0:
                        with self.lock:
                            if self.gate_open:
                                self.inference_ms.append(v)

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
        raise SupervisorError(
            f"the arm did not reach {np.round(p1, 3).tolist()} within {timeout_s:.0f} s of sim time "
            f"({timeout_s / rate:.0f} s of the node's clock at {rate:.2f}x; TCP at "
            f"{np.round(now[:3, 3], 3).tolist()}, {100 * path.s:.0f} % along the path "
            f"after {path.restarts} restart(s) from the arm, "
            f"gripper {w * 1000:.0f} mm for {width * 1000:.0f} mm)"
        )

    def reset_scene(self, seed: int, timeout_s: float = 10.0, check=None) -> dict:
        self.pub_reset.publish(self._Int64(data=int(seed)))
        return self.wait_for(
            lambda: self.scene if self.scene and self.scene.get("seed") == seed else None,
            timeout_s,
            f"{TOPIC_TWIN_SCENE} for seed {seed}",
            check,
        )

    def sim_rate(self) -> float:
        """How fast the twin runs against the wall clock (0.05-1): timeouts and plan clocks scale by it."""
        return min(1.0, max(0.05, self.twin().get("steps_per_s", 1000.0) / 1000.0))

    def twin(self) -> dict:
        with self.lock:
            return dict(self.twin_state or {})

    def acknowledge_stop(self, timeout_s: float = 10.0, check=None) -> str:
        """Act as the operator between episodes: acknowledge a stop franka_node holds for (a robot
        error or a divergence stop in the last episode) so the next episode can home; returns what
        was acknowledged ("" when nothing). The caller says so: it is never silent."""
        if not self.ack_client.wait_for_service(timeout_sec=timeout_s):
            raise SupervisorError(f"no {SERVICE_FRANKA_ACKNOWLEDGE} service: is franka_node running?")
        future = self.ack_client.call_async(self._Trigger.Request())
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
        self.pub_recorder.publish(self._String(data=command))
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
        with that seed's noise (``chunk.SamplingSeeds``)."""
        with self.lock:
            self.chunk_arrivals, self.end_to_end_ms, self.inference_ms = [], [], []
            self.dropped = []
            self._held = []
            self._gate_open_ns = self.now_ns()
            if episode_seed is not None:
                episode = {"seed": int(episode_seed), "start_ns": self._gate_open_ns}
                self.pub_episode.publish(self._String(data=json.dumps(episode)))
            self.gate_open = True
        if self.sim_time:
            self.pub_await.publish(self._Bool(data=True))

    def close_gate(self) -> tuple[list[float], list[str], list[float], list[float]]:
        """Stop forwarding; (forward times s, reasons of dropped observations, end-to-end ms, inference ms)."""
        if self.sim_time:
            self.pub_await.publish(self._Bool(data=False))
        with self.lock:
            self.gate_open = False
            self._held = []
            return (list(self.chunk_arrivals), list(self.dropped), list(self.end_to_end_ms), list(self.inference_ms))


# --- bringing up the twin stack -------------------------------------------------------------------


class TwinStack:
    """All nodes of the twin as separate processes on a private ROS domain, plus the supervisor.

    ``with TwinStack(...) as stack:`` starts twin_node, one camera_node (backend twin) per
    configured camera, voxel_node, franka_node (robot_ip = the twin's loopback address),
    recorder_node and optionally policy_node (its chunks remapped to the supervisor's gate);
    leaving the block (normally, on error, Ctrl-C or SIGTERM) stops them all.

    ``realtime=False`` (the default): twin_node owns the clock (/clock), every other node runs
    with use_sim_time, the cameras take the frames the sim requests and policy chunks take
    effect at their observation's time + ``latency_s``. ``realtime=True``: everything on the
    wall clock, as on a lab machine; only meaningful where the machine holds real time.
    """

    def __init__(
        self,
        out_dir,
        lab_path,
        twin_path,
        policy: str | None = None,
        domain_id: int | None = None,
        task: str = "twin",
        device: str = "cpu",
        precision: str = TWIN_PRECISION,
        seed: int = 0,
        record_clouds: bool = False,
        start_timeout_s: float = 120.0,
        torch_threads: int | None = None,
        lenient: bool = False,
        attach: bool = False,
        realtime: bool = False,
        latency_s: float = 0.1,
        stall_timeout_s: float = 30.0,
        max_speed: float = 1.0,
        composed: bool = False,
        log=print,
    ):
        self.out_dir = Path(out_dir)
        self.lab_path, self.twin_path = Path(lab_path), Path(twin_path)
        self.lab = load_lab_config(self.lab_path)
        self.cfg = load_twin_config(self.twin_path)
        self.policy, self.domain_id, self.task, self.device = policy, domain_id, task, device
        self.precision = precision  # policy_node's
        self.seed, self.record_clouds, self.start_timeout_s = seed, record_clouds, start_timeout_s
        # On simulated time the sim waits while the policy infers, so inference has the machine to
        # itself: all cores. On real time everything runs at once, and one thread was faster.
        self.torch_threads = torch_threads if torch_threads is not None else (1 if realtime else os.cpu_count() or 1)
        # lenient: accept older observations (CI machines too loaded to hold 5 Hz); never for reported numbers
        self.lenient = lenient
        self.attach = attach  # nodes started by someone else (launch file): only supervise them
        self.realtime, self.latency_s, self.stall_timeout_s = realtime, latency_s, stall_timeout_s
        self.max_speed = max_speed  # simulated time: at most this many sim seconds per wall second
        self.composed = composed  # every node but twin_node in one process (equidiff_ros.composed)
        self.log = log
        self.group = None
        self.sup: Supervisor | None = None

    def __enter__(self) -> Self:
        if self.attach:
            self.log(f"[twin] attaching to the running nodes on ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')}")
            self.sup = self._supervisor()
            try:
                self.sup.wait_ready(self.start_timeout_s)
                self.sup.wait_for(
                    lambda: self.sup.recorder_status.startswith("idle"), self.start_timeout_s, "recorder_node"
                )
            except BaseException:
                self.__exit__(None, None, None)
                raise
            return self
        env = private_ros_env(self.domain_id, OMP_NUM_THREADS="1", LP_NUM_THREADS="1")
        self.domain_id = int(env["ROS_DOMAIN_ID"])
        env["EQUIDIFF_TWIN_SHM"] = f"equidiff_twin_{self.domain_id}_{os.getpid()}"
        # the supervisor (this process) joins the same private domain
        for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "EQUIDIFF_TWIN_SHM", "MUJOCO_GL"):
            os.environ[key] = env[key]
        self.host = free_loopback_host()
        self.group = ProcessGroup(env, self.out_dir / "logs").__enter__()
        try:
            self._start_nodes(node_command)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def _supervisor(self) -> Supervisor:
        return Supervisor(
            self.lab.base_frame,
            sim_time=not self.realtime,
            latency_s=self.latency_s,
            stall_timeout_s=self.stall_timeout_s,
        )

    def _start_nodes(self, node_command) -> None:
        g = self.group
        sim = not self.realtime
        clock = f"simulated time (latency budget {self.latency_s * 1000:.0f} ms)" if sim else "real time"
        self.log(
            f"[twin] ROS_DOMAIN_ID={self.domain_id}; franky-sim on {self.host}; {clock}; logs in {g.log_dir}"
            + ("; the pipeline's nodes in one process" if self.composed else "")
        )
        g.start(
            "twin_node",
            node_command(
                "twin_node",
                {
                    "lab_config": str(self.lab_path),
                    "twin_config": str(self.twin_path),
                    "host": self.host,
                    "seed": self.seed,
                    "clock": "sim" if sim else "realtime",
                    "latency_s": float(self.latency_s),
                    "stall_timeout_s": float(self.stall_timeout_s),
                    "max_speed": float(self.max_speed),
                },
            ),
        )
        self.sup = self._supervisor()
        self.sup.wait_for(
            lambda: self.sup.twin_state is not None, self.start_timeout_s, "twin_node's /twin/state", g.check
        )
        specs = self._pipeline_specs()
        if self.composed:
            g.start(
                "pipeline",
                composed_command(
                    {name: params for name, (_kind, params, _remaps) in specs.items()},
                    self.out_dir / "logs" / "pipeline_params.yaml",
                    {name: remaps for name, (_kind, _params, remaps) in specs.items() if remaps},
                    kinds={name: kind for name, (kind, _params, _remaps) in specs.items()},
                ),
                priority=True,
            )  # franka_node is in it
        else:
            for name, (kind, params, remaps) in specs.items():
                if name != kind:  # its node name, as in the composed process and twin.launch.py
                    remaps = {**remaps, "__node": name}
                g.start(name, node_command(kind, params, remaps), priority=name == "franka_node")
        self.sup.wait_ready(self.start_timeout_s, g.check)
        self.sup.wait_for(
            lambda: self.sup.recorder_status.startswith("idle"), self.start_timeout_s, "recorder_node", g.check
        )
        if self.policy:  # an episode must not owe chunks to a policy still loading its checkpoint
            self.sup.wait_for(
                lambda: self.sup.policy_chunks_seen > 0,
                self.start_timeout_s,
                "policy_node's first chunk (loading and warming up the policy)",
                g.check,
            )
        self.log("[twin] all nodes up")

    def _pipeline_specs(self) -> dict[str, tuple[str, dict, dict]]:
        """Every node but twin_node: name -> (executable, parameters, remaps), in start order; one
        camera_node per camera, named ``camera_<camera>``."""
        sim = not self.realtime
        common = {"lab_config": str(self.lab_path), "use_sim_time": sim}  # twin_node owns the clock
        clouds = {"reliable_clouds": True} if sim else {}  # the lockstep owes every frame a chunk
        specs = {}
        for cam in self.lab.cameras:
            specs[f"camera_{cam.name}"] = (
                "camera_node",
                {
                    **common,
                    **clouds,
                    "backend": "twin",
                    "camera": cam.name,
                    **({"backend_options": "{lockstep: true}"} if sim else {}),
                },
                {},
            )
        voxel = {"stale_after_s": 3.0, "slop_s": 0.15} if self.lenient and not sim else {}
        specs["voxel_node"] = ("voxel_node", {**common, **clouds, **voxel}, {})
        # run_dir: its unclean-exit marker lives with this job's logs, not in the machine's tmp
        specs["franka_node"] = (
            "franka_node",
            # require_ack_on_start: the supervisor is the twin's operator (it acknowledges stops before homing)
            {
                **common,
                "robot_ip": self.host,
                "realtime": False,
                "run_dir": str(self.out_dir / "logs"),
                "require_ack_on_start": False,
            },
            {},
        )
        specs["recorder_node"] = (
            "recorder_node",
            {
                **common,
                "output_dir": str(self.out_dir / "bags"),
                "task": self.task,
                "record_clouds": self.record_clouds,
            },
            {},
        )
        if self.policy:
            if sim:  # an observation is at most L old in sim time when its chunk is due
                # the twin holds each chunk until its stamp + L exactly: the policy bridges that L
                # (its latency_s auto would see only the publication, not the hold)
                timing = {"max_observation_age_s": max(0.5, self.latency_s + 0.2), "latency_s": float(self.latency_s)}
            else:
                timing = {"max_observation_age_s": 4.0, "max_state_offset_s": 0.5} if self.lenient else {}
            control = load_control_config(default_config_dir() / "control.yaml")  # franka_node's, as started here
            specs["policy_node"] = (
                "policy_node",
                {
                    **common,
                    "checkpoint": str(self.policy),
                    "device": self.device,
                    "precision": self.precision,
                    "torch_threads": self.torch_threads,
                    "rtc_max_gap_m": control.safety.max_first_step_jump_m,
                    **timing,
                },
                {TOPIC_COMMAND_CHUNK: TOPIC_TWIN_POLICY_CHUNK},
            )
        return specs

    def __exit__(self, *exc) -> None:
        try:
            if self.sup is not None and self.sup.recorder_status.startswith("recording"):
                try:  # keep what was recorded, marked as interrupted
                    self.sup.recorder("stop failure interrupted", "idle", timeout_s=5.0)
                except SupervisorError:
                    pass
        finally:
            if self.group is not None:
                self.group.__exit__(*exc)
                self.group = None
            if self.sup is not None:
                self.sup.close()
                self.sup = None

    def check(self) -> None:
        if self.group is not None:
            self.group.check()

    def home(self) -> None:
        """Move to the ready pose; first acknowledge a stop franka_node holds for, saying so."""

        stopped = self.sup.acknowledge_stop(check=self.check)
        if stopped:
            print(
                f"[twin] franka_node held after '{stopped}'; acknowledged (as the operator) before homing", flush=True
            )
        ex = self.cfg.expert
        self.sup.move_to(
            tcp_pose(ex.ready_position, 0.0),
            ex.open_width,
            speed=ex.speed,
            timeout_s=self.cfg.episode.home_timeout_s,
            check=self.check,
        )


def object_poses_from_state(state: dict) -> tuple[np.ndarray, np.ndarray]:
    """4x4 block and bowl poses from a /twin/state message."""
    out = []
    for body in ("block", "bowl"):
        obj = state["objects"][body]
        out.append(geometry.make_pose(geometry.rotz(obj["yaw"]), np.asarray(obj["xyz"], dtype=float)))
    return out[0], out[1]


class LiveTwin:
    """The live twin stack as an ``episode.EpisodeWorld``: the supervisor homes the arm, resets
    the scene, reads success from /twin/state and drives recorder_node."""

    def __init__(self, stack: TwinStack):
        self.stack, self.sup = stack, stack.sup
        self.scene: ScenePoses | None = None

    def home(self) -> None:
        self.stack.home()

    def reset_scene(self, seed: int) -> None:
        self.scene = ScenePoses.from_dict(self.sup.reset_scene(seed, check=self.stack.check))  # recorded with the bag

    def settle(self, seconds: float) -> None:
        self.sup.sim_sleep(seconds, self.stack.check)

    def now_s(self) -> float:
        return self.sup.now_ns() / NS

    def success(self) -> bool:
        return bool(self.sup.twin().get("success"))

    def start_recording(self) -> str:
        status = self.sup.recorder(f"start {self.stack.task}", "recording", check=self.stack.check)
        return status.split(" ", 1)[1] if " " in status else ""

    def stop_recording(self, keep: bool, success: bool, note: str) -> None:
        scene = scene_record(self.stack.cfg.scene, self.scene) if self.scene is not None else {}
        words = " ".join(f"extra.{key}={value}" for key, value in scene.items())
        command = f"stop {'success' if success else 'failure'} {words} {note}" if keep else "discard"
        self.sup.recorder(command, "idle", check=self.stack.check)


class GatedPolicy:
    """policy_node as an ``episode.Actor``: its chunks reach the robot while the gate is open.

    The episode's duration counts from the first chunk; a stall twin_node reports (a stage that
    did not deliver within its stall timeout, simulated time) ends the episode at once."""

    def __init__(self, stack: TwinStack, seed: int | None = None, poll_s: float = 0.05):
        self.stack, self.sup, self.seed, self.poll_s = stack, stack.sup, seed, poll_s
        self.stalls0 = 0
        self.arrivals: list[float] = []
        self.dropped: list[str] = []
        self.end_to_end_ms: list[float] = []
        self.inference_ms: list[float] = []

    def begin(self) -> float:
        sup = self.sup
        self.stalls0 = sup.twin().get("stalls", 0)
        sup.open_gate(self.seed)
        gate_t = sup.now_ns() / NS
        sup.wait_for(
            lambda: sup.chunk_arrivals or sup.twin().get("stalls", 0) > self.stalls0,
            60.0 + self.stack.stall_timeout_s,
            "the first policy chunk",
            self.stack.check,
        )
        return sup.chunk_arrivals[0] if sup.chunk_arrivals else gate_t

    def advance(self) -> None:
        time.sleep(self.poll_s)

    def judging(self) -> bool:
        return True

    def done(self) -> bool:
        return False

    def stalled(self) -> str:
        self.stack.check()
        self.sup.check_clock()
        state = self.sup.twin()
        return state.get("last_stall", "a stage of the pipeline") if state.get("stalls", 0) > self.stalls0 else ""

    def end(self) -> None:
        self.arrivals, self.dropped, self.end_to_end_ms, self.inference_ms = self.sup.close_gate()
        self.sup.send_target(*self.sup.current())  # hold where it is while the recorder closes


class LiveExpert:
    """The scripted expert as an ``episode.Actor`` through the teleop path: one-point chunks at
    ``hz`` (20 Hz), as teleop_node sends them.

    The plan's clock advances only while the arm keeps up (TCP within ``max_lag_m`` of the
    target, like teleop's ``max_lead_m``), so a twin slower than real time (a loaded CPU) gets
    the same motion, just later. Success counts once the plan is done; ``extra_s`` after it the
    expert gives up. An arm that never catches up (blocked, in a reflex) raises
    SupervisorError after ``timeout_s`` (default: 30 s + 10x the plan)."""

    def __init__(
        self,
        stack: TwinStack,
        hz: float | None = None,
        max_lag_m: float = 0.03,
        extra_s: float = 4.0,
        timeout_s: float | None = None,
    ):
        self.stack, self.sup, self.cfg = stack, stack.sup, stack.cfg
        self.hz = hz or self.cfg.expert.command_hz
        self.max_lag_m, self.extra_s, self.timeout_s = max_lag_m, extra_s, timeout_s
        self.plan = None
        self.t_plan = 0.0

    def begin(self) -> float:
        sup, cfg = self.sup, self.cfg
        block, bowl = object_poses_from_state(sup.twin())
        start, width = sup.current()
        self.plan = plan_pick_place(start, width, block, bowl, cfg.scene.block_size[2], cfg.expert)
        self.t_plan, self.last = 0.0, sup.now_ns() / NS
        limit = self.timeout_s if self.timeout_s is not None else 30.0 + 10.0 * self.plan.duration  # node clock
        self.deadline = self.last + limit / sup.time_scale()
        return self.last

    def advance(self) -> None:
        sup, plan = self.sup, self.plan
        now = sup.now_ns() / NS
        if now > self.deadline:
            lag_mm = 1000 * np.linalg.norm(sup.current()[0][:3, 3] - plan.target_at(self.t_plan)[0][:3, 3])
            raise SupervisorError(
                f"the scripted expert's {plan.duration:.0f} s plan did not finish in time: "
                f"plan clock at {self.t_plan:.1f} s, TCP {lag_mm:.0f} mm from its target"
            )
        dt, self.last = now - self.last, now
        pose, width = plan.target_at(self.t_plan)
        keeping_up = np.linalg.norm(sup.current()[0][:3, 3] - pose[:3, 3]) < self.max_lag_m
        # the plan's clock waits for a lagging arm, except after the plan (its final target holds)
        if keeping_up or self.t_plan >= plan.duration:
            self.t_plan += dt * sup.time_scale()
        sup.send_target(pose, width)
        time.sleep(1.0 / self.hz)  # wall pacing of the stream; the plan runs on the node's clock

    def judging(self) -> bool:
        return self.t_plan >= self.plan.duration

    def done(self) -> bool:
        return self.t_plan >= self.plan.duration + self.extra_s

    def stalled(self) -> str:
        self.stack.check()
        self.sup.check_clock()
        return ""

    def end(self) -> None:
        pass  # the plan's last target holds the arm


def run_policy_episode(stack: TwinStack, seed: int, max_duration_s: float) -> EpisodeRecord:
    """One episode of the main job (``episode.run_episode`` with policy_node acting through the
    gate); durations on the node clock (simulated time by default).

    An episode in which twin_node reports a stall (a camera or the policy did not deliver within
    its stall timeout) ends at once as ``stalled``, naming the stage; its bag is kept."""

    policy = GatedPolicy(stack, seed)
    result = run_episode(LiveTwin(stack), policy, seed, max_duration_s, stack.cfg.success.hold_s)
    return EpisodeRecord(
        seed=seed,
        success=result.success,
        duration_s=result.duration_s,
        chunks=len(policy.arrivals),
        dropped_cycles=len(policy.dropped),  # observations due an answer that got none
        bag=result.bag,
        end_to_end_ms=policy.end_to_end_ms,
        inference_ms=policy.inference_ms,
        stalled=result.stalled,
    )
