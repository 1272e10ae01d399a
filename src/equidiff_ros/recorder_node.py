"""recorder_node: records demonstration episodes to rosbag2 MCAP directories, one per episode.

Wiring: raw (serialised CDR) subscriptions on every recorded topic are written untouched
into the bag by ``equidiff_core.data.recording.EpisodeWriter`` at their receive time; the
episode starts and stops on

* services (std_srvs/Trigger): /recorder/start, /recorder/stop (keep, success),
  /recorder/stop_failure (keep, success=false), /recorder/discard;
* the /recorder/command topic (std_msgs/String): ``start [task]``,
  ``stop [success|failure] [seed=N] [operator=NAME] [extra.KEY=VALUE...] [notes...]``, ``discard``;
* the keyboard when ``keyboard:=true`` and stdin is a terminal: s = start, k = keep
  (success), f = keep (failure), d = discard, then Enter.

Teleop takeovers (/teleop/active true..false) during an episode are in the bag and listed in
its metadata (``extra.interventions``: start-end seconds from the episode start,
``extra.intervention_count``).

While recording, the messages a training set is built from are decoded first with the
decoders their live readers use: a ``/voxels`` message that is not lab.yaml's grid
(``wire.pointcloud.check_voxel_msg``), a ``/franka/command_chunk`` that does not decode
(``wire.chunk.chunk_from_msg``, base frame), a ``/franka/ee_pose`` that is not a pose in the base
frame (``wire.rosmsg.pose_from_msg``: NaN / inf, a non-unit quaternion) or a ``/franka/joint_states``
that ``wire.rosmsg.gripper_width_from_joint_state`` refuses (names and positions that disagree, a name
twice, NaN / inf, a width outside the hand's stroke) is dropped from the bag, counted on /diagnostics
(``recorder_node``: ``dropped_<topic>_<reason>``, ``last_drop``) and logged (throttled); one
bad message would otherwise cost the whole episode when the dataset is built. Every other
topic is written untouched.

State is published latched on /recorder/status (std_msgs/String: ``idle`` or ``recording
<path>``). Episodes go to ``output_dir/<task>_NNNN`` and are never overwritten; free disk is
checked before each start and while recording (stop-and-keep when low). A killed recorder's
bag is recovered with ``equidiff bags repair``.

Parameters: ``PARAMETERS`` below, each field of ``RecordingConfig`` and the episode's metadata
(``--help``, ``ros2 param describe``, docs/parameters.md); config/data.yaml sets them.
"""

from __future__ import annotations

import collections
import sys
import threading

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from std_msgs.msg import Bool, String
from std_srvs.srv import Trigger

from equidiff_core.data.bags import EpisodeMeta
from equidiff_core.data.recording import (
    EpisodeWriter,
    InterventionLog,
    RecordingConfig,
    RecordingError,
    next_episode_path,
    recorded_topics,
)
from equidiff_core.wire import rosmsg, topics
from equidiff_core.wire.chunk import ChunkError, chunk_from_msg
from equidiff_core.wire.pointcloud import CloudError, VoxelGridSpec, check_voxel_msg
from equidiff_core.wire.rosmsg import MessageError, RclpyFactory, gripper_width_from_joint_state, pose_from_msg
from equidiff_core.wire.topics import (
    TOPIC_COMMAND_CHUNK,
    TOPIC_DIAGNOSTICS,
    TOPIC_EE_POSE,
    TOPIC_JOINT_STATES,
    TOPIC_RECORDER_COMMAND,
    TOPIC_TELEOP_ACTIVE,
    TOPIC_VOXELS,
)
from equidiff_ros.common import LATCHED_QOS, RELIABLE_QOS, declare_config, declare_lab_config, now_ns, wait_for_clock
from equidiff_ros.parameters import LAB_CONFIG, NodeParameter, NodeParameters, config_parameters, parameters_help
from equidiff_ros.runner import run_node

# The contract's profiles, but with deep queues: a recorder must not drop 100 Hz state
# while a chunk is being flushed to disk (best effort still matches either publisher kind).
RECORD_SENSOR_QOS = QoSProfile(
    depth=200,
    reliability=ReliabilityPolicy.BEST_EFFORT,
    durability=DurabilityPolicy.VOLATILE,
    history=HistoryPolicy.KEEP_LAST,
)
RECORD_RELIABLE_QOS = QoSProfile(
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
    history=HistoryPolicy.KEEP_LAST,
)
RECORD_CLOUD_QOS = QoSProfile(
    depth=10,
    reliability=ReliabilityPolicy.BEST_EFFORT,  # ~5 MB each
    durability=DurabilityPolicy.VOLATILE,
    history=HistoryPolicy.KEEP_LAST,
)
# Colour images come from camera_node with the clouds' QoS (sensor data, or reliable in the
# lockstep twin): best effort matches both; tens of kB each, so a deeper queue is cheap.
RECORD_IMAGE_QOS = QoSProfile(
    depth=30,
    reliability=ReliabilityPolicy.BEST_EFFORT,
    durability=DurabilityPolicy.VOLATILE,
    history=HistoryPolicy.KEEP_LAST,
)

PARAMETERS = (
    NodeParameters(LAB_CONFIG)
    + config_parameters(RecordingConfig)
    + NodeParameters(
        NodeParameter("task", "episode", "Task name: the episode directory's prefix and its metadata"),
        NodeParameter("operator", "", "Operator's name, in each episode's metadata"),
        NodeParameter("notes", "", "Notes, in each episode's metadata"),
        NodeParameter(
            "keyboard", False, "Keys on the terminal: s start, k keep (success), f keep (failure), d discard"
        ),
        NodeParameter("autostart", False, "Start an episode as soon as the node is up"),
    )
)

USAGE = (
    __doc__
    + parameters_help(PARAMETERS)
    + """
usage: recorder_node [--ros-args -p output_dir:=DIR -p task:=NAME -p operator:=NAME -p record_images:=true
                      -p record_clouds:=false ...]
"""
)

BEST_EFFORT_TOPICS = (topics.TOPIC_EE_POSE, topics.TOPIC_JOINT_STATES, topics.TOPIC_JOY)  # match any publisher


def parse_command(text: str) -> tuple[str, dict]:
    """'/recorder/command' text -> (action, metadata updates); ValueError if unknown."""
    words = text.strip().split()
    if not words:
        raise ValueError("empty command")
    action, rest = words[0].lower(), words[1:]
    if action == "start":
        return "start", ({"task": rest[0]} if rest else {})
    if action == "stop":
        updates: dict = {"success": True}
        if rest and rest[0].lower() in ("success", "ok", "true"):
            rest = rest[1:]
        elif rest and rest[0].lower() in ("failure", "fail", "false"):
            updates["success"] = False
            rest = rest[1:]
        notes = []
        for word in rest:  # key=value words set metadata fields (seed=3 operator=ana); the rest are notes
            key, sep, value = word.partition("=")
            if sep and key == "seed" and value.lstrip("-").isdigit():
                updates["seed"] = int(value)
            elif sep and key in ("operator", "task"):
                updates[key] = value
            elif sep and key.startswith("extra.") and len(key) > len("extra."):
                updates.setdefault("extra", {})[key.removeprefix("extra.")] = value
            else:
                notes.append(word)
        if notes:
            updates["notes"] = " ".join(notes)
        return "stop", updates
    if action == "discard":
        return "discard", {}
    raise ValueError(f"unknown recorder command {words[0]!r} (start, stop [success|failure] [notes], discard)")


class RecorderNode(Node):
    def __init__(self, node_name: str = "recorder_node"):
        super().__init__(node_name)
        wait_for_clock(self)  # simulated time (the twin): nothing is timed before /clock
        self.lab = declare_lab_config(self)
        self.cfg = declare_config(self, RecordingConfig)
        self.task = PARAMETERS.declare(self, "task")
        self.operator = PARAMETERS.declare(self, "operator")
        self.notes = PARAMETERS.declare(self, "notes")
        keyboard = PARAMETERS.declare(self, "keyboard")
        autostart = PARAMETERS.declare(self, "autostart")
        self.factory = RclpyFactory()
        self.lock = threading.Lock()
        self.writer: EpisodeWriter | None = None
        self.interventions: InterventionLog | None = None  # of the episode being recorded
        self.teleop_active = False
        self.topics = recorded_topics(self.lab, self.cfg.record_clouds, self.cfg.record_images)
        grid_spec = VoxelGridSpec.of(self.lab.workspace, self.lab.base_frame)
        # topic -> a check that raises CloudError / ChunkError / MessageError (with a ``reason``) on a
        # message the dataset cannot use
        self.checks = {
            TOPIC_VOXELS: lambda msg: check_voxel_msg(msg, grid_spec),
            TOPIC_COMMAND_CHUNK: lambda msg: chunk_from_msg(msg, self.lab.base_frame),
            TOPIC_EE_POSE: lambda msg: pose_from_msg(msg, self.lab.base_frame),
            TOPIC_JOINT_STATES: gripper_width_from_joint_state,
            topics.TOPIC_POLICY_DOUBT: rosmsg.doubt_from_msg,
        }
        self.dropped: collections.Counter[str] = collections.Counter()
        self.last_drop = ""
        for topic, msgtype in self.topics.items():
            if topics.camera_of_color_topic(topic) is not None:
                qos = RECORD_IMAGE_QOS
            elif topic.startswith(topics.CAMERA_TOPIC_PREFIX):
                qos = RECORD_CLOUD_QOS
            else:
                qos = RECORD_SENSOR_QOS if topic in BEST_EFFORT_TOPICS else RECORD_RELIABLE_QOS
            self.create_subscription(self.factory.cls(msgtype), topic, self._writer_cb(topic, msgtype), qos, raw=True)
        self.status_pub = self.create_publisher(String, topics.TOPIC_RECORDER_STATUS, LATCHED_QOS)
        self.create_subscription(Bool, TOPIC_TELEOP_ACTIVE, self.on_teleop_active, LATCHED_QOS)
        self.create_subscription(String, TOPIC_RECORDER_COMMAND, self.on_command, RELIABLE_QOS)
        self.create_service(Trigger, topics.SERVICE_RECORDER_START, self._service(self.start))
        self.create_service(Trigger, topics.SERVICE_RECORDER_STOP, self._service(lambda: self.stop(success=True)))
        self.create_service(
            Trigger, topics.SERVICE_RECORDER_STOP_FAILURE, self._service(lambda: self.stop(success=False))
        )
        self.create_service(Trigger, topics.SERVICE_RECORDER_DISCARD, self._service(self.discard))
        self.create_timer(0.5, self.housekeeping)
        self.diag_pub = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, RELIABLE_QOS)
        self.create_timer(1.0, self.publish_diagnostics)
        self.publish_status()
        self.get_logger().info(f"recording {sorted(self.topics)} to {self.cfg.output_dir}/")
        if keyboard:
            self.start_keyboard()
        if autostart:
            self.start()

    # -- episode control -------------------------------------------------------------
    def start(self, **meta_updates) -> str:
        with self.lock:
            if self.writer is not None:
                raise RecordingError(f"already recording {self.writer.path}")
            task = meta_updates.get("task", self.task)
            meta = EpisodeMeta(task=task, operator=self.operator, notes=self.notes)
            path = next_episode_path(self.cfg.output_dir, task)
            writer = EpisodeWriter(path, meta, self.cfg).open()
            for topic, msgtype in self.topics.items():
                writer.add_topic(topic, msgtype, reliable=topic not in BEST_EFFORT_TOPICS)
            start_ns = now_ns(self)
            writer.write_tf_static(self.lab, start_ns)
            self.writer = writer
            self.interventions = InterventionLog(start_ns)
            self.interventions.update(self.teleop_active, start_ns)  # already driving at the start
        self.publish_status()
        self.get_logger().info(f"episode started: {path}")
        return str(path)

    def stop(self, **meta_updates) -> str:
        with self.lock:
            if self.writer is None:
                raise RecordingError("not recording")
            writer, self.writer = self.writer, None
            path = writer.close(**self._with_interventions(writer, meta_updates))
            counts = dict(writer.counts)
        self.publish_status()
        self.get_logger().info(f"episode kept: {path} ({sum(counts.values())} messages: {counts})")
        return str(path)

    def discard(self) -> str:
        with self.lock:
            if self.writer is None:
                raise RecordingError("not recording")
            writer, self.writer = self.writer, None
            writer.discard()
        self.publish_status()
        self.get_logger().info(f"episode discarded: {writer.path}")
        return f"discarded {writer.path}"

    def _with_interventions(self, writer, meta_updates: dict) -> dict:
        log, self.interventions = self.interventions, None
        if log is None:
            return meta_updates
        extra = {**writer.meta.extra, **meta_updates.get("extra", {}), **log.metadata(now_ns(self))}
        return {**meta_updates, "extra": extra}

    def on_teleop_active(self, msg):
        with self.lock:
            self.teleop_active = bool(msg.data)
            if self.interventions is not None:
                self.interventions.update(self.teleop_active, now_ns(self))

    # -- plumbing --------------------------------------------------------------------
    def _writer_cb(self, topic: str, msgtype: str):
        check = self.checks.get(topic)
        msg_class = self.factory.cls(msgtype)

        def cb(data: bytes):
            if self.writer is None:
                return
            if check is not None:
                try:
                    check(deserialize_message(data, msg_class))
                except (CloudError, ChunkError, MessageError) as err:
                    return self._drop(topic, str(err.reason), str(err))
            with self.lock:
                if self.writer is not None:
                    self.writer.write_raw(topic, now_ns(self), data, msgtype)

        return cb

    def _drop(self, topic: str, reason: str, detail: str) -> None:
        self.dropped[f"{topic.strip('/').replace('/', '_')}_{reason}"] += 1
        self.last_drop = f"{topic}: {reason}: {detail}"
        self.get_logger().warning(f"not recording a {topic} message ({reason}): {detail}", throttle_duration_sec=2.0)

    def publish_diagnostics(self) -> None:
        writer = self.writer
        values = {f"dropped_{key}": count for key, count in sorted(self.dropped.items())}
        values.update(recording=writer is not None, last_drop=self.last_drop)
        level = rosmsg.WARN if self.dropped else rosmsg.OK
        text = "idle" if writer is None else f"recording {writer.path}"
        if self.dropped:
            text += f"; {sum(self.dropped.values())} unusable message(s) not recorded"
        self.diag_pub.publish(
            rosmsg.diagnostic_array(self.factory, now_ns(self), self.get_name(), "", level, text, values)
        )

    def _service(self, action):
        def handler(request, response):
            try:
                response.message = action()
                response.success = True
            except RecordingError as err:
                response.success, response.message = False, str(err)
                self.get_logger().error(str(err))
            return response

        return handler

    def on_command(self, msg):
        try:
            action, updates = parse_command(msg.data)
            if action == "start":
                self.start(**updates)
            elif action == "stop":
                self.stop(**updates)
            else:
                self.discard()
        except (ValueError, RecordingError) as err:
            self.get_logger().error(f"{TOPIC_RECORDER_COMMAND}: {err}")

    def publish_status(self):
        writer = self.writer
        self.status_pub.publish(String(data="idle" if writer is None else f"recording {writer.path}"))

    def housekeeping(self):
        with self.lock:
            writer = self.writer
            if writer is not None:
                writer.flush_if_old()  # bounds what a SIGKILL can lose
        if writer is not None and writer.low_disk:
            self.get_logger().error("disk nearly full: stopping and keeping the episode")
            self.stop(success=None, notes="stopped: disk nearly full")

    def start_keyboard(self):
        if not sys.stdin or not sys.stdin.isatty():
            self.get_logger().warn(
                f"keyboard:=true but stdin is not a terminal; use services or {TOPIC_RECORDER_COMMAND}"
            )
            return
        print("recorder keys: s=start  k=keep (success)  f=keep (failure)  d=discard  [Enter]", flush=True)

        def loop():
            actions = {
                "s": self.start,
                "k": lambda: self.stop(success=True),
                "f": lambda: self.stop(success=False),
                "d": self.discard,
            }
            for line in sys.stdin:
                key = line.strip()[:1].lower()
                if key in actions:
                    try:
                        print(actions[key](), flush=True)
                    except RecordingError as err:
                        print(f"recorder: {err}", flush=True)

        threading.Thread(target=loop, daemon=True, name="recorder-keyboard").start()

    def shutdown(self):
        with self.lock:
            writer, self.writer = self.writer, None
        if writer is not None:  # keep what was recorded; the operator judges it later
            notes = (writer.meta.notes + " [recorder shut down mid-episode]").strip()
            writer.close(**self._with_interventions(writer, {"success": None, "notes": notes}))
            self.get_logger().info(f"episode kept on shutdown: {writer.path}")


# the errors that end a start-up with a one-line message (exit 1), not a traceback
STARTUP_ERRORS = (RecordingError,)


def main(args=None) -> int:
    return run_node("recorder_node", USAGE, RecorderNode, STARTUP_ERRORS, args)


if __name__ == "__main__":
    sys.exit(main())
