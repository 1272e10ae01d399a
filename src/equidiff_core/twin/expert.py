"""Scripted expert for "put the block in the bowl": a grasp-lift-place plan from the sim state.

The plan is a list of timed keyframes (TCP pose, gripper width) interpolated linearly in
position and yaw at operator-like speeds; ``target_at(t)`` gives the pose a SpaceMouse
operator would be commanding at time t. The same plan drives the direct sim (tests) and the
ROS teleop path (``twin collect``: one-point ``/franka/command_chunk`` targets at 20 Hz,
exactly what teleop_node publishes), so demonstrations go through the recorder like human ones.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from .. import geometry
from ..geometry import rotation_angle
from .config import ExpertConfig, TwinConfig

# TCP pointing down, fingers closing along the TCP's y axis (FR3 hand at q7 = pi/4 has yaw 0).
DOWN = np.diag([1.0, -1.0, -1.0])


def tcp_pose(position, yaw: float) -> np.ndarray:
    return geometry.make_pose(geometry.rotz(yaw) @ DOWN, np.asarray(position, dtype=float))


def tcp_yaw(T: np.ndarray) -> float:
    """Yaw of a (roughly) downward TCP: angle of its x axis in the base xy plane."""
    return math.atan2(T[1, 0], T[0, 0])


def grasp_yaw(block_yaw: float, reference_yaw: float = 0.0) -> float:
    """Hand yaw that closes the fingers across the block's short (local y) side.

    The fingers close along the hand's y axis, so the hand yaw must equal the block yaw
    modulo pi; of the two we take the one nearest ``reference_yaw`` (the wrist's range is finite).
    """
    candidates = [block_yaw + k * math.pi for k in range(-3, 4)]
    return min(candidates, key=lambda a: abs(_wrap(a - reference_yaw)) + 1e-9 * abs(a))


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


class LinePath:
    """A straight TCP path to ``target`` streamed as teleop targets, one per ``next(tcp)`` call at
    ``hz``, that waits for the arm and restarts from the arm when the arm is not on it.

    The path advances only while the TCP is within ``max_lag_m`` / ``max_lag_rad`` of the last
    target: on a twin slower than real time a wall-clock path ran ahead of the arm until
    franka_node rejected it as a jump (and franka_node turns the hand at most 0.6 rad/s). When the TCP is farther than ``restart_m`` (or ``restart_rad``) from the last target,
    the arm is elsewhere (still braking after a divergence stop, or pushed), every target on the
    old line would be rejected as a jump (80 mm / 0.6 rad), and the line restarts where the arm
    is: a fresh-clone main job once failed its homing that way with the arm 319 mm off the path.
    Rotation is slerped from the start orientation, so a tilted start is no jump either."""

    def __init__(
        self,
        start: np.ndarray,
        target: np.ndarray,
        speed: float = 0.12,
        angular_speed: float = 1.0,
        hz: float = 20.0,
        max_lag_m: float = 0.03,
        max_lag_rad: float = 0.2,
        restart_m: float = 0.05,
        restart_rad: float = 0.4,
    ):
        self.target = np.asarray(target, dtype=float)
        self.speed, self.angular_speed, self.hz = speed, angular_speed, hz
        self.max_lag_m, self.max_lag_rad = max_lag_m, max_lag_rad
        self.restart_m, self.restart_rad = restart_m, restart_rad
        self.restarts = 0
        self._restart(np.asarray(start, dtype=float))

    def _restart(self, start: np.ndarray) -> None:
        self.p0 = start[:3, 3].copy()
        self._slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([start[:3, :3], self.target[:3, :3]])))
        self.duration = max(
            float(np.linalg.norm(self.target[:3, 3] - self.p0)) / self.speed,
            rotation_angle(start[:3, :3], self.target[:3, :3]) / self.angular_speed,
            0.3,
        )
        self.s = 0.0
        self.pose = start.copy()

    @property
    def done(self) -> bool:
        return self.s >= 1.0

    def next(self, tcp: np.ndarray) -> np.ndarray:
        """The next target, given the measured TCP pose."""
        lag = float(np.linalg.norm(tcp[:3, 3] - self.pose[:3, 3]))
        lag_rad = rotation_angle(tcp[:3, :3], self.pose[:3, :3])
        if lag > self.restart_m or lag_rad > self.restart_rad:
            self.restarts += 1
            self._restart(np.asarray(tcp, dtype=float))
        elif lag < self.max_lag_m and lag_rad < self.max_lag_rad:
            self.s = min(1.0, self.s + 1.0 / (self.hz * self.duration))
        if self.done:
            self.pose = self.target.copy()
        else:
            self.pose = geometry.make_pose(
                self._slerp(self.s).as_matrix(), (1 - self.s) * self.p0 + self.s * self.target[:3, 3]
            )
        return self.pose


@dataclass(frozen=True)
class Keyframe:
    t: float  # seconds from plan start
    position: np.ndarray
    yaw: float
    width: float
    phase: str


@dataclass
class ExpertPlan:
    keyframes: list[Keyframe] = field(default_factory=list)

    @property
    def duration(self) -> float:
        return self.keyframes[-1].t

    def phase_at(self, t: float) -> str:
        for b in self.keyframes[1:]:
            if t < b.t:
                return b.phase
        return "done"

    def target_at(self, t: float) -> tuple[np.ndarray, float]:
        """(4x4 TCP target, gripper width) at plan time t (held at the ends)."""
        ks = self.keyframes
        if t <= ks[0].t:
            return tcp_pose(ks[0].position, ks[0].yaw), ks[0].width
        for a, b in itertools.pairwise(ks):
            if t < b.t:
                s = (t - a.t) / max(b.t - a.t, 1e-9)
                s = 0.5 - 0.5 * math.cos(math.pi * s)  # smooth start and stop of every segment
                pos = (1 - s) * a.position + s * b.position
                yaw = a.yaw + s * (b.yaw - a.yaw)
                # gripper width switches at the segment start (a grasp is a button press)
                return tcp_pose(pos, yaw), b.width
        return tcp_pose(ks[-1].position, ks[-1].yaw), ks[-1].width


def plan_pick_place(
    start: np.ndarray, start_width: float, block: np.ndarray, bowl: np.ndarray, block_height: float, cfg: ExpertConfig
) -> ExpertPlan:
    """Plan from the current TCP pose to the block (4x4), grasp, lift, over the bowl (4x4), release."""
    yaw0 = tcp_yaw(start)
    g_yaw = grasp_yaw(tcp_yaw(block), reference_yaw=0.0)
    block_xy, bowl_xy = block[:2, 3], bowl[:2, 3]
    grasp_z = max(cfg.grasp_height, block[2, 3] + block_height / 2 - 0.012)
    frames = [Keyframe(0.0, start[:3, 3].copy(), yaw0, start_width, "start")]

    def go(position, yaw, width, phase, speed, dwell=0.0):
        last = frames[-1]
        position = np.asarray(position, dtype=float)
        dist = float(np.linalg.norm(position - last.position))
        dyaw = abs(yaw - last.yaw)
        # cosine profile peaks at pi/2 x mean speed: stretch so the peak stays at `speed`
        dt = max(dist / speed * math.pi / 2, dyaw / cfg.yaw_speed * math.pi / 2, 0.2) + dwell
        frames.append(Keyframe(last.t + dt, position, yaw, width, phase))

    def wait(seconds, width, phase):
        last = frames[-1]
        frames.append(Keyframe(last.t + seconds, last.position, last.yaw, width, phase))

    above_block = [*block_xy, cfg.approach_height]
    go(above_block, g_yaw, cfg.open_width, "approach", cfg.speed)
    go([*block_xy, grasp_z + 0.03], g_yaw, cfg.open_width, "descend", cfg.speed)
    go([*block_xy, grasp_z], g_yaw, cfg.open_width, "descend", cfg.slow_speed)
    wait(cfg.settle_s, cfg.open_width, "settle")
    wait(cfg.gripper_wait_s, cfg.close_width, "grasp")
    go([*block_xy, cfg.lift_height], g_yaw, cfg.close_width, "lift", cfg.slow_speed * 2)
    go([*bowl_xy, cfg.lift_height], g_yaw, cfg.close_width, "transfer", cfg.speed)
    go([*bowl_xy, cfg.place_height], g_yaw, cfg.close_width, "lower", cfg.slow_speed * 2)
    wait(cfg.settle_s, cfg.close_width, "settle")
    wait(cfg.gripper_wait_s, cfg.open_width, "release")
    go([*bowl_xy, cfg.lift_height], g_yaw, cfg.open_width, "retreat", cfg.speed)
    return ExpertPlan(frames)


def object_poses_from_state(state: dict) -> tuple[np.ndarray, np.ndarray]:
    """4x4 block and bowl poses from twin_node's /twin/state (its ``objects``), to plan from."""
    out = []
    for body in ("block", "bowl"):
        obj = state["objects"][body]
        out.append(geometry.make_pose(geometry.rotz(obj["yaw"]), np.asarray(obj["xyz"], dtype=float)))
    return out[0], out[1]


@dataclass(frozen=True)
class ExpertResult:
    seed: int
    success: bool
    duration_s: float
    details: dict


def run_direct_episode(sim, seed: int, cfg: TwinConfig, max_extra_s: float = 3.0) -> ExpertResult:
    """Reset ``sim`` (a DirectSim) to ``seed``, move to the ready pose, run the plan, judge success."""
    from .scene import BLOCK, BOWL, body_pose

    sim.reset(seed)
    ex = cfg.expert
    ready = tcp_pose(ex.ready_position, 0.0)
    sim.command(ready, ex.open_width)
    sim.step(1500)
    plan = plan_pick_place(
        sim.tcp_pose(),
        sim.gripper_width(),
        body_pose(sim.model, sim.data, BLOCK),
        body_pose(sim.model, sim.data, BOWL),
        cfg.scene.block_size[2],
        ex,
    )
    t0 = sim.time
    control_dt = 1.0 / ex.command_hz
    steps = round(control_dt * 1000)
    while sim.time - t0 < plan.duration + max_extra_s:
        pose, width = plan.target_at(sim.time - t0)
        sim.command(pose, width)
        sim.step(steps)
        if sim.time - t0 > plan.duration and sim.success()["success"]:
            break
    details = sim.success()
    return ExpertResult(seed, bool(details["success"]), sim.time - t0, details)
