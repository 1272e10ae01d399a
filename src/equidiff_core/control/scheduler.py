"""Time-indexed execution of pose chunks: the setpoint (pose, twist, width) at any absolute time.

Same idea as diffusion_policy's ``PoseTrajectoryInterpolator.schedule_waypoint``: a chunk's
steps carry absolute times; steps already past (earlier than now + a small margin) are dropped;
a new chunk *replaces* the remainder of the old one, and the new trajectory starts from the
setpoint the robot is being commanded right now, so position is continuous.

Position is ``linear`` (piecewise-constant velocity through the steps, diffusion_policy's
choice; the default, it tracked best on franky-sim) or ``cubic``: a C1 cubic Hermite spline
(scipy) whose first velocity is the current setpoint velocity, so velocity is continuous
across chunk switches, with knot velocities kept from pointing against the chords (no
reversal, bounded overshoot). Rotation is slerp (scipy ``Slerp``) with a piecewise-constant angular velocity;
the gripper width is held at each step's value from that step's time (a step, not a ramp:
gripper commands are discrete).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicHermiteSpline
from scipy.spatial.transform import Rotation, Slerp

from .. import geometry
from ..wire.chunk import ChunkError, ChunkReason, PoseChunk
from .config import SchedulerConfig

NS = 1e9


@dataclass(frozen=True)
class Setpoint:
    pose: np.ndarray  # (4, 4)
    linear_velocity: np.ndarray  # (3,)
    angular_velocity: np.ndarray  # (3,)
    width: float  # gripper target, NaN = no gripper command yet
    active: bool  # False once the trajectory has ended (holding its last pose)


class ChunkScheduler:
    """Holds one trajectory (the remainder of the newest chunk) and samples it at any time."""

    def __init__(self, config: SchedulerConfig = SchedulerConfig()):
        self.config = config
        self._t0_ns: int | None = None  # time origin of the spline (seconds are relative to it)
        self._times: np.ndarray | None = None  # (K,) knot times, seconds from t0
        self._position = None  # callable t -> (3,), with .derivative()
        self._velocity = None
        self._slerp: Slerp | None = None
        self._rotations: Rotation | None = None
        self._width_times: np.ndarray | None = None
        self._widths: np.ndarray | None = None

    @property
    def has_trajectory(self) -> bool:
        return self._times is not None

    def end_ns(self) -> int | None:
        return None if self._times is None else self._t0_ns + int(self._times[-1] * NS)

    def clear(self) -> None:
        self._times = None

    def live_steps(self, chunk: PoseChunk, now_ns: int) -> PoseChunk:
        """The steps of ``chunk`` still to execute; raise ChunkError if it is stale, stamped more
        than ``max_future_stamp_s`` ahead of ``now_ns``, or its first live step lies more than
        ``max_first_step_lead_s`` ahead.

        A chunk whose steps all lie in the past but whose last step is recent (a teleop target
        stamped 'now', a policy chunk that arrived late) becomes one step at now + lead_s.
        """
        cfg = self.config
        ahead_s = (chunk.stamp_ns - now_ns) / NS
        if ahead_s > cfg.max_future_stamp_s:
            raise ChunkError(
                f"chunk is stamped {ahead_s * 1000:.0f} ms in the future "
                f"(limit {cfg.max_future_stamp_s * 1000:.0f} ms): a clock is wrong",
                ChunkReason.FUTURE,
            )
        live = chunk.after(now_ns + int(cfg.drop_margin_s * NS))
        if live is not None:
            lead_s = (int(live.times_ns[0]) - now_ns) / NS
            if lead_s > cfg.max_first_step_lead_s:
                raise ChunkError(
                    f"chunk's first step is {lead_s:.3g} s in the future (limit {cfg.max_first_step_lead_s:.3g} s)",
                    ChunkReason.FUTURE,
                )
            return live
        age_s = (now_ns - int(chunk.times_ns[-1])) / NS
        if age_s > cfg.max_step_age_s:
            raise ChunkError(
                f"chunk is stale: its last step was {age_s * 1000:.0f} ms ago "
                f"(limit {cfg.max_step_age_s * 1000:.0f} ms)",
                ChunkReason.STALE,
            )
        return PoseChunk(
            chunk.stamp_ns,
            np.array([now_ns + int(cfg.lead_s * NS)], dtype=np.int64),
            chunk.poses[-1:],
            chunk.widths[-1:],
        )

    def schedule(self, live: PoseChunk, now_ns: int, current: Setpoint) -> None:
        """Replace the trajectory by: ``current`` setpoint at ``now_ns``, then the live steps."""
        t_steps = (live.times_ns - now_ns) / NS
        keep = t_steps > 1e-3  # a step at 'now' would make a zero-length segment
        if not keep.any():
            t_steps, poses, widths = np.array([self.config.lead_s]), live.poses[-1:], live.widths[-1:]
        else:
            t_steps, poses, widths = t_steps[keep], live.poses[keep], live.widths[keep]
        times = np.concatenate([[0.0], t_steps])
        positions = np.concatenate([current.pose[None, :3, 3], poses[:, :3, 3]])
        rotations = Rotation.from_matrix(np.concatenate([current.pose[None, :3, :3], poses[:, :3, :3]]))
        # Identical knot times (duplicated steps) would break the splines: keep the later copy.
        uniq = np.concatenate([np.diff(times) > 1e-6, [True]])
        uniq[0] = True
        times, positions = times[uniq], positions[uniq]
        rotations = rotations[np.flatnonzero(uniq)]
        if len(times) < 2:
            times = np.array([0.0, self.config.lead_s])
            positions = np.repeat(positions[:1], 2, axis=0)
            rotations = Rotation.concatenate([rotations[0], rotations[0]])

        if self.config.interpolation == "linear":
            slopes = np.diff(positions, axis=0) / np.diff(times)[:, None]
            self._position = _PiecewiseLinear(times, positions, slopes)
        else:
            slopes = _curve_slopes(times, positions, current.linear_velocity)
            self._position = CubicHermiteSpline(times, positions, slopes, axis=0)
        self._velocity = self._position.derivative()
        self._rotations = rotations
        self._slerp = Slerp(times, rotations)
        self._times = times
        self._t0_ns = int(now_ns)
        self._width_times = t_steps
        self._widths = widths

    def sample(self, t_ns: int, hold_width: float = float("nan")) -> Setpoint | None:
        """The setpoint at ``t_ns`` (None without a trajectory); past the end: its last pose, at rest."""
        if self._times is None:
            return None
        t = (t_ns - self._t0_ns) / NS
        t_end = self._times[-1]
        active = t < t_end
        tc = float(np.clip(t, 0.0, t_end))
        position = np.asarray(self._position(tc), dtype=np.float64)
        R = self._slerp([tc]).as_matrix()[0]
        if active:
            v = np.asarray(self._velocity(tc), dtype=np.float64)
            seg = int(np.clip(np.searchsorted(self._times, tc, side="right") - 1, 0, len(self._times) - 2))
            rel = self._rotations[seg + 1] * self._rotations[seg].inv()
            w = rel.as_rotvec() / (self._times[seg + 1] - self._times[seg])
        else:
            v, w = np.zeros(3), np.zeros(3)
        passed = np.flatnonzero(self._width_times <= tc + 1e-9)
        # Gripper: the target of the step being approached, so a close starts on time.
        idx = min(int(passed[-1]) + 1 if len(passed) else 0, len(self._widths) - 1)
        width = float(self._widths[idx]) if len(self._widths) else hold_width
        return Setpoint(geometry.make_pose(R, position), v, w, width, bool(active))


class _PiecewiseLinear:
    def __init__(self, times, positions, slopes):
        self.times, self.positions, self.slopes = times, positions, slopes

    def _seg(self, t):
        return int(np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.times) - 2))

    def __call__(self, t):
        i = self._seg(t)
        return self.positions[i] + self.slopes[i] * (t - self.times[i])

    def derivative(self):
        return lambda t: self.slopes[self._seg(t)]


def _curve_slopes(times: np.ndarray, positions: np.ndarray, v0: np.ndarray) -> np.ndarray:
    """Knot velocities for a C1 cubic through the waypoints that never runs backwards along a chord.

    Interior knots: the three-point (non-uniform Catmull-Rom) finite difference, which keeps
    the speed even along a curve (per-axis PCHIP flattens every axis extremum and made the
    speed swing by +-45 % on a circle). Knot 0: the current setpoint velocity (continuity
    across chunk switches). Last knot: the last chord's velocity. A knot velocity pointing
    against an adjacent chord is projected onto the plane normal to it and then capped at 3x
    the chord speed (Fritsch-Carlson's bound), so no segment reverses or overshoots far.
    """
    dt = np.diff(times)[:, None]
    chords = np.diff(positions, axis=0) / dt  # (K-1, 3) chord velocities
    slopes = np.empty_like(positions)
    slopes[0] = np.asarray(v0, dtype=np.float64)
    slopes[-1] = chords[-1]
    if len(times) > 2:
        slopes[1:-1] = (positions[2:] - positions[:-2]) / (times[2:] - times[:-2])[:, None]
    for i in range(len(times)):
        for c in (chords[i - 1] if i > 0 else None, chords[i] if i < len(chords) else None):
            if c is None:
                continue
            cn = float(np.dot(c, c))
            if cn < 1e-18:
                slopes[i] = 0.0
                continue
            along = float(np.dot(slopes[i], c))
            if along < 0:
                slopes[i] = slopes[i] - along / cn * c
            cap = 3.0 * np.sqrt(cn)
            norm = float(np.linalg.norm(slopes[i]))
            if norm > cap:
                slopes[i] *= cap / norm
    return slopes
