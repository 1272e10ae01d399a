"""Safety checks the franka node applies to every target, whoever sent it (policy, teleop, a script).

Two layers, both pure functions of poses and limits:

* ``check_chunk`` at arrival: NaN/inf, non-orthonormal rotations, widths, and the jump between
  the robot's current pose and the chunk's first live step. A failing chunk raises
  ``SafetyRejection`` (a ``ChunkError``) and nothing of it is executed.
* ``SafetyFilter.filter`` at every control tick: clip the position to the workspace box (shrunk
  by a margin), then limit the linear and angular speed relative to the previous command. The
  previous command is inside the box and the box is convex, so every command stays inside.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .. import geometry
from ..chunk import ChunkError, PoseChunk
from ..config import Workspace
from .config import SafetyConfig


class SafetyRejection(ChunkError):
    """A chunk that is well-formed but violates a safety limit (too far from the robot)."""


def check_chunk(chunk: PoseChunk, current_pose: np.ndarray | None, limits: SafetyConfig) -> None:
    """Raise SafetyRejection/ChunkError if ``chunk`` must not be executed from ``current_pose``.

    ``chunk`` should already hold only its live steps (past ones dropped), so the jump is
    measured to what the robot will actually be asked to do next.
    """
    if not np.all(np.isfinite(chunk.poses)) or not np.all(np.isfinite(chunk.widths)):
        raise ChunkError("chunk contains NaN or inf")
    try:
        geometry.validate_pose(chunk.poses, tol=limits.orthonormal_tol)
    except geometry.GeometryError as err:
        raise ChunkError(f"chunk pose invalid: {err}") from err
    if current_pose is None:
        return
    first = chunk.poses[0]
    jump = float(np.linalg.norm(first[:3, 3] - current_pose[:3, 3]))
    if jump > limits.max_first_step_jump_m:
        raise SafetyRejection(f"first step is {jump * 1000:.0f} mm from the current pose "
                              f"(limit {limits.max_first_step_jump_m * 1000:.0f} mm)")
    angle = geometry.rotation_angle(current_pose[:3, :3], first[:3, :3])
    if angle > limits.max_first_step_rotation_rad:
        raise SafetyRejection(f"first step is rotated {np.degrees(angle):.0f} deg from the current pose "
                              f"(limit {np.degrees(limits.max_first_step_rotation_rad):.0f} deg)")


@dataclass(frozen=True)
class FilteredTarget:
    pose: np.ndarray  # (4, 4) the command actually sent
    linear_velocity: np.ndarray  # (3,) feed-forward twist, base frame
    angular_velocity: np.ndarray  # (3,)
    clipped: bool  # the position was outside the (shrunk) workspace box
    speed_limited: bool


class SafetyFilter:
    """Per-tick workspace clip + speed limit. Stateless apart from the limits."""

    def __init__(self, workspace: Workspace, limits: SafetyConfig):
        self.limits = limits
        margin = limits.workspace_margin_m
        if 2 * margin >= workspace.edge:
            raise ValueError(f"workspace margin {margin} m leaves no room in a {workspace.edge} m box")
        self.lower = workspace.lower + margin
        self.upper = workspace.upper - margin

    def inside(self, position: np.ndarray, tol: float = 1e-9) -> bool:
        return bool(np.all(position >= self.lower - tol) and np.all(position <= self.upper + tol))

    def clip_position(self, position: np.ndarray) -> np.ndarray:
        return np.clip(position, self.lower, self.upper)

    def clip_width(self, width: float) -> float:
        return float(np.clip(width, self.limits.min_gripper_width_m, self.limits.max_gripper_width_m))

    def filter(self, previous: np.ndarray, target: np.ndarray, dt: float,
               linear_velocity: np.ndarray | None = None,
               angular_velocity: np.ndarray | None = None) -> FilteredTarget:
        """Clip ``target`` to the box and move from ``previous`` towards it within the speed limits."""
        if dt <= 0:
            raise ValueError(f"dt must be positive, got {dt}")
        goal_p = self.clip_position(target[:3, 3])
        clipped = not np.allclose(goal_p, target[:3, 3], atol=1e-9)
        prev_p = previous[:3, 3]
        step = goal_p - prev_p
        dist = float(np.linalg.norm(step))
        max_dist = self.limits.max_linear_speed_m_s * dt
        lin_limited = dist > max_dist
        new_p = prev_p + step * (max_dist / dist) if lin_limited else goal_p

        R_prev = Rotation.from_matrix(previous[:3, :3])
        delta = Rotation.from_matrix(target[:3, :3]) * R_prev.inv()  # world-frame rotation
        rotvec = delta.as_rotvec()
        angle = float(np.linalg.norm(rotvec))
        max_angle = self.limits.max_angular_speed_rad_s * dt
        ang_limited = angle > max_angle
        if ang_limited:
            rotvec = rotvec * (max_angle / angle)
        new_R = (Rotation.from_rotvec(rotvec) * R_prev).as_matrix()

        v = np.zeros(3) if linear_velocity is None else np.asarray(linear_velocity, dtype=np.float64)
        w = np.zeros(3) if angular_velocity is None else np.asarray(angular_velocity, dtype=np.float64)
        if clipped or lin_limited:
            v = (new_p - prev_p) / dt  # feed forward what we actually command, never the raw request
        if ang_limited:
            w = rotvec / dt
        speed = float(np.linalg.norm(v))
        if speed > self.limits.max_linear_speed_m_s:
            v = v * (self.limits.max_linear_speed_m_s / speed)
        wn = float(np.linalg.norm(w))
        if wn > self.limits.max_angular_speed_rad_s:
            w = w * (self.limits.max_angular_speed_rad_s / wn)
        return FilteredTarget(geometry.make_pose(new_R, new_p), v, w, clipped, lin_limited or ang_limited)
