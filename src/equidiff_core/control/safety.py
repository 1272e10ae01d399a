"""Safety checks the franka node applies to every target, whoever sent it (policy, teleop, a script).

Two layers, both pure functions of poses and limits:

* ``check_chunk`` at arrival: NaN/inf, non-orthonormal rotations, the orientation cone (every
  step's tool axis within ``max_tilt_rad`` of straight down), and the jump between the robot's
  current pose and the chunk's first live step. A failing chunk raises ``SafetyRejection`` (a
  ``ChunkError``) and nothing of it is executed: the arm keeps its trajectory or holds.
* ``SafetyFilter.filter`` at every control tick: clip the position to the safety box (lab.yaml
  ``safety_box``, its floor raised by the floor margin) shrunk by ``box_margin_m``, swing the
  orientation back into the cone (only interpolation between two accepted steps can leave it,
  by a little), then limit the linear and angular speed relative to the previous command, and
  brake towards each wall (at most sqrt(2 a d) at distance d, ``wall_deceleration_m_s2``). The
  previous command is inside the box and the box is convex, so every command stays inside; the
  braking and the margin keep the *measured* TCP inside too: a command that stopped dead at a
  wall at the speed limit let the impedance-tracked arm overshoot it (2.7 mm on franky-sim).
  Widths are clipped to the hand's range.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .. import geometry
from ..config import SafetyBox
from ..wire.chunk import ChunkError, ChunkReason, PoseChunk
from .config import SafetyConfig


class SafetyRejection(ChunkError):
    """A chunk that is well-formed but violates a safety limit: ``kind`` "jump" (too far from the
    robot) or "cone" (tilted past the orientation cone)."""

    def __init__(self, message: str, kind: str = "jump"):
        super().__init__(message, ChunkReason(kind))
        self.kind = kind


def check_chunk(chunk: PoseChunk, current_pose: np.ndarray | None, limits: SafetyConfig) -> None:
    """Raise SafetyRejection/ChunkError if ``chunk`` must not be executed from ``current_pose``.

    ``chunk`` should already hold only its live steps (past ones dropped), so the jump is
    measured to what the robot will actually be asked to do next.
    """
    if not np.all(np.isfinite(chunk.poses)) or not np.all(np.isfinite(chunk.widths)):
        raise ChunkError("chunk contains NaN or inf", ChunkReason.NAN)
    try:
        geometry.validate_pose(chunk.poses, tol=limits.orthonormal_tol)
    except geometry.GeometryError as err:
        raise ChunkError(f"chunk pose invalid: {err}", ChunkReason.NAN) from err
    tilts = [geometry.tilt_angle(T[:3, :3]) for T in chunk.poses]
    worst = int(np.argmax(tilts))
    if tilts[worst] > limits.max_tilt_rad:
        raise SafetyRejection(
            f"step {worst} tilts the tool {np.degrees(tilts[worst]):.0f} deg from straight down "
            f"(cone {np.degrees(limits.max_tilt_rad):.0f} deg)",
            kind="cone",
        )
    if current_pose is None:
        return
    first = chunk.poses[0]
    jump = float(np.linalg.norm(first[:3, 3] - current_pose[:3, 3]))
    if jump > limits.max_first_step_jump_m:
        raise SafetyRejection(
            f"first step is {jump * 1000:.0f} mm from the current pose "
            f"(limit {limits.max_first_step_jump_m * 1000:.0f} mm)"
        )
    angle = geometry.rotation_angle(current_pose[:3, :3], first[:3, :3])
    if angle > limits.max_first_step_rotation_rad:
        raise SafetyRejection(
            f"first step is rotated {np.degrees(angle):.0f} deg from the current pose "
            f"(limit {np.degrees(limits.max_first_step_rotation_rad):.0f} deg)"
        )


@dataclass(frozen=True)
class FilteredTarget:
    pose: np.ndarray  # (4, 4) the command actually sent
    linear_velocity: np.ndarray  # (3,) feed-forward twist, base frame
    angular_velocity: np.ndarray  # (3,)
    clipped: bool  # the position was outside the safety box (or the orientation outside the cone)
    speed_limited: bool


class SafetyFilter:
    """Per-tick safety-box clip, cone limit and speed limit. Stateless apart from the limits."""

    def __init__(self, box: SafetyBox, limits: SafetyConfig):
        self.limits = limits
        self.box = box
        margin = limits.box_margin_m
        if np.any(box.max_corner - box.min_corner <= 2 * margin):
            raise ValueError(
                f"box_margin_m {margin} leaves nothing of the safety box {box.min_corner}..{box.max_corner}"
            )
        self.lower = box.min_corner + margin  # where commands may go: the floor margin and box_margin_m included
        self.upper = box.max_corner - margin

    def inside(self, position: np.ndarray, tol: float = 1e-9) -> bool:
        """Whether ``position`` is inside the safety box itself (not only where commands may go)."""
        return bool(np.all(position >= self.box.min_corner - tol) and np.all(position <= self.box.max_corner + tol))

    def clip_position(self, position: np.ndarray) -> np.ndarray:
        return np.clip(position, self.lower, self.upper)

    def clip_width(self, width: float) -> float:
        return float(np.clip(width, self.limits.min_gripper_width_m, self.limits.max_gripper_width_m))

    def filter(
        self,
        previous: np.ndarray,
        target: np.ndarray,
        dt: float,
        linear_velocity: np.ndarray | None = None,
        angular_velocity: np.ndarray | None = None,
    ) -> FilteredTarget:
        """Clip ``target`` to the box and move from ``previous`` towards it within the speed limits."""
        if dt <= 0:
            raise ValueError(f"dt must be positive, got {dt}")
        goal_p = self.clip_position(target[:3, 3])
        target_R = np.asarray(target[:3, :3], dtype=np.float64)
        goal_R = geometry.limit_tilt(target_R, self.limits.max_tilt_rad)
        clipped = not np.allclose(goal_p, target[:3, 3], atol=1e-9) or goal_R is not target_R
        prev_p = previous[:3, 3]
        step = goal_p - prev_p
        dist = float(np.linalg.norm(step))
        max_dist = self.limits.max_linear_speed_m_s * dt
        lin_limited = dist > max_dist
        new_p = prev_p + step * (max_dist / dist) if lin_limited else goal_p
        braked = self._brake(prev_p, new_p, dt)
        lin_limited = lin_limited or braked is not new_p
        new_p = braked

        R_prev = Rotation.from_matrix(previous[:3, :3])
        delta = Rotation.from_matrix(goal_R) * R_prev.inv()  # world-frame rotation
        rotvec = delta.as_rotvec()
        angle = float(np.linalg.norm(rotvec))
        max_angle = self.limits.max_angular_speed_rad_s * dt
        ang_limited = angle > max_angle
        if ang_limited:
            rotvec = rotvec * (max_angle / angle)
        slerped = (Rotation.from_rotvec(rotvec) * R_prev).as_matrix()
        new_R = geometry.limit_tilt(slerped, self.limits.max_tilt_rad)  # a big yaw can swing the axis out midway
        clipped = clipped or new_R is not slerped

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

    def _brake(self, prev_p: np.ndarray, new_p: np.ndarray, dt: float) -> np.ndarray:
        """``new_p`` with each axis's step towards a wall cut to sqrt(2 a d) dt, d the previous
        command's distance to that wall (``new_p`` itself when nothing was cut)."""
        step = new_p - prev_p
        gap = np.where(step > 0, self.upper - prev_p, prev_p - self.lower)  # to the wall it heads for
        allowed = np.sqrt(2.0 * self.limits.wall_deceleration_m_s2 * np.maximum(gap, 0.0)) * dt
        if np.all(np.abs(step) <= allowed):
            return new_p
        return prev_p + np.clip(step, -allowed, allowed)
