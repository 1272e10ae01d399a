"""franka_node: the arm. Executes /franka/command_chunk safely with franky; publishes the robot state.

Wiring:
  /franka/command_chunk (MultiDOFJointTrajectory, decoded only by ``wire.chunk.chunk_from_msg``)
      -> ``control.Controller.submit`` (drop past steps, safety checks, replace the trajectory)
  ``Controller`` thread at ``control_hz`` -> ``robots.Robot`` (franky CartesianImpedanceTracker,
      or the dry run) ; watchdog, workspace clip, speed limits, error recovery live there
  timer at ``state_hz`` (>= 100 Hz) -> /franka/ee_pose, /franka/joint_states, /franka/executed_target,
      /tf (base -> fr3_hand_tcp, where tf2_msgs is installed: RViz, easy_handeye2)
  timer at 1 Hz -> /diagnostics (``franka_node``: rejected chunks, stops, watchdog holds, ...)
  timer at 20 Hz -> /franka/status (latched JSON ``Controller.status()``, published on change:
      moving | holding | homing | awaiting_ack | faulted, with the reason and the last fault;
      ``control.state_machine.STATUS`` names the controller's states so)
  service /franka/acknowledge (Trigger) -> ``Controller.acknowledge``: after a user stop, a reflex,
      a lost connection, a divergence stop or a restart the arm holds and chunks are refused
      until an operator calls it; refused while the user stop is pressed or if recovery fails
  service /franka/home (Trigger) -> ``Controller.go_home``: glide slowly to the configured home pose
      (chunks refused until it arrives); refused while a stop awaits acknowledgement

Every start holds until acknowledged (``require_ack_on_start``, default true; false only where
nothing else could move the arm unexpectedly: the twin's launchers, the dry run): the node does
not move home on its own and refuses chunks, since the policy may still be publishing. An unclean
exit (killed, crashed) leaves its marker file ``<run_dir>/franka_node_<robot_ip>.pid`` behind;
the next franka_node for the same robot names it in its reason, and holds even with the waiver.

Policy and teleop publish the same chunk topic, so both go through the same checks.

Parameters: ``PARAMETERS`` below (``--help``, ``ros2 param describe``, docs/parameters.md).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import ClassVar

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import MultiDOFJointTrajectory

from equidiff_core.config import ConfigError, RobotConfig, default_config_dir
from equidiff_core.control import AcknowledgeRefused, Controller, check_home_inside, load_control_config
from equidiff_core.robots import BACKENDS, RobotError, make_robot
from equidiff_core.wire import rosmsg
from equidiff_core.wire.chunk import ChunkError, chunk_from_msg
from equidiff_core.wire.topics import (
    SERVICE_FRANKA_ACKNOWLEDGE,
    SERVICE_FRANKA_HOME,
    TOPIC_COMMAND_CHUNK,
    TOPIC_DIAGNOSTICS,
    TOPIC_EE_POSE,
    TOPIC_EXECUTED_TARGET,
    TOPIC_FRANKA_STATUS,
    TOPIC_JOINT_STATES,
    TOPIC_TF,
)
from equidiff_ros.common import LATCHED_QOS, RELIABLE_QOS, declare_lab_config, node_clock, now_ns, wait_for_clock
from equidiff_ros.parameters import LAB_CONFIG, NodeParameter, NodeParameters, bounds_of, parameters_help
from equidiff_ros.runner import run_node

NODE_NAME = "franka_node"

PARAMETERS = NodeParameters(
    LAB_CONFIG,
    NodeParameter(
        "control_config",
        "",
        "Path of control.yaml: limits, scheduling, gains",
        default_from="the installed config/control.yaml",
    ),
    NodeParameter("backend", "franky", "The arm: franky (an FR3 or franky-sim) or dryrun", choices=BACKENDS),
    NodeParameter("robot_ip", "", "The robot's address; empty: lab.yaml's robot.ip"),
    NodeParameter("realtime", True, "Real-time control loop: false for franky-sim or a machine without an RT kernel"),
    NodeParameter(
        "home_on_start",
        False,
        "Move home at start; with the start hold only when the TCP is outside the safety box (the acknowledgement "
        "then moves it home)",
        default_from="control.yaml home_on_start",
    ),
    NodeParameter(
        "require_ack_on_start",
        True,
        "Every start holds until /franka/acknowledge; false only where nothing else could move the arm unexpectedly "
        "(the twin's launchers, the dry run)",
        default_from="true; false with backend dryrun",
    ),
    NodeParameter("gripper", True, "Drive the Franka Hand (false: the arm only)"),
    NodeParameter(
        "run_dir",
        "",
        "Directory of the unclean-exit marker franka_node_<robot_ip>.pid; empty: $XDG_RUNTIME_DIR, else the temp dir",
    ),
    NodeParameter(
        "state_hz",
        100.0,
        "Rate of /franka/ee_pose, /franka/joint_states and /tf",
        bounds_of(RobotConfig, "state_hz"),
        default_from="lab.yaml robot.state_hz",
        number=True,
    ),
)

USAGE = (
    __doc__
    + parameters_help(PARAMETERS)
    + """
usage: franka_node [--ros-args -p backend:=franky|dryrun -p robot_ip:=172.16.0.2 -p realtime:=true
                    -p control_config:=config/control.yaml -p lab_config:=config/lab.yaml
                    -p require_ack_on_start:=true]
"""
)


class FrankaNode(Node):
    def __init__(self, node_name: str = NODE_NAME):
        super().__init__(node_name)
        wait_for_clock(self)  # simulated time (the twin): nothing is timed before /clock
        self.lab = declare_lab_config(self)
        param = lambda name: PARAMETERS.declare(self, name)
        control_path = PARAMETERS.declare(self, "control_config", str(default_config_dir() / "control.yaml"))
        backend = param("backend")
        robot_ip = param("robot_ip") or self.lab.robot.ip
        realtime = param("realtime")
        gripper = param("gripper")
        run_dir = param("run_dir") or os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir()
        self.config = load_control_config(Path(control_path))
        check_home_inside(self.config, self.lab.safety_box)  # a home outside the box would be clipped, never reached
        home = PARAMETERS.declare(self, "home_on_start", self.config.home_on_start)
        # the dry run moves nothing, so nothing can resume on its own there
        require_ack = PARAMETERS.declare(self, "require_ack_on_start", backend != "dryrun")
        state_hz = PARAMETERS.declare(self, "state_hz", self.lab.robot.state_hz)
        self.frame = self.lab.base_frame
        self.factory = rosmsg.RclpyFactory()
        self.hardware_id = "dryrun" if backend == "dryrun" else robot_ip

        log = _ros_logger_adapter(self.get_logger())
        kwargs = (
            {}
            if backend == "dryrun"
            else {
                "ip": robot_ip,
                "config": self.config.franky,
                "realtime": realtime,
                "gripper": gripper,
                "safety": self.config.safety,
            }
        )
        # a dry run moves nothing: no marker (and parallel dry runs on one machine never hold each other)
        self.marker = None if backend == "dryrun" else Path(run_dir) / f"franka_node_{self.hardware_id}.pid"
        unclean = "" if self.marker is None else previous_exit_was_unclean(self.marker)
        hold = unclean or (
            "franka_node started: acknowledge (`equidiff lab ack`) before it accepts chunks" if require_ack else ""
        )
        self.robot = make_robot(backend, logger=log, **kwargs)
        self.get_logger().info(f"connecting to the robot ({backend}, {self.hardware_id})")
        self.robot.connect()
        # ticks, stamps, staleness and the watchdog on the node's clock: simulated time in the twin
        self.controller = Controller(
            self.robot,
            self.lab.safety_box,
            dataclasses.replace(self.config, home_on_start=home),
            clock=node_clock(self),
            logger=log,
        )

        self.pub_pose = self.create_publisher(PoseStamped, TOPIC_EE_POSE, RELIABLE_QOS)
        self.pub_joints = self.create_publisher(JointState, TOPIC_JOINT_STATES, RELIABLE_QOS)
        self.pub_target = self.create_publisher(PoseStamped, TOPIC_EXECUTED_TARGET, RELIABLE_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, RELIABLE_QOS)
        self.pub_tf = None  # base -> TCP on /tf for RViz and ROS hand-eye tools, where tf2_msgs exists
        try:
            from tf2_msgs.msg import TFMessage

            self.pub_tf = self.create_publisher(TFMessage, TOPIC_TF, RELIABLE_QOS)
        except ImportError:
            self.get_logger().info(
                "tf2_msgs is not installed: base -> TCP is not published on /tf (/franka/ee_pose carries the same pose)"
            )
        self.pub_status = self.create_publisher(String, TOPIC_FRANKA_STATUS, LATCHED_QOS)
        self._status_sent = None
        try:
            self.controller.start(hold=hold)
        except Exception:
            self.robot.disconnect()
            raise
        if unclean:
            self.controller.record_fault(unclean)
        if self.marker is not None:
            self.marker.write_text(str(os.getpid()))
        self.create_subscription(MultiDOFJointTrajectory, TOPIC_COMMAND_CHUNK, self.on_chunk, RELIABLE_QOS)
        # after a robot error or a divergence stop the arm holds until an operator says go on
        self.create_service(Trigger, SERVICE_FRANKA_ACKNOWLEDGE, self.on_acknowledge)
        self.create_service(Trigger, SERVICE_FRANKA_HOME, self.on_home)
        self.create_timer(1.0 / state_hz, self.publish_state)
        self.create_timer(1.0, self.publish_diagnostics)
        self.create_timer(0.05, self.publish_status)
        self._last_target_stamp = self._last_state_stamp = None
        self.publish_status()
        self.get_logger().info(
            f"streaming at {self.config.control_hz:.0f} Hz, state at {state_hz:.0f} Hz; "
            f"safety box {self.controller.safety.lower.round(3).tolist()} .. "
            f"{self.controller.safety.upper.round(3).tolist()}"
        )

    def on_chunk(self, msg) -> None:
        try:
            chunk = chunk_from_msg(msg, self.frame)
        except ChunkError as err:
            self.controller.record_rejection(err)
            return
        self.controller.submit(chunk)

    def on_acknowledge(self, _request, response):
        try:
            reason = self.controller.acknowledge()
            response.success = True
            response.message = f"acknowledged: {reason}" if reason else "nothing to acknowledge"
        except AcknowledgeRefused as err:
            response.success, response.message = False, f"refused: {err}"
        self.publish_status()
        return response

    def on_home(self, _request, response):
        try:
            seconds = self.controller.go_home()
            response.success = True
            response.message = f"homing to {list(self.config.home_position)} in {seconds:.1f} s"
        except ChunkError as err:
            response.success, response.message = False, f"refused: {err}"
        self.publish_status()
        return response

    def publish_status(self) -> None:
        """/franka/status, latched, whenever it changed (checked at 20 Hz and after each service call)."""
        status = self.controller.status().as_dict()
        if status != self._status_sent:
            self._status_sent = status
            self.pub_status.publish(String(data=json.dumps(status)))

    def publish_state(self) -> None:
        state = self.controller.state
        if state is None or state.stamp_ns == self._last_state_stamp:
            return  # a stopped robot is read at 10 Hz, an unreachable one not at all: no stale repeats
        self._last_state_stamp = state.stamp_ns
        self.pub_pose.publish(rosmsg.pose_stamped(self.factory, state.ee_pose, state.stamp_ns, self.frame))
        self.pub_joints.publish(rosmsg.joint_state(self.factory, state, state.stamp_ns))
        if self.pub_tf is not None:
            self.pub_tf.publish(
                rosmsg.tf_message(self.factory, [(self.frame, rosmsg.TCP_FRAME, state.ee_pose)], state.stamp_ns)
            )
        command = self.controller.last_command
        if command is not None and command.stamp_ns != self._last_target_stamp:
            self._last_target_stamp = command.stamp_ns
            self.pub_target.publish(
                rosmsg.pose_stamped(self.factory, command.target.pose, command.stamp_ns, self.frame)
            )

    def publish_diagnostics(self) -> None:
        stats, status = self.controller.stats, self.controller.status()
        if status.state == "faulted":
            level, text = rosmsg.ERROR, f"faulted (acknowledge again once fixed): {status.reason}"
        elif status.state == "awaiting_ack":
            level, text = rosmsg.ERROR, f"holding until acknowledged (/franka/acknowledge): {status.reason}"
        else:
            level, text = rosmsg.OK, status.state + (f": {status.reason}" if status.reason else "")
        if stats.last_rejection and level == rosmsg.OK:
            level, text = rosmsg.WARN, f"{text}; last rejected chunk: {stats.last_rejection}"
        values = {k: v for k, v in stats.as_dict().items() if k not in ("last_rejection",)}
        # faulted and awaiting_ack are the controller's state, not counters; their keys stay for the readers
        values.update(
            faulted=self.controller.faulted,
            awaiting_ack=self.controller.awaiting_ack,
            state=status.state,
            last_fault=status.last_fault,
        )
        self.pub_diag.publish(
            rosmsg.diagnostic_array(self.factory, now_ns(self), NODE_NAME, self.hardware_id, level, text, values)
        )

    def shutdown(self) -> None:
        self.controller.stop()
        self.robot.disconnect()
        if self.marker is not None:
            self.marker.unlink(missing_ok=True)  # a clean exit: the next franka_node may move home


def previous_exit_was_unclean(marker: Path) -> str:
    """Why the arm must wait for an operator ('' if it need not): the marker of a franka_node that
    did not shut down cleanly, whose process is gone. A live one is left alone (its own start-up
    fails on the robot connection, which a robot gives to one client at a time)."""
    try:
        pid = int(marker.read_text().strip() or 0)
    except (OSError, ValueError):
        return ""
    if pid > 0 and pid != os.getpid():
        try:
            os.kill(pid, 0)
            return ""
        except ProcessLookupError:
            pass
        except PermissionError:
            return ""
    return f"the previous franka_node (pid {pid}) for this robot exited uncleanly (killed or crashed)"


def _ros_logger_adapter(ros_logger):
    """A logging.Logger whose records go to the node's ROS logger (core modules log with `logging`)."""
    logger = logging.getLogger(f"equidiff.{NODE_NAME}")
    logger.propagate = False
    logger.setLevel(logging.INFO)

    class _Handler(logging.Handler):
        last_warned: ClassVar[dict[str, float]] = {}

        def emit(self, record):
            msg = self.format(record)
            if record.levelno >= logging.ERROR:
                ros_logger.error(msg)
            elif record.levelno >= logging.WARNING:
                # Throttled per kind of warning (text before the first ':'), so a burst of
                # rejected chunks does not hide the watchdog, and vice versa.
                kind, now = msg.split(":")[0][:40], time.monotonic()
                if now - self.last_warned.get(kind, -1e9) >= 1.0:
                    self.last_warned[kind] = now
                    ros_logger.warning(msg)
            else:
                ros_logger.info(msg)

    logger.handlers[:] = [_Handler()]
    return logger


# the errors that end a start-up with a one-line message (exit 1), not a traceback
STARTUP_ERRORS = (ConfigError, RobotError, ValueError)


def main(args=None) -> int:
    return run_node(NODE_NAME, USAGE, FrankaNode, STARTUP_ERRORS, args)


if __name__ == "__main__":
    sys.exit(main())
