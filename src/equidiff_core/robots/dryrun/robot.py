"""Dry-run robot: logs what would be sent and pretends to track it perfectly.

For checking a policy or teleop set-up end to end without moving hardware: the franka node
with ``backend: dryrun`` runs the same scheduler and safety filter and publishes the same
state, but the 'robot' is this object. Every command is kept (bounded) in ``sent`` and logged
at most once per ``log_period_s``.
"""

from __future__ import annotations

import collections
import logging
import time

import numpy as np

from ... import geometry
from ..base import Robot, RobotError, RobotState
from .config import DryRunConfig

log = logging.getLogger("equidiff.robot.dryrun")


class DryRunRobot(Robot):
    def __init__(self, config: DryRunConfig | None = None, logger: logging.Logger | None = None):
        self.config = config = config or DryRunConfig()
        self.log = logger or log
        self._pose = geometry.pose_from_pos_quat(config.initial_position, config.initial_quaternion_xyzw)
        self._width = config.initial_width
        self._connected = False
        self._streaming = False
        self._last_log = 0.0
        self._last_logged: np.ndarray | None = None
        self.sent: collections.deque = collections.deque(maxlen=config.keep_last)  # (kind, t_ns, value)

    def connect(self) -> None:
        self._connected = True
        self.log.info("dry run: no robot is connected; commands are logged, not sent")

    def disconnect(self) -> None:
        self._connected = False
        self._streaming = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    def read_state(self) -> RobotState:
        return RobotState(
            time.time_ns(), self._pose.copy(), np.array(self.config.joint_positions), np.zeros(7), self._width
        )

    def move_to(self, pose: np.ndarray) -> None:
        self._record("move_to", pose)
        self._pose = np.array(pose, dtype=np.float64)

    def start_streaming(self) -> None:
        self._streaming = True

    def stream_target(self, pose, linear_velocity, angular_velocity) -> None:
        if not self._streaming:
            raise RobotError("dry run: stream_target before start_streaming")
        self._record("target", pose)
        self._pose = np.array(pose, dtype=np.float64)

    def stop_streaming(self) -> None:
        self._streaming = False

    def move_gripper(self, width: float) -> None:
        self._record("gripper", width, force_log=True)
        self._width = float(width)

    def recover(self) -> str:
        return "dry run: nothing to recover"

    @property
    def has_errors(self) -> bool:
        return False

    def _record(self, kind: str, value, force_log: bool = False) -> None:
        now = time.time_ns()
        value = np.array(value, dtype=np.float64)
        self.sent.append((kind, now, value))
        # Holding still is not news: log a target only when it moved since the last logged one.
        moved = self._last_logged is None or kind != "target" or np.abs(value - self._last_logged).max() > 5e-4
        if force_log or (moved and now / 1e9 - self._last_log >= self.config.log_period_s):
            self._last_logged = value if kind == "target" else self._last_logged
            self._last_log = now / 1e9
            if kind == "gripper":
                self.log.info(f"dry run: would move the gripper to {float(value) * 1000:.1f} mm")
            else:
                p, q = geometry.pos_quat_from_pose(value)
                self.log.info(
                    f"dry run: would send {kind} xyz={np.round(p, 4).tolist()} "
                    f"quat_xyzw={np.round(q, 4).tolist()} ({len(self.sent)} commands so far)"
                )
