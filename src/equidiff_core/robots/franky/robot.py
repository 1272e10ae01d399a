"""franky 2.0 backend (PyPI ``franky-control``): a real FR3 or franky-sim at ``ip``.

Streaming uses franky 2.0's ``CartesianImpedanceTracker``: one long-lived torque-controlled
motion whose target we set at the control rate with a velocity feed-forward. On franky-sim
that tracked a 5 Hz chunk stream without stop-and-go, while preempting
motions per chunk stops at every chunk and ``CartesianWaypointMotion`` needs per-waypoint
velocities and ``minimum_time`` not to stop or overshoot (``docs/results/control.md``
for our own measurement). Being torque-controlled it also cannot trip the motion generator's
discontinuity reflexes. The gripper has its own thread, which sends the newest requested width
(``move_async`` / ``grasp_async``) and reads the width back: a gripper read blocks until the
gripper's next state message, and a gripper command could block the 200 Hz loop (it froze the arm).
That thread sends one command at a time, as libfranka's blocking gripper API assumes: a command
sent while another runs made franky-sim drop the first one's reply, and franky then blocked the
second call forever, so the gripper never moved again (the twin's homing failed "gripper 50 mm
for 80 mm").

Limits set explicitly on connect, never franky's or the robot's defaults: the collision reflex
thresholds (``FrankyConfig.collision_*``, ``Robot.set_collision_behavior``), the joint velocity
limit of blocking moves (``SafetyConfig.max_joint_speeds_rad_s``, capped at franky's maximum),
and the tracker's joint position limits (``SafetyConfig.joint_position_*``: franky pushes the
joints back within ``FrankyConfig.joint_limit_activation_rad`` of them). ``applied_limits``
holds what was set. franky-sim acknowledges the collision thresholds but simulates no reflex.

Stops: when the motion ends on its own, ``stream_target`` raises ``RobotStopped`` with the kind
read from the robot (``user_stop`` for libfranka's "User Stop pressed" or mode ``UserStopped``,
``reflex``, ``connection_lost`` for a ``NetworkException`` or an unreadable state, else
``error``). ``recover`` refuses while the user stop is pressed, and after a lost connection
builds a new ``franky.Robot`` (and ``Gripper``): libfranka's ``Robot`` is dead for good once its
1 s UDP receive timeout fired ("TCP send bytes: I/O error" on every later call).
"""

from __future__ import annotations

import gc
import logging
import threading
import time

import numpy as np

from ...runtime.machine import keep_thread_scheduler
from ..base import JointLimits, Robot, RobotError, RobotState, RobotStopped, UserStopPressed
from .config import FrankyConfig

log = logging.getLogger("equidiff.robot.franky")


class FrankyRobot(Robot):
    def __init__(
        self,
        ip: str,
        config: FrankyConfig | None = None,
        realtime: bool = True,
        gripper: bool = True,
        logger: logging.Logger | None = None,
        safety: JointLimits | None = None,
    ):
        """``safety``: the joint limits set on connect; ``control.SafetyConfig`` carries the same fields
        (control.yaml's ``safety:``) and is what franka_node passes."""
        self.ip = ip
        self.config = config or FrankyConfig()
        self.safety = safety or JointLimits()
        self.applied_limits: dict = {}
        self.realtime = realtime  # False for franky-sim / a machine without an RT kernel
        self.use_gripper = gripper
        self.log = logger or log
        self._robot = None
        self._gripper = None
        self._tracker = None
        self._posture_q: np.ndarray | None = None  # null-space posture target (joint positions)
        self._width = float("nan")
        self._gripper_stop = threading.Event()
        self._gripper_lock = threading.Lock()
        self._gripper_request: float | None = None
        self._gripper_thread: threading.Thread | None = None
        self._lost = False  # the connection died (libfranka timed out): only a new franky.Robot recovers

    # --- connection --------------------------------------------------------------------
    def connect(self) -> None:
        import franky

        rt = franky.RealtimeConfig.Enforce if self.realtime else franky.RealtimeConfig.Ignore
        try:
            with keep_thread_scheduler("libfranka"):
                self._robot = franky.Robot(self.ip, realtime_config=rt)
        except Exception as err:  # franky raises its own NetworkException etc.
            raise RobotError(f"cannot connect to the robot at {self.ip}: {err}") from err
        self._lost = False
        self._robot.relative_dynamics_factor = self.config.relative_dynamics_factor
        self._clear_errors()
        self._apply_limits()
        if self.use_gripper:
            try:
                self._gripper = franky.Gripper(self.ip)
                self._width = float(self._gripper.width)
            except Exception as err:
                raise RobotError(f"cannot connect to the gripper at {self.ip}: {err}") from err
            self._gripper_stop.clear()
            self._gripper_thread = threading.Thread(target=self._poll_gripper, name="gripper-poll", daemon=True)
            self._gripper_thread.start()

    def disconnect(self) -> None:
        if self._robot is None:
            return
        try:
            self.stop_streaming()
        except Exception as err:  # noqa: BLE001 - never let shutdown hide the original problem
            self.log.warning(f"stopping the tracker on disconnect: {err}")
        self._release()

    def _release(self) -> None:
        """Drop the franky objects (their sockets close with them) and the gripper thread."""
        self._gripper_stop.set()
        if self._gripper_thread is not None:
            self._gripper_thread.join(timeout=3)
        self._gripper_thread = None
        self._gripper = None
        self._tracker = None
        self._robot = None
        gc.collect()  # libfranka closes its connection when the Robot goes: franky-sim serves one client

    def _reconnect(self) -> None:
        self.log.warning(f"the connection to the robot at {self.ip} was lost: connecting again")
        self._release()
        self.connect()

    def _clear_errors(self) -> None:
        """``recover_from_errors``: UserStopPressed while the user stop is pressed, RobotError on
        any other refusal (e.g. "manual error recovery required")."""
        try:
            self._require().recover_from_errors()
        except Exception as err:  # franky's CommandException / NetworkException
            if "User Stop" in str(err):
                raise UserStopPressed(f"the user stop is still pressed ({err})") from err
            raise RobotError(f"recover_from_errors failed: {err}") from err

    @property
    def is_connected(self) -> bool:
        return self._robot is not None

    def _apply_limits(self) -> None:
        cfg, robot = self.config, self._robot
        try:
            robot.set_collision_behavior(
                list(cfg.collision_torque_thresholds_nm), list(cfg.collision_force_thresholds_n)
            )
            limit = robot.joint_velocity_limit
            speeds = np.minimum(self.safety.max_joint_speeds_rad_s, limit.max)
            limit.set(speeds)
        except Exception as err:  # franky's CommandException / RuntimeError: never stream with unknown limits
            raise RobotError(f"cannot set the robot's limits at {self.ip}: {err}") from err
        self.applied_limits = {
            "collision_torque_thresholds_nm": list(cfg.collision_torque_thresholds_nm),
            "collision_force_thresholds_n": list(cfg.collision_force_thresholds_n),
            "move_joint_velocity_limit_rad_s": [float(v) for v in limit.get()],
            "joint_position_min_rad": list(self.safety.joint_position_min_rad),
            "joint_position_max_rad": list(self.safety.joint_position_max_rad),
        }
        self.log.info(f"limits set: {self.applied_limits}")

    def _require(self):
        if self._robot is None:
            raise RobotError("robot is not connected")
        return self._robot

    # --- state ---------------------------------------------------------------------------
    def read_state(self) -> RobotState:
        state = self._fresh_state()
        return RobotState(
            time.time_ns(),
            np.array(state.O_T_EE.matrix, dtype=np.float64),
            np.array(state.q, dtype=np.float64),
            np.array(state.dq, dtype=np.float64),
            self._width,
            state.time.to_sec(),
            _MODES.get(str(state.robot_mode).rsplit(".", 1)[-1], "other"),
        )

    def _fresh_state(self):
        """franky's state: the control loop's while a motion runs, else read from the robot.
        Read twice then: libfranka takes the newest state already queued on its socket, and
        after a pause (a held arm polled at 10 Hz) the queue holds only old ones (the socket
        buffer fills in ~0.1 s and drops what comes after); the second read waits for a new one."""
        robot = self._require()
        try:
            state = robot.state
            if not robot.is_in_control:
                state = robot.state
        except Exception as err:  # franky's NetworkException / RuntimeError("Net Exception"): the connection is dead
            self._lost = True
            raise RobotStopped("connection_lost", f"cannot read the robot state: {err}") from err
        return state

    def _poll_gripper(self) -> None:
        """The gripper's own thread: once the last command has finished, sends the newest requested
        width; then reads the width back. Widths requested meanwhile are superseded, never queued."""
        running, sent_at, warned = None, 0.0, False
        while not self._gripper_stop.wait(0.05):
            if running is not None and not _finished(running):
                if not warned and time.monotonic() - sent_at > self.config.gripper_command_timeout_s:
                    self.log.warning(
                        f"the gripper command sent {self.config.gripper_command_timeout_s:.0f} s "
                        f"ago has not finished; newer widths wait for it"
                    )
                    warned = True
                width = None
            else:
                running, warned = None, False
                with self._gripper_lock:
                    width, self._gripper_request = self._gripper_request, None
            try:
                if width is not None:
                    running, sent_at = self._send_gripper(width), time.monotonic()
                self._width = float(self._gripper.width)
            except Exception as err:  # noqa: BLE001 - franky raises many kinds; the gripper thread must live on
                self.log.warning(f"gripper command or read failed: {err}")
                with self._gripper_lock:  # retry a failed width unless a newer one replaced it
                    if width is not None and self._gripper_request is None:
                        self._gripper_request = width
                time.sleep(0.5)

    # --- motion --------------------------------------------------------------------------
    def move_to(self, pose: np.ndarray) -> None:
        import franky

        robot = self._require()
        if self._tracker is not None:
            raise RobotError("move_to while streaming: stop_streaming first")
        target = franky.Affine(np.asarray(pose, dtype=np.float64))
        # Retries after recover_from_errors: on a loaded franky-sim the first motion after connecting
        # was rejected now and then (ruckig -101, "incorrect object size"). franky motions cannot be reused.
        attempts = 3
        for attempt in range(1, attempts + 1):
            try:
                with keep_thread_scheduler("libfranka"):  # a blocking move runs libfranka's loop in this thread
                    robot.move(franky.CartesianMotion(target))
                return
            except Exception as err:
                if attempt == attempts:
                    raise RobotError(f"move to home failed after {attempts} attempts: {err}") from err
                self.log.warning(f"move to home failed ({err}); recovering and retrying")
                self._clear_errors()
                time.sleep(0.5)

    def start_streaming(self) -> None:
        import franky

        robot = self._require()
        cfg = self.config
        friction = franky.FrictionCompensationParams(
            coulomb=list(cfg.friction_coulomb),
            viscous=list(cfg.friction_viscous),
            max_torque=[cfg.friction_max_torque] * 7,
        )
        if self._posture_q is None:  # where streaming first starts: the home pose; kept across recoveries
            self._posture_q = np.array(robot.state.q, dtype=np.float64)
        posture = (
            franky.PostureTask(self._posture_q, cfg.posture_stiffness, max_torque=cfg.posture_max_torque)
            if cfg.posture_stiffness > 0
            else None
        )
        try:
            self._tracker = franky.CartesianImpedanceTracker(
                robot,
                translational_stiffness=cfg.translational_stiffness,
                rotational_stiffness=cfg.rotational_stiffness,
                friction=friction,
                posture_task=posture,
                lower_joint_limits=np.asarray(self.safety.joint_position_min_rad, dtype=np.float64),
                upper_joint_limits=np.asarray(self.safety.joint_position_max_rad, dtype=np.float64),
                joint_limit_activation_distance=cfg.joint_limit_activation_rad,
            )
        except Exception as err:
            self._tracker = None
            raise RobotError(f"cannot start the impedance tracker: {err}") from err

    def stream_target(self, pose, linear_velocity, angular_velocity) -> None:
        import franky

        robot = self._require()
        if self._tracker is None:
            raise RobotError("stream_target before start_streaming")
        if not robot.is_in_control:
            raise self._stopped()
        self._tracker.set_target(
            franky.Affine(np.asarray(pose, dtype=np.float64)),
            franky.Twist(np.asarray(linear_velocity, dtype=np.float64), np.asarray(angular_velocity, dtype=np.float64)),
        )

    def stop_streaming(self) -> None:
        tracker, self._tracker = self._tracker, None
        if tracker is None:
            return
        try:
            tracker.stop()
        except Exception as err:  # franky's ControlException / ProtocolException: the motion has ended anyway
            raise RobotError(f"stopping the impedance tracker: {err}") from err

    def _stopped(self) -> RobotStopped:
        """What ended the streaming motion: its exception and the robot's mode, as a RobotStopped."""
        import franky

        reason, exception = "the motion ended without a robot error (stopped or preempted by another client)", None
        try:
            self._robot.join_motion(timeout=0.0)
        except Exception as err:  # noqa: BLE001 - franky's ControlException / NetworkException carry libfranka's reason
            reason, exception = " ".join(str(err).split()), err
        if isinstance(exception, franky.NetworkException):
            self._lost = True
            return RobotStopped("connection_lost", reason)
        try:
            state = self._fresh_state()
        except RobotStopped as err:
            return RobotStopped("connection_lost", f"{reason}; {err.reason}")
        mode = _MODES.get(str(state.robot_mode).rsplit(".", 1)[-1], "other")
        if exception is None:
            for attr in ("last_motion_errors", "current_errors"):
                text = str(getattr(state, attr, ""))
                if text not in ("", "[]", "None"):
                    reason = f"{attr}: {text}"
                    break
        if mode == "user_stopped" or "User Stop" in reason:
            return RobotStopped("user_stop", reason)
        if mode == "reflex" or "reflex" in reason:
            return RobotStopped("reflex", reason)
        return RobotStopped("error", reason)

    def move_gripper(self, width: float) -> None:
        """Hand the width to the gripper thread and return at once.

        A franky gripper call can block while the previous one runs (on franky-sim the control
        loop froze after the policy changed the width often, arm and gripper with it);
        the control loop must never wait for the gripper, and only the newest width matters."""
        if self._gripper is None:
            return
        with self._gripper_lock:
            self._gripper_request = float(width)

    def _send_gripper(self, width: float):
        cfg = self.config
        if np.isfinite(self._width) and width < self._width:
            # Closing is a grasp with a wide outer epsilon: closing on an object then counts as
            # success and keeps squeezing it (on franky-sim a plain move to the object's width does not hold it).
            return self._gripper.grasp_async(
                float(width),
                cfg.gripper_speed_m_s,
                cfg.gripper_force_n,
                epsilon_inner=0.08,
                epsilon_outer=cfg.gripper_epsilon_outer_m,
            )
        return self._gripper.move_async(float(width), cfg.gripper_speed_m_s)

    def recover(self) -> str:
        done = []
        if self._lost:
            self._reconnect()  # connect() clears the errors (or refuses while the user stop is pressed)
            done.append("reconnected")
        else:
            self._tracker = None
            if self.read_state().mode == "user_stopped":
                raise UserStopPressed("the user stop is still pressed")
            self._clear_errors()
        done.append("errors cleared")
        return ", ".join(done)

    @property
    def has_errors(self) -> bool:
        return self._robot is not None and bool(self._robot.has_errors)


# franky's RobotMode names -> RobotState.mode
_MODES = {
    "Idle": "idle",
    "Move": "move",
    "Guiding": "guiding",
    "Reflex": "reflex",
    "UserStopped": "user_stopped",
    "AutomaticErrorRecovery": "error_recovery",
    "Other": "other",
}


def _finished(future) -> bool:
    """Whether a franky gripper future (``BoolFuture``) is done; its result (grasped or not) is not
    an error here: a grasp that closes on nothing just ends at the commanded width."""
    return bool(future.wait(0.0))
