"""The robot interface every backend (franky, dryrun) implements.

Shaped like the camera interface (LeRobot style): an abstract context manager with
``connect`` / ``disconnect``, plus what a streaming Cartesian controller needs: read the
state, stream a target pose with a feed-forward twist, move the gripper without blocking,
and recover from errors. Safety is not the backend's job: ``control.Controller`` filters
every target before it reaches ``stream_target``.

When the robot stops on its own (its user stop, a reflex, a lost connection) ``stream_target``
or ``read_state`` raise ``RobotStopped`` saying which; ``recover`` clears it (reconnecting
when the connection was lost) but refuses with ``UserStopPressed`` while the user stop is
pressed. Nothing here decides whether to go on: the controller holds until an operator does.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import Self

import numpy as np

ARM_JOINT_NAMES = tuple(f"fr3_joint{i}" for i in range(1, 8))
FINGER_JOINT_NAMES = ("fr3_finger_joint1", "fr3_finger_joint2")


@dataclass(frozen=True)
class JointLimits:
    """The FR3's joint limits a backend sets on the arm itself on connect (franky: the velocity limit of
    blocking moves, the tracker's position limits). ``control.SafetyConfig`` has the same fields, from
    control.yaml, with these as defaults."""

    # per joint: 95 % of the FR3's limits (2.62 rad/s for joints 1-4, 5.26 / 4.18 / 5.26 for the wrist;
    # franky-sim's fr3.urdf). One 2.5 for all had stopped fast but legal wrist turns.
    max_joint_speeds_rad_s: tuple[float, ...] = (2.5, 2.5, 2.5, 2.5, 5.0, 4.0, 5.0)
    # The FR3's joint position limits (datasheet; franky-sim's fr3.xml)
    joint_position_min_rad: tuple[float, ...] = (-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159)
    joint_position_max_rad: tuple[float, ...] = (2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159)


class CartesianLimits:
    """The FR3's Cartesian limits, as franky 2.0 reports them (``Robot.translation_velocity_limit.max``
    and its siblings; libfranka's published FR3 limits): config speeds and decelerations must not exceed them."""

    translation_velocity_m_s = 1.7
    translation_acceleration_m_s2 = 13.0
    translation_jerk_m_s3 = 6500.0
    rotation_velocity_rad_s = 2.5
    rotation_acceleration_rad_s2 = 25.0
    rotation_jerk_rad_s3 = 12500.0


# The FR3's joint speed limits (rad/s, joints 1-7; franky-sim's fr3.urdf): a configured joint speed may not exceed them.
FR3_JOINT_SPEEDS_RAD_S = (2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26)


class RobotError(RuntimeError):
    """The robot refused or aborted a command (reflex, connection loss, motion failure)."""


# RobotStopped.kind: what stopped the robot, and how an operator reads it
STOP_KINDS = {
    "user_stop": "user stop",
    "reflex": "reflex",
    "connection_lost": "connection to the robot lost",
    "error": "robot error",
}


class RobotStopped(RobotError):
    """The robot ended the motion on its own. ``kind`` (``STOP_KINDS``): ``user_stop`` (its user
    stop was pressed), ``reflex`` (a collision or limit reflex), ``connection_lost`` (no state
    within the client's timeout: only a new connection recovers), ``error`` (anything else, e.g.
    an aborted motion); ``reason`` is the robot's own text."""

    def __init__(self, kind: str, reason: str):
        if kind not in STOP_KINDS:
            raise ValueError(f"kind must be one of {sorted(STOP_KINDS)}, got {kind!r}")
        super().__init__(f"{STOP_KINDS[kind]}: {reason}")
        self.kind, self.reason = kind, reason


class UserStopPressed(RobotError):
    """Recovery refused: the user stop is still pressed (release it first)."""


@dataclass(frozen=True)
class RobotState:
    stamp_ns: int  # when the state was read (the backend's wall clock; control.Controller re-stamps on its own)
    ee_pose: np.ndarray  # (4, 4) TCP pose in the base frame
    joint_positions: np.ndarray  # (7,) rad
    joint_velocities: np.ndarray  # (7,) rad/s
    gripper_width: float  # m (NaN if unknown)
    robot_time_s: float = float("nan")  # the robot's own clock (libfranka's state time); NaN if it has none
    # the robot's own mode: "idle", "move", "user_stopped", "reflex", "guiding", "error_recovery",
    # "other"; "" for a backend without one
    mode: str = ""


class Robot(abc.ABC):
    """A Cartesian-streaming arm. Use as ``with make_robot(...) as robot: ...``."""

    @abc.abstractmethod
    def connect(self) -> None:
        """Connect; raise RobotError naming the address if the robot is unreachable."""

    @abc.abstractmethod
    def disconnect(self) -> None:
        """Stop any motion and release the robot; safe to call twice."""

    @property
    @abc.abstractmethod
    def is_connected(self) -> bool: ...

    @abc.abstractmethod
    def read_state(self) -> RobotState:
        """The newest state (non-blocking apart from the transport); RobotStopped
        ("connection_lost") when the robot cannot be read."""

    @abc.abstractmethod
    def move_to(self, pose: np.ndarray) -> None:
        """Blocking point-to-point move (used once, to go home before streaming starts)."""

    @abc.abstractmethod
    def start_streaming(self) -> None:
        """Start the streaming controller, seeded at the current pose (so nothing jumps)."""

    @abc.abstractmethod
    def stream_target(self, pose: np.ndarray, linear_velocity: np.ndarray, angular_velocity: np.ndarray) -> None:
        """Set the streaming controller's target (any rate); raise RobotStopped (or RobotError) if it stopped."""

    @abc.abstractmethod
    def stop_streaming(self) -> None:
        """Bring the arm to rest and end the streaming controller."""

    @abc.abstractmethod
    def move_gripper(self, width: float) -> None:
        """Start moving the gripper to ``width`` (m) and return at once."""

    @abc.abstractmethod
    def recover(self) -> str:
        """Clear the robot's errors, reconnecting first when the connection was lost, so that
        ``start_streaming`` can follow (it does not start streaming itself: the caller checks
        where the arm is first); return what was done.

        Raise UserStopPressed while the user stop is pressed, RobotError if recovery failed."""

    @property
    @abc.abstractmethod
    def has_errors(self) -> bool: ...

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.disconnect()
