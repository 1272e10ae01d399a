"""teleop_node: SpaceMouse (direct HID or the spacenav driver's /spacenav/joy) -> /franka/command_chunk.

Wiring: /franka/ee_pose + /franka/joint_states (measured state) and the input source feed
``equidiff_core.lab.teleop.TeleopIntegrator`` at ``rate_hz``; while the operator is active it
publishes one-point chunks at ``publish_hz`` on /franka/command_chunk, exactly like the
policy, so the franka node's safety and scheduling apply to human commands too. It says on
/teleop/active (std_msgs/Bool, latched) when the operator takes over (the first input beyond
the deadzone) and when they let go again (``resync_after_s`` without input): a running policy
pauses on the first, and the recorder marks both in the episode. After
``resync_after_s`` without input the target re-starts from the measured pose (the policy or
a script may have moved the arm meanwhile), and nothing is published while idle, so teleop
never fights the policy.

A /franka/ee_pose or /franka/joint_states message that ``wire.rosmsg`` refuses (another frame than
the base frame, NaN / inf, a non-unit quaternion; names and positions that disagree, a name
twice, a gripper width outside the hand's stroke) is dropped, logged (throttled) and counted on
/diagnostics (``teleop_node``: ``dropped_<topic>_<reason>``, ``last_drop``; WARN once it dropped
one); the target keeps following the last good state.

Freshness: a Joy message counts from its header stamp (the driver stamps each device event;
the receive time if that is earlier, or if the message is unstamped), a direct SpaceMouse from
its last HID report; input older than ``input_timeout_s`` is no input, so the target holds.

Parameters: ``PARAMETERS`` below, each field of ``TeleopConfig`` and ``resync_after_s`` (``--help``,
``ros2 param describe``, docs/parameters.md); config/data.yaml sets them.
"""

from __future__ import annotations

import collections
import dataclasses
import sys

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import JointState, Joy
from std_msgs.msg import Bool
from trajectory_msgs.msg import MultiDOFJointTrajectory

from equidiff_core.config import Bounds
from equidiff_core.lab.teleop import (
    SpaceMouseSource,
    TeleopConfig,
    TeleopError,
    TeleopInput,
    TeleopIntegrator,
    is_fresh,
)
from equidiff_core.wire import rosmsg
from equidiff_core.wire.chunk import chunk_to_msg
from equidiff_core.wire.rosmsg import (
    NS_PER_S,
    MessageError,
    RclpyFactory,
    gripper_width_from_joint_state,
    pose_from_msg,
)
from equidiff_core.wire.topics import (
    TOPIC_COMMAND_CHUNK,
    TOPIC_DIAGNOSTICS,
    TOPIC_EE_POSE,
    TOPIC_JOINT_STATES,
    TOPIC_JOY,
    TOPIC_TELEOP_ACTIVE,
)
from equidiff_ros.common import (
    LATCHED_QOS,
    RELIABLE_QOS,
    SENSOR_QOS,
    declare_config,
    declare_lab_config,
    now_ns,
    wait_for_clock,
)
from equidiff_ros.parameters import LAB_CONFIG, NodeParameter, NodeParameters, config_parameters, parameters_help
from equidiff_ros.runner import run_node

PARAMETERS = (
    NodeParameters(LAB_CONFIG)
    + config_parameters(TeleopConfig)
    + NodeParameters(
        NodeParameter(
            "resync_after_s",
            1.0,
            "Idle this long, the operator has let go (/teleop/active false) and the target restarts from the "
            "measured pose",
            Bounds("s", gt=0, le=60.0),
        )
    )
)

USAGE = (
    __doc__
    + parameters_help(PARAMETERS)
    + """
usage: teleop_node [--ros-args -p source:=joy|spacemouse -p gripper_mode:=buttons|toggle|hold ...]
"""
)


class TeleopNode(Node):
    def __init__(self, node_name: str = "teleop_node"):
        super().__init__(node_name)
        wait_for_clock(self)  # simulated time (the twin): nothing is timed before /clock
        self.lab = declare_lab_config(self)
        self.cfg = declare_config(self, TeleopConfig)
        self.resync_after_s = PARAMETERS.declare(self, "resync_after_s")
        self.factory = RclpyFactory()
        self.teleop = TeleopIntegrator(self.cfg, self.lab.workspace)
        self.measured = None  # latest /franka/ee_pose (4x4)
        self.width_measured: float | None = None
        self.input = None  # the newest TeleopInput, stamped when the device reported it
        self.warned_unstamped = False
        self.last_active_ns = 0
        self.last_publish_ns = 0
        self.last_tick_ns: int | None = None
        self.dropped: collections.Counter[str] = collections.Counter()  # by ``<topic>_<reason>``
        self.last_drop = ""

        self.pub = self.create_publisher(MultiDOFJointTrajectory, TOPIC_COMMAND_CHUNK, RELIABLE_QOS)
        self.pub_active = self.create_publisher(Bool, TOPIC_TELEOP_ACTIVE, LATCHED_QOS)
        self.taken_over = False
        self.pub_active.publish(Bool(data=False))
        self.create_subscription(PoseStamped, TOPIC_EE_POSE, self.on_pose, SENSOR_QOS)
        self.create_subscription(JointState, TOPIC_JOINT_STATES, self.on_joints, SENSOR_QOS)
        self.device = None
        if self.cfg.source == "spacemouse":
            self.device = SpaceMouseSource(self.cfg.device)
            self.device.connect()  # TeleopError names what was looked for
        else:
            self.create_subscription(Joy, TOPIC_JOY, self.on_joy, SENSOR_QOS)
        self.create_timer(1.0 / self.cfg.rate_hz, self.tick)
        self.pub_diag = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, RELIABLE_QOS)
        self.create_timer(1.0, self.publish_diagnostics)
        self.get_logger().info(
            f"teleop from {self.cfg.source} ({TOPIC_JOY if self.device is None else 'HID'}), "
            f"{self.cfg.translation_frame}-frame translation, gripper {self.cfg.gripper_mode}"
        )

    def drop(self, topic: str, err: MessageError) -> None:
        """Count (``dropped_<topic>_<reason>``) and say (throttled) that a robot-state message was unusable."""
        self.dropped[f"{topic.strip('/').replace('/', '_').removeprefix('franka_')}_{err.reason}"] += 1
        self.last_drop = f"{topic}: {err.reason}: {err}"
        self.get_logger().warning(f"dropped a {topic} message ({err.reason}): {err}", throttle_duration_sec=2.0)

    def on_pose(self, msg):
        try:
            pose = pose_from_msg(msg, self.lab.base_frame)
        except MessageError as err:
            return self.drop(TOPIC_EE_POSE, err)
        self.measured = pose
        if self.teleop.ready:
            self.teleop.observe(pose)

    def on_joints(self, msg):
        try:
            width = gripper_width_from_joint_state(msg)
        except MessageError as err:
            return self.drop(TOPIC_JOINT_STATES, err)
        if width is not None:
            self.width_measured = width

    def publish_diagnostics(self) -> None:
        values = {f"dropped_{key}": count for key, count in sorted(self.dropped.items())}
        values.update(active=self.taken_over, last_drop=self.last_drop)
        level = rosmsg.WARN if self.dropped else rosmsg.OK
        text = "operator active" if self.taken_over else "idle"
        if self.dropped:
            text += f"; {sum(self.dropped.values())} unusable robot-state message(s) dropped"
        self.pub_diag.publish(
            rosmsg.diagnostic_array(self.factory, now_ns(self), self.get_name(), "", level, text, values)
        )

    def on_joy(self, msg):
        try:
            inp = TeleopInput.from_joy(msg)
        except TeleopError as err:
            self.get_logger().warn(f"ignoring {TOPIC_JOY}: {err}", throttle_duration_sec=2.0)
            return
        received = now_ns(self)
        if inp.stamp_ns <= 0:
            if not self.warned_unstamped:
                self.warned_unstamped = True
                self.get_logger().warn(
                    f"{TOPIC_JOY} messages carry no header stamp: their age is "
                    "counted from receipt, so a stalled driver is noticed late"
                )
            stamp = received
        else:
            # Messages delayed in transport are as old as their stamp; a stamp from the future
            # (another machine's clock) cannot make them younger than their receipt.
            stamp = min(inp.stamp_ns, received)
            if received - inp.stamp_ns > 10 * NS_PER_S:
                self.get_logger().warn(
                    f"{TOPIC_JOY} stamps are {(received - inp.stamp_ns) / 1e9:.1f} s behind this node's "
                    "clock (use_sim_time on one side only?): input treated as stale, teleop holds",
                    throttle_duration_sec=5.0,
                )
        self.input = dataclasses.replace(inp, stamp_ns=stamp)

    def tick(self):
        now = now_ns(self)
        dt = 0.0 if self.last_tick_ns is None else (now - self.last_tick_ns) / 1e9
        self.last_tick_ns = now
        if self.device is not None:
            try:
                self.input = self.device.read(now)
            except Exception as err:  # noqa: BLE001 - unplugged mid-session: hold still, say why
                self.get_logger().error(f"SpaceMouse read failed: {err}", throttle_duration_sec=2.0)
                self.input = None
        inp = self.input if is_fresh(self.input, now, self.cfg.input_timeout_s) else None
        if not self.teleop.engaged(inp):
            if self.teleop.ready:  # keep button edges in sync while idle
                self.teleop.step(None, dt)
            if self.taken_over and (now - self.last_active_ns) / 1e9 > self.resync_after_s:
                self.set_taken_over(False)
            return
        if self.measured is None:
            self.get_logger().warn(
                f"operator input but no {TOPIC_EE_POSE} yet: not commanding", throttle_duration_sec=2.0
            )
            return
        if not self.taken_over:
            self.set_taken_over(True)
        idle_s = (now - self.last_active_ns) / 1e9
        if not self.teleop.ready or idle_s > self.resync_after_s:
            self.teleop.reset(self.measured, self.width_measured)
            dt = 0.0
        self.last_active_ns = now
        try:
            self.teleop.step(inp, min(dt, 0.1))  # a long stall must not turn into a jump
        except TeleopError as err:
            self.get_logger().warn(str(err), throttle_duration_sec=2.0)
            return
        if (now - self.last_publish_ns) >= 1e9 / self.cfg.publish_hz * 0.95:
            self.last_publish_ns = now
            self.pub.publish(chunk_to_msg(self.teleop.chunk(now), self.factory, self.lab.base_frame))

    def set_taken_over(self, active: bool):
        self.taken_over = active
        self.pub_active.publish(Bool(data=active))
        self.get_logger().info("operator took over (SpaceMouse)" if active else "operator let go")

    def destroy_node(self):
        if self.device is not None:
            self.device.disconnect()
        return super().destroy_node()


# the errors that end a start-up with a one-line message (exit 1), not a traceback
STARTUP_ERRORS = (TeleopError,)


def main(args=None) -> int:
    return run_node("teleop_node", USAGE, TeleopNode, STARTUP_ERRORS, args)


if __name__ == "__main__":
    sys.exit(main())
