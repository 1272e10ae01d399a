"""policy_node: voxels + robot state -> DDIM policy, once per observation -> /franka/command_chunk.

Wiring:
  /voxels (PointCloud2 of occupied voxels)       -> newest observation (kept raw; decoded in the worker);
                                                    a new one starts a cycle at once if the worker is idle
                                                    and the inputs are fresh, else waits for the worker
                                                    (newer observations replace it meanwhile); read best
                                                    effort (``common.VOXEL_READER_QOS``): a paused policy
                                                    must not hold the grids back from the other readers
  /franka/ee_pose, /franka/joint_states          -> short history; the pose/width nearest the voxel stamp
  worker: ``InferencePolicy.predict`` -> the steps of the predicted ``horizon`` that bridge the
          latency (``policy.chunk_sizing.ChunkSizing``: ``n_action_steps``, ``execute_steps``, ``latency_s``)
          -> ``wire.chunk.chunk_from_actions`` (step i at observation stamp + i·dt) -> /franka/command_chunk
  timer at ``rate_hz`` -> warns when no fresh observation has come (a camera or the voxel node is down)
  timer at 1 Hz -> /diagnostics (``policy_node``: inference_ms, observation_age_ms, skipped_cycles,
                   obs_to_cmd_ms and its p50/p95, latency_s (auto | auto (initial) | fixed | off),
                   latency_estimate_ms, latency_bridged_max_ms, publish_steps; WARN when L exceeds
                   what the chunks can bridge)
  /policy/doubt (geometry_msgs/Vector3Stamped) <- each chunk's doubt (``policy.doubt``, ``wire.rosmsg.doubt_msg``),
                   stamped with the chunk's stamp; also on /diagnostics (doubt_m, doubt_disagreement_m, ...)
  /policy/skipped (std_msgs/String JSON {stamp_ns, reason}) <- each observation that will get no chunk
                   (the twin's sim then stops waiting for it; a recorder or operator sees why)
  /policy/enable (std_srvs/SetBool service)      -> true runs, false pauses the policy (``equidiff lab policy``)
  /teleop/active (std_msgs/Bool, latched)        -> true (the operator took over with the SpaceMouse) pauses it;
                   it stays paused until the operator enables it again
  /policy/state (std_msgs/String, latched)       <- ``running`` or ``paused <reason>``
  /policy/episode (std_msgs/String JSON {seed, start_ns}, latched) -> an episode begins (the twin's
                   supervisor): the first observation stamped at or after start_ns is answered at once,
                   and the episode's answered observations get ``wire.chunk.SamplingSeeds``' noise for its
                   seed, the in-process evaluation's, so both sample a scene alike

With ``doubt_gate`` a chunk whose doubt exceeds ``doubt_quantile`` of the signal over the policy's own demos
(the calibration ``equidiff check doubt --write`` stores in the policy file) is not published: the node pauses
as ``asks for help: <why>`` (announced as ``doubt`` on /policy/skipped, WARN on /diagnostics), franka_node
holds once the steps already sent have run, and only an enable (``p`` in ``equidiff lab``) lets it go on.

While paused no chunk is published: each observation is announced on /policy/skipped as
``paused`` (an inference already running is finished and dropped), and /diagnostics says
``paused``. ``start_paused`` (default false; robot.launch.py sets true) waits for an enable.

The policy runs once per observation, so the cameras set its rate, with no timer
phase between a grid and its inference; on the twin's simulated time, which pauses until
this observation's chunk has arrived, a cycle waiting for a timer tick would never come.
What it refuses of its inputs, and the counters that say so: docs/architecture.md, "What a node refuses".
An observation is skipped (``skipped_<reason>``, with a throttled warning) when a newer one
replaced it while the worker was busy (``busy``), when it is older than
``max_observation_age_s`` (``stale_observation``; a missing camera stops the voxel node's
matched sets, so it shows up as a stale grid), when the voxel node reports ERROR in
/diagnostics (``voxel_error``), or when there is no robot state near its stamp (``no_robot_state``).

Chunk execution (``n_action_steps``, ``execute_steps``, ``latency_s``, ``rtc``) is described in
docs/chunking.md; the defaults are ``wire.chunk.DEFAULT_*``, which robot.launch.py and twin.launch.py
declare as their launch arguments' defaults. ``execute_steps`` 0 (answer once a chunk has run,
fewer steps when the latency needs it) was chosen by the twin's closed-loop evaluation
(docs/evaluation_scheme.md).

Parameters: ``PARAMETERS`` below (``--help``, ``ros2 param describe``, docs/parameters.md).
"""

from __future__ import annotations

import collections
import json
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from rclpy.node import Node
from sensor_msgs.msg import JointState, PointCloud2
from std_msgs.msg import Bool, String
from std_srvs.srv import SetBool
from trajectory_msgs.msg import MultiDOFJointTrajectory

from equidiff_core.config import Bounds, ConfigError, LabConfig
from equidiff_core.control import SafetyConfig
from equidiff_core.control.metrics import percentiles_ms
from equidiff_core.perception.observation import MAX_FUTURE_STAMP_S, STATE_TOLERANCE_S, StateHistory, ee_input
from equidiff_core.policy.chunk_sizing import ChunkSizing
from equidiff_core.policy.doubt import (
    DEFAULT_GATE,
    DEFAULT_GATE_QUANTILE,
    DEFAULT_SAMPLES,
    DEFAULT_SIGNAL,
    HELP_REASON,
    SIGNALS,
    DoubtGate,
    DoubtTracker,
)
from equidiff_core.policy.file import CheckpointError
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.runtime.machine import PRECISIONS
from equidiff_core.wire import rosmsg
from equidiff_core.wire.chunk import (
    DEFAULT_EXECUTE_STEPS,
    DEFAULT_LATENCY_S,
    DEFAULT_N_ACTION_STEPS,
    DEFAULT_RTC,
    DEFAULT_TRANSPORT_S,
    RealTimeChunking,
    SamplingSeeds,
    chunk_from_actions,
    chunk_to_msg,
)
from equidiff_core.wire.pointcloud import CloudError, VoxelGridSpec, voxel_msg_to_grid
from equidiff_core.wire.rosmsg import RclpyFactory, stamp_to_ns
from equidiff_core.wire.topics import (
    SERVICE_POLICY_ENABLE,
    TOPIC_COMMAND_CHUNK,
    TOPIC_DIAGNOSTICS,
    TOPIC_EE_POSE,
    TOPIC_JOINT_STATES,
    TOPIC_POLICY_DOUBT,
    TOPIC_POLICY_EPISODE,
    TOPIC_POLICY_SKIPPED,
    TOPIC_POLICY_STATE,
    TOPIC_TELEOP_ACTIVE,
    TOPIC_VOXELS,
)
from equidiff_ros.common import LATCHED_QOS, RELIABLE_QOS, VOXEL_READER_QOS, declare_lab_config, now_ns, wait_for_clock
from equidiff_ros.parameters import LAB_CONFIG, NodeParameter, NodeParameters, bounds_of, parameters_help
from equidiff_ros.runner import run_node

NODE_NAME = "policy_node"

PARAMETERS = NodeParameters(
    LAB_CONFIG,
    NodeParameter("checkpoint", "", "Exported policy file (required)"),
    NodeParameter("device", "cpu", "Torch device: cpu, cuda[:N] or auto"),
    NodeParameter(
        "precision",
        "auto",
        "Inference precision; auto: bf16 on CUDA, fp32 on a CPU",
        choices=PRECISIONS,
    ),
    NodeParameter("jit", True, "Trace the denoising step with torch.jit.trace"),
    NodeParameter("compile", False, "Compile the denoising step with torch.compile"),
    NodeParameter(
        "rate_hz",
        5.0,
        "Rate at which a missing observation is reported (the observations set the inference rate)",
        bounds_of(LabConfig, "observation_hz"),
        default_from="lab.yaml observation_hz",
        number=True,
    ),
    NodeParameter(
        "max_observation_age_s",
        0.5,
        "An older observation is skipped as stale_observation",
        Bounds("s", gt=0, le=10.0),
        number=True,
    ),
    NodeParameter(
        "max_state_offset_s",
        STATE_TOLERANCE_S,
        "Robot state farther than this from the observation's stamp is no state (no_robot_state)",
        Bounds("s", gt=0, le=1.0),
        number=True,
    ),
    NodeParameter(
        "max_future_stamp_s",
        MAX_FUTURE_STAMP_S,
        "A grid stamped further ahead of this node's clock is skipped as future_observation",
        Bounds("s", gt=0, le=1.0),
        number=True,
    ),
    NodeParameter("seed", -1, "DDIM noise seed outside an announced episode; -1: random", Bounds("", ge=-1)),
    NodeParameter(
        "n_action_steps",
        DEFAULT_N_ACTION_STEPS,
        "Steps published per chunk, at most the horizon; 0: enough to bridge the latency (the preset's with "
        "latency_s -1)",
        Bounds("", ge=0),
    ),
    NodeParameter(
        "execute_steps",
        DEFAULT_EXECUTE_STEPS,
        "Steps of a chunk that run before the next observation is answered (the others are skipped as "
        "executing); 0: all n_action_steps, fewer when the latency is too long for them; 1: answer every observation",
        Bounds("", ge=0),
    ),
    NodeParameter(
        "latency_s",
        DEFAULT_LATENCY_S,
        "Observation-to-arrival latency L each chunk bridges: auto (measured online, p95 of the last 20, plus "
        "latency_transport_s), a number of seconds 0..10 (fixed), or -1 (off: chunks of n_action_steps)",
        dynamic_typing=True,
    ),
    NodeParameter(
        "latency_transport_s",
        DEFAULT_TRANSPORT_S,
        "latency_s auto: added to the measured latency for DDS delivery and franka_node's control tick, which "
        "this node cannot see",
        Bounds("s", ge=0, le=1.0),
        number=True,
    ),
    NodeParameter("rtc", DEFAULT_RTC, "Real-time chunking: each chunk denoised towards the previous one"),
    NodeParameter(
        "rtc_max_gap_m",
        SafetyConfig.max_first_step_jump_m,
        "rtc: a previous chunk farther than this from the observed TCP is not joined (franka_node rejected it); "
        "the launchers pass control.yaml's safety.max_first_step_jump_m",
        bounds_of(SafetyConfig, "max_first_step_jump_m"),
        number=True,
    ),
    NodeParameter(
        "torch_threads",
        1,
        "Inference threads; 0: torch's default (on a shared CPU more threads are slower)",
        Bounds("", ge=0, le=1024),
    ),
    NodeParameter(
        "doubt_signal",
        DEFAULT_SIGNAL,
        "The doubt signal on /policy/doubt's x and /diagnostics' doubt_m (docs/doubt.md): disagreement (the new "
        "chunk against the previous one's remainder, free) or spread (of doubt_samples samples)",
        choices=SIGNALS,
    ),
    NodeParameter(
        "doubt_samples",
        DEFAULT_SAMPLES,
        "DDIM samples per observation sharing one encoder pass (the first is published); 2 or more also give the "
        "spread; 1: plain DDIM",
        Bounds("", ge=1, le=64),
    ),
    NodeParameter(
        "doubt_gate",
        DEFAULT_GATE,
        "Ask for help: a chunk whose doubt exceeds doubt_quantile of the policy's demos is not published and the "
        "node pauses (the arm holds) until enabled again; needs the calibration in the policy file (equidiff check "
        "doubt --write)",
    ),
    NodeParameter(
        "doubt_quantile",
        DEFAULT_GATE_QUANTILE,
        "doubt_gate: the threshold, this quantile of the signal over the policy's demos",
        Bounds("", gt=0, le=1),
        number=True,
    ),
    NodeParameter("start_paused", False, "Start paused: no chunks until /policy/enable (robot.launch.py sets it)"),
)

USAGE = (
    __doc__
    + parameters_help(PARAMETERS)
    + """
usage: policy_node --ros-args -p checkpoint:=/path/policy.pt [-p device:=cpu -p precision:=auto|fp32|bf16
                   -p rate_hz:=5.0 -p max_observation_age_s:=0.5 -p execute_steps:=0 -p latency_s:=auto
                   -p latency_transport_s:=0.01 -p rtc:=false -p rtc_max_gap_m:=0.08]
"""
)


class PolicyNode(Node):
    def __init__(self, node_name: str = NODE_NAME):
        super().__init__(node_name)
        self.lab = declare_lab_config(self)
        param = lambda name: PARAMETERS.declare(self, name)
        checkpoint = param("checkpoint")
        device = param("device")
        precision = param("precision")
        jit = param("jit")
        compile_step = param("compile")
        rate_hz = PARAMETERS.declare(self, "rate_hz", self.lab.observation_hz)
        self.max_obs_age_ns = int(param("max_observation_age_s") * 1e9)
        self.max_state_offset_ns = int(param("max_state_offset_s") * 1e9)
        self.max_future_ns = int(param("max_future_stamp_s") * 1e9)
        seed = param("seed")
        n_steps = param("n_action_steps")
        execute_steps = param("execute_steps")
        latency_s = param("latency_s")
        transport_s = param("latency_transport_s")
        rtc = param("rtc")
        rtc_max_gap_m = param("rtc_max_gap_m")
        threads = param("torch_threads")
        doubt_signal = param("doubt_signal")
        gate_on, gate_quantile = param("doubt_gate"), param("doubt_quantile")
        self.doubt_samples = param("doubt_samples")
        if doubt_signal == "spread" and self.doubt_samples < 2:
            raise ValueError(f"doubt_signal spread needs doubt_samples >= 2, got {self.doubt_samples}")
        self._paused = "waiting for an enable (start_paused)" if param("start_paused") else ""  # "" = running
        if not checkpoint:
            raise CheckpointError(
                "the 'checkpoint' parameter is required (an exported policy file, "
                "e.g. -p checkpoint:=runs/pick/policy.pt)"
            )
        # Loading and warming up on one thread: the node starts beside every other node (in the twin also
        # beside the sim's cameras), where more threads than idle cores are slower (docs/results/twin.md
        # measures it for inference). Inference then gets its own.
        inference_threads = int(threads) if threads > 0 else torch.get_num_threads()
        torch.set_num_threads(1)
        t0 = time.perf_counter()
        self.policy = load_inference_policy(
            Path(checkpoint), device=device, precision=precision, jit=jit, compile=compile_step
        )
        if self.policy.workspace != self.lab.workspace:
            raise CheckpointError(
                f"{checkpoint}: trained for workspace {self.policy.workspace}, but lab.yaml "
                f"has {self.lab.workspace}: the voxel grids would not match"
            )
        self.policy.warmup()
        torch.set_num_threads(inference_threads)
        preset = self.policy.preset
        self.sizing = ChunkSizing(preset, n_steps, execute_steps, latency_s, transport_s)
        self.last_publish_steps = 0
        # real-time chunking: each chunk denoised towards the previous one (None: plain DDIM, as without it);
        # its delay (the steps due before a chunk arrives) follows L, set before each inference
        self.chunking = (
            RealTimeChunking(
                RealTimeChunking.delay_for(self.sizing.latency_s(), preset.dt), self.sizing.dt_ns, rtc_max_gap_m
            )
            if rtc
            else None
        )
        self.seeds = SamplingSeeds(None if seed < 0 else int(seed))
        self.doubt = DoubtTracker(self.sizing.dt_ns, doubt_signal)  # reset where an episode or the operator restarts
        self.last_doubt = None  # the newest chunk's ChunkDoubt
        self.gate = None  # DoubtGate when doubt_gate is on
        self.alarms = 0
        if gate_on:
            if self.policy.doubt_calibration is None:
                raise CheckpointError(
                    f"doubt_gate needs the doubt calibration in {checkpoint}: run `equidiff check doubt "
                    f"{checkpoint} --demos <its training demos> --write <policy file>` first"
                )
            self.gate = DoubtGate(self.policy.doubt_calibration, gate_quantile, doubt_signal, self.doubt_samples)
        self._episode: dict | None = None  # announced on /policy/episode, begins at its start_ns
        self.get_logger().info(
            f"loaded {self.policy.name} policy '{preset.name}' from {checkpoint} "
            f"(weights sha256 {self.policy.weights_sha256}) on {device} ({precision}), sampling in "
            f"{self.policy.inference_steps} DDIM steps at t = {self.policy.timesteps}, "
            f"and warmed up in {time.perf_counter() - t0:.1f} s; executing {self.sizing.answers.steps} steps of dt "
            f"{preset.dt} s before the next answer"
            f"{' (fewer if the latency needs it)' if self.sizing.adaptive_steps else ''}; "
            f"publishing {self.sizing.describe()}"
            f"{'; real-time chunking' if self.chunking is not None else ''}"
        )
        # simulated time (the twin): nothing is timed before /clock. Loading and warming up time nothing,
        # so they come first: a twin that starts this node first overlaps them with its own start-up.
        wait_for_clock(self)

        self.factory = RclpyFactory()
        self._grid_spec = VoxelGridSpec.of(self.policy.workspace, self.lab.base_frame)
        self._lock = threading.Lock()
        self._voxels = None  # newest PointCloud2 that decoded
        self._grid = None  # its grid
        self.dropped = collections.Counter()  # robot-state messages dropped, by topic
        self._poses = StateHistory()  # TCP poses, matched to observations as training matches them
        self._widths = StateHistory()  # gripper widths
        self._voxel_error = ""  # voxel node status at ERROR level, if any
        self._busy = False
        self._cycle_lock = threading.Lock()  # the executor thread and the worker both start cycles
        self._last_obs_stamp = None
        self.skipped = collections.Counter()
        self.published = 0
        self.failures = 0
        self.inference_s = collections.deque(maxlen=50)
        self.obs_to_cmd_s = collections.deque(maxlen=50)
        self.obs_age_s = collections.deque(maxlen=50)

        self.pub_chunk = self.create_publisher(MultiDOFJointTrajectory, TOPIC_COMMAND_CHUNK, RELIABLE_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, RELIABLE_QOS)
        self.pub_skipped = self.create_publisher(String, TOPIC_POLICY_SKIPPED, RELIABLE_QOS)
        self.pub_doubt = self.create_publisher(Vector3Stamped, TOPIC_POLICY_DOUBT, RELIABLE_QOS)
        # before /voxels: the executor serves ready subscriptions in creation order, so an episode
        # announced just before a grid is applied before that grid is answered
        self.create_subscription(String, TOPIC_POLICY_EPISODE, self.on_episode, LATCHED_QOS)
        self.create_subscription(PointCloud2, TOPIC_VOXELS, self.on_voxels, VOXEL_READER_QOS)
        self.create_subscription(PoseStamped, TOPIC_EE_POSE, self.on_pose, RELIABLE_QOS)
        self.create_subscription(JointState, TOPIC_JOINT_STATES, self.on_joints, RELIABLE_QOS)
        self.create_subscription(DiagnosticArray, TOPIC_DIAGNOSTICS, self.on_diagnostics, RELIABLE_QOS)
        self.pub_state = self.create_publisher(String, TOPIC_POLICY_STATE, LATCHED_QOS)
        self.create_subscription(Bool, TOPIC_TELEOP_ACTIVE, self.on_teleop_active, LATCHED_QOS)
        self.create_service(SetBool, SERVICE_POLICY_ENABLE, self.on_enable)
        self.publish_state()
        self.worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="policy")
        self.create_timer(1.0 / rate_hz, self.watch_observations)
        self.create_timer(1.0, self.publish_diagnostics)

    # --- inputs (cheap: callbacks never wait for inference) ---------------------------
    def on_voxels(self, msg) -> None:
        # Decoded here, not in the worker: a message that is not this policy's grid must not
        # replace the observation waiting for the worker.
        stamp = stamp_to_ns(msg.header.stamp)
        try:
            rosmsg.check_not_future(stamp, now_ns(self), self.max_future_ns, "a voxel grid")
        except rosmsg.MessageError as err:
            return self.skip("future_observation", f"{err}: a clock is wrong", stamp)
        try:
            grid = voxel_msg_to_grid(msg, self._grid_spec)
        except CloudError as err:
            return self.skip(
                "malformed_observation", f"a {TOPIC_VOXELS} message is not this policy's grid: {err}", stamp
            )
        with self._cycle_lock:
            previous = self._voxels
            if self._busy and previous is not None and stamp_to_ns(previous.header.stamp) != self._last_obs_stamp:
                self.skip(
                    "busy",
                    "an observation was replaced by a newer one while the previous inference ran",
                    stamp_to_ns(previous.header.stamp),
                )
            self._voxels, self._grid = msg, grid
        self.start_cycle()

    def drop(self, topic: str, reason: str, detail: str) -> None:
        """Count (``dropped_<topic>_<reason>``) and say (throttled) that an input message was unusable."""
        self.dropped[f"{topic.strip('/').replace('/', '_').removeprefix('franka_')}_{reason}"] += 1
        self.get_logger().warning(f"dropped a {topic} message ({reason}): {detail}", throttle_duration_sec=5.0)

    def _robot_state_stamp(self, msg, topic: str) -> int:
        """The header stamp of a robot-state message; MessageError (FUTURE) when it is too far ahead."""
        stamp = stamp_to_ns(msg.header.stamp)
        rosmsg.check_not_future(stamp, now_ns(self), self.max_future_ns, f"a {topic} message")
        return stamp

    def on_pose(self, msg) -> None:
        try:
            stamp = self._robot_state_stamp(msg, TOPIC_EE_POSE)
            pose = rosmsg.pose_from_msg(msg, self.lab.base_frame)
        except rosmsg.MessageError as err:
            return self.drop(TOPIC_EE_POSE, err.reason, str(err))
        with self._lock:
            self._poses.add(stamp, pose)

    def on_joints(self, msg) -> None:
        try:
            stamp = self._robot_state_stamp(msg, TOPIC_JOINT_STATES)
            width = rosmsg.gripper_width_from_joint_state(msg)
        except rosmsg.MessageError as err:
            return self.drop(TOPIC_JOINT_STATES, err.reason, str(err))
        if width is None:  # an arm-only publisher: the gripper's state comes in another message
            return
        with self._lock:
            self._widths.add(stamp, width)

    def on_diagnostics(self, msg) -> None:
        try:
            entries = rosmsg.diagnostic_entries(msg)
        except rosmsg.MessageError as err:
            return self.drop(TOPIC_DIAGNOSTICS, err.reason, str(err))
        for entry in entries:
            if entry.name.startswith("voxel"):
                self._voxel_error = entry.message if entry.level >= rosmsg.ERROR else ""

    def on_episode(self, msg) -> None:
        try:
            episode = json.loads(msg.data)
            episode = {"seed": int(episode["seed"]), "start_ns": int(episode["start_ns"])}
        except (ValueError, TypeError, KeyError) as err:
            self.get_logger().warning(f"ignoring a malformed {TOPIC_POLICY_EPISODE} message {msg.data!r}: {err}")
            return
        with self._cycle_lock:
            self._episode = episode
        self.get_logger().info(
            f"episode {episode['seed']} announced: it begins at the first observation from {episode['start_ns']}"
        )

    # --- the operator's gate -------------------------------------------------------------
    def set_paused(self, reason: str) -> None:
        if reason != self._paused:
            self._paused = reason
            if reason:  # the operator has the arm: the next chunk starts afresh
                self.doubt.reset()
                if self.chunking is not None:
                    self.chunking.reset()
            self.get_logger().info(f"policy paused: {reason}" if reason else "policy running")
            self.publish_state()

    def publish_state(self) -> None:
        self.pub_state.publish(String(data=f"paused {self._paused}" if self._paused else "running"))

    def on_enable(self, request, response):
        self.set_paused("" if request.data else "by the operator")
        response.success, response.message = True, "running" if not self._paused else "paused"
        return response

    def on_teleop_active(self, msg) -> None:
        if msg.data and not self._paused:  # never resumes on its own: the operator enables again
            self.set_paused("teleop takeover")

    # --- the 5 Hz cycle ------------------------------------------------------------------
    def skip(self, reason: str, detail: str = "", stamp: int | None = None, counted: bool = True) -> None:
        """Count a skip (``skipped_<reason>``) and warn of its ``detail``; with the observation's ``stamp``,
        announce on /policy/skipped that it gets no chunk. No ``detail``: nothing to fix, no warning (paused,
        or the last chunk still executing). ``counted=False``: a failure, which ``failures`` counts."""
        if counted:
            self.skipped[reason] += 1
        if detail:
            self.get_logger().warning(f"skipping a cycle: {detail}", throttle_duration_sec=2.0)
        if stamp is not None:
            self.pub_skipped.publish(String(data=json.dumps({"stamp_ns": int(stamp), "reason": reason})))

    def watch_observations(self) -> None:
        msg = self._voxels
        if msg is None:
            return self.skip("no_observation", f"no {TOPIC_VOXELS} received yet")
        age = now_ns(self) - stamp_to_ns(msg.header.stamp)
        if age > self.max_obs_age_ns:
            self.skip(
                "stale_observation",
                f"newest voxel grid is {age / 1e6:.0f} ms old "
                f"(limit {self.max_obs_age_ns / 1e6:.0f} ms): a camera or the voxel node is down",
            )

    def start_cycle(self) -> None:
        """Hand the newest unused observation to the worker if it is idle and the inputs are fresh."""
        with self._cycle_lock:
            msg = self._voxels
            if self._busy or msg is None:
                return
            stamp = stamp_to_ns(msg.header.stamp)
            if stamp == self._last_obs_stamp:
                return  # answered already
            self._last_obs_stamp = stamp  # whatever happens next, this observation is used up
            if self._episode is not None and stamp >= self._episode["start_ns"]:  # the episode's first
                self.sizing.answers.restart()
                self.seeds.start_episode(self._episode["seed"])
                if self.chunking is not None:
                    self.chunking.reset()
                self.doubt.reset()
                self._episode = None
            if self._paused:
                return self.skip("paused", stamp=stamp)
            with self._lock:
                self.sizing.follow_latency()
            if not self.sizing.answers.due(stamp):
                return self.skip("executing", stamp=stamp)  # the last chunk still runs: the schedule, no warning
            age = now_ns(self) - stamp
            if age > self.max_obs_age_ns:
                return self.skip(
                    "stale_observation",
                    f"a voxel grid {age / 1e6:.0f} ms old arrived (limit {self.max_obs_age_ns / 1e6:.0f} ms)",
                    stamp,
                )
            if self._voxel_error:
                return self.skip("voxel_error", f"voxel node reports: {self._voxel_error}", stamp)
            with self._lock:
                pose = self._poses.nearest(stamp, self.max_state_offset_ns)
                width = self._widths.nearest(stamp, self.max_state_offset_ns)
            if pose is None or width is None:  # no guessed state: training would have dropped this step too
                missing = TOPIC_EE_POSE if pose is None else f"gripper width on {TOPIC_JOINT_STATES}"
                return self.skip(
                    "no_robot_state",
                    f"no {missing} within {self.max_state_offset_ns / 1e6:.0f} ms of the observation",
                    stamp,
                )
            self._busy = True
            self.sizing.answers.answer(stamp)
            self.obs_age_s.append(age / 1e9)
            self.worker.submit(self.infer, self._grid, stamp, pose, float(width), self.seeds.next())

    def infer(self, grid, stamp: int, pose, width: float, seed: int) -> None:
        try:
            t0 = time.perf_counter()
            ee = ee_input(pose, width)
            guide = None
            if self.chunking is not None:
                self.chunking.delay_steps = RealTimeChunking.delay_for(self.sizing.latency_s(), self.sizing.dt_ns / 1e9)
                guide = self.chunking.guide(stamp, ee)
            samples = self.policy.predict_samples(grid, ee, self.doubt_samples, seed=seed, guide=guide)
            actions = samples[0]
            if self.chunking is not None:
                self.chunking.remember(stamp, actions)
            doubt = self.doubt.update(stamp, samples)
            inference = time.perf_counter() - t0
            self.pub_doubt.publish(rosmsg.doubt_msg(self.factory, doubt))
            alarm = "" if self.gate is None else self.gate.alarm(doubt)
            if alarm and not self._paused:  # hold the arm (no more chunks) and ask the operator for help
                with self._lock:
                    self.alarms += 1
                    self.last_doubt = doubt
                self.get_logger().warning(f"policy {HELP_REASON}: {alarm}")
                self.set_paused(f"{HELP_REASON}: {alarm}")
                return self.skip("doubt", stamp=stamp)
            with self._lock:  # this chunk's own latency (it is published next) sizes it for the next one
                self.sizing.record_latency(
                    (now_ns(self) - stamp) / 1e9
                )  # and the next answer's k, which this chunk must outlast
                steps = self.sizing.publish_steps()
            chunk = chunk_from_actions(actions[:steps], stamp, self.sizing.dt_ns)
            if self._paused:  # paused while it ran: the operator has the arm now
                return self.skip("paused", stamp=stamp)
            self.pub_chunk.publish(chunk_to_msg(chunk, self.factory, self.lab.base_frame))
            with self._lock:  # the diagnostics read both as a pair
                self.inference_s.append(inference)
                self.obs_to_cmd_s.append((now_ns(self) - stamp) / 1e9)
                self.published += 1
                self.last_publish_steps = steps
                self.last_doubt = doubt
        except Exception as err:  # noqa: BLE001 - bad input or a bad prediction: skip it, say why, keep serving
            self.failures += 1
            self.get_logger().error(f"inference failed: {type(err).__name__}: {err}", throttle_duration_sec=2.0)
            self.skip("failure", stamp=stamp, counted=False)
        finally:
            with self._cycle_lock:
                self._busy = False
        self.start_cycle()  # an observation that came in meanwhile

    def publish_diagnostics(self) -> None:
        def last_ms(values):
            return round(values[-1] * 1000, 1) if values else -1.0

        with self._lock:
            inference, obs_to_cmd = last_ms(self.inference_s), last_ms(self.obs_to_cmd_s)
            p50, p95 = percentiles_ms(self.obs_to_cmd_s)
            latency = self.sizing.latency.value_s
            source = self.sizing.latency.source
            doubt = self.last_doubt
        values = {
            "inference_ms": inference,
            "observation_age_ms": last_ms(self.obs_age_s),
            "obs_to_cmd_ms": obs_to_cmd,
            "obs_to_cmd_p50_ms": -1.0 if p50 is None else p50,
            "obs_to_cmd_p95_ms": -1.0 if p95 is None else p95,
            "skipped_cycles": sum(self.skipped.values()),
            "published_chunks": self.published,
            "failures": self.failures,
            "state": f"paused {self._paused}" if self._paused else "running",
            **{f"skipped_{k}": v for k, v in self.skipped.items()},
            **{f"dropped_{k}": v for k, v in self.dropped.items()},
        }
        values.update(
            {
                "latency_s": source,
                "latency_estimate_ms": -1.0 if latency is None else round(latency * 1000, 1),
                "latency_bridged_max_ms": round(self.sizing.max_bridged_s * 1000, 1),
                "publish_steps": self.last_publish_steps,
                "execute_steps": self.sizing.answers.steps,
                # the newest published chunk's doubt (NaN: not computed for it; -1: no chunk yet)
                "doubt_signal": self.doubt.signal,
                "doubt_samples": self.doubt_samples,
                "doubt_m": -1.0 if doubt is None else round(doubt.value, 5),
                "doubt_disagreement_m": -1.0 if doubt is None else round(doubt.disagreement_m, 5),
                "doubt_spread_m": -1.0 if doubt is None else round(doubt.spread_m, 5),
                "doubt_gate": "on" if self.gate is not None else "off",
                "doubt_threshold_m": -1.0 if self.gate is None else round(self.gate.threshold_m, 5),
                "doubt_alarms": self.alarms,
            }
        )
        stale = self.skipped["stale_observation"] + self.skipped["no_observation"]
        level = rosmsg.WARN if (self.failures or stale) and not self.obs_to_cmd_s else rosmsg.OK
        message = f"{self.published} chunks published"
        if not self.sizing.fixed_steps and latency is not None and latency > self.sizing.max_bridged_s + 1e-9:
            level = max(level, rosmsg.WARN)
            message += (
                f"; latency {latency * 1000:.0f} ms exceeds the {self.sizing.max_bridged_s * 1000:.0f} ms the "
                f"chunks can bridge (execute_steps {self.sizing.answers.steps}): the arm stands still at each "
                "chunk boundary" + ("" if self.sizing.adaptive_steps else "; a lower execute_steps (or 0) bridges more")
            )
        if self._paused:
            message = f"paused ({self._paused}), no chunks; {message}"
            if self._paused.startswith(HELP_REASON):  # the arm holds until the operator takes over or enables
                level = max(level, rosmsg.WARN)
        self.pub_diag.publish(
            rosmsg.diagnostic_array(self.factory, now_ns(self), NODE_NAME, self.policy.name, level, message, values)
        )

    def shutdown(self) -> None:
        self.worker.shutdown(wait=True, cancel_futures=True)


# the errors that end a start-up with a one-line message (exit 1), not a traceback
STARTUP_ERRORS = (CheckpointError, ConfigError, ValueError)


def main(args=None) -> int:
    return run_node(NODE_NAME, USAGE, PolicyNode, STARTUP_ERRORS, args)


if __name__ == "__main__":
    sys.exit(main())
