"""Closed-loop evaluation of a policy in the twin, in-process on the sim clock.

Used by ``equidiff bench generalization``: the same scene, cameras (rendered from the sim
state), voxeliser and inference code as the live stack, but stepped synchronously, so the
result does not depend on how fast this machine is. Like diffusion_policy's and EquiDiff's
simulation evaluations, each observation's first ``n_action_steps`` actions are executed
(at the policy's dt, linearly interpolated at 20 Hz, as franka_node does) before the next
observation; the gripper follows each step's width.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from .. import geometry
from ..config import LabConfig
from .config import TwinConfig
from .scene import BLOCK, BOWL, body_pose, sample_scene


@dataclass(frozen=True)
class EvalEpisode:
    seed: int
    success: bool
    duration_s: float
    observations: int
    block_yaw_deg: float
    # how far a failure got: the stages of the task the episode reached at some point
    reached: bool = False  # the TCP within REACH_M of the block (horizontally) and below LOW_M above it
    lifted: bool = False  # the block LIFT_M above where it started
    closest_to_bowl_m: float = float("nan")  # nearest the block's centre came to the bowl's axis
    closest_to_block_m: float = float("nan")  # nearest the TCP came to the block's centre


REACH_M, LOW_M, LIFT_M = 0.02, 0.03, 0.03


class _Progress:
    """Tracks the stages an episode reaches, from the sim's block, bowl and TCP poses."""

    def __init__(self, sim):
        self.sim = sim
        self.block_z0 = self._position(BLOCK)[2]
        self.reached = self.lifted = False
        self.closest_to_bowl_m = self.closest_to_block_m = float("inf")

    def _position(self, body: str) -> np.ndarray:
        return body_pose(self.sim.model, self.sim.data, body)[:3, 3]

    def update(self) -> None:
        block, bowl, tcp = self._position(BLOCK), self._position(BOWL), self.sim.tcp_pose()[:3, 3]
        self.reached |= bool(np.hypot(*(tcp[:2] - block[:2])) < REACH_M and tcp[2] - block[2] < LOW_M)
        self.lifted |= bool(block[2] - self.block_z0 > LIFT_M)
        self.closest_to_bowl_m = min(self.closest_to_bowl_m, float(np.hypot(*(block[:2] - bowl[:2]))))
        self.closest_to_block_m = min(self.closest_to_block_m, float(np.linalg.norm(tcp - block)))


def evaluate_policy(policy, cfg: TwinConfig, lab: LabConfig, seeds: Iterable[int], max_duration_s: float = 30.0,
                    log: Callable[[str], None] = print, recorder=None) -> list[EvalEpisode]:
    """Roll ``policy`` (an ``inference.InferencePolicy``) out from each seed's scene; returns per-episode results."""
    from .demos import DirectRecorder
    from .expert import tcp_pose

    rec = recorder or DirectRecorder(cfg, lab)
    sim, ex = rec.sim, cfg.expert
    dt = float(policy.preset.dt)
    n_exec = int(policy.preset.n_action_steps)
    sub = max(1, int(round(dt * ex.command_hz)))  # 20 Hz targets between policy steps
    results = []
    try:
        for seed in seeds:
            poses = sim.reset(seed)
            sim.command(tcp_pose(ex.ready_position, 0.0), ex.open_width)
            sim.step(1500)
            t0, n_obs, success_since, ok = sim.time, 0, None, False
            progress = _Progress(sim)
            while sim.time - t0 < max_duration_s and not ok:
                grid = rec.voxel_grid(int((sim.time - t0) * 1e9))
                ee = geometry.pose_to_action(sim.tcp_pose(), np.asarray(sim.gripper_width()))
                actions = policy.predict(grid, ee.astype(np.float32), seed=seed * 1000 + n_obs)[:n_exec]
                n_obs += 1
                poses_a, widths = geometry.action_to_pose(actions)
                prev = sim.tcp_pose()
                for pose, width in zip(poses_a, widths):
                    for k in range(1, sub + 1):
                        s = k / sub
                        target = prev.copy()
                        target[:3, 3] = (1 - s) * prev[:3, 3] + s * pose[:3, 3]
                        target[:3, :3] = pose[:3, :3] if s >= 0.5 else prev[:3, :3]
                        sim.command(target, float(np.clip(width, 0.0, 0.08)))
                        sim.step(int(round(1000 * dt / sub)))
                    prev = pose
                    progress.update()
                    if sim.success()["success"]:
                        success_since = sim.time if success_since is None else success_since
                        if sim.time - success_since >= cfg.success.hold_s:
                            ok = True
                            break
                    else:
                        success_since = None
            results.append(EvalEpisode(seed, ok, round(sim.time - t0, 2), n_obs,
                                       round(float(np.degrees(poses.block_yaw)), 1), progress.reached,
                                       progress.lifted, round(progress.closest_to_bowl_m, 3),
                                       round(progress.closest_to_block_m, 3)))
            log(f"[eval] seed {seed} (block yaw {np.degrees(poses.block_yaw):+.0f} deg): "
                f"{'success' if ok else 'failure'} after {sim.time - t0:.1f} s sim, {n_obs} observations; "
                f"TCP within {progress.closest_to_block_m * 1000:.0f} mm of the block, "
                f"reached it: {'yes' if progress.reached else 'no'}, lifted it: "
                f"{'yes' if progress.lifted else 'no'}, block came within {progress.closest_to_bowl_m * 1000:.0f} mm "
                f"of the bowl's centre")
    finally:
        if recorder is None:
            rec.close()
    return results


def unseen_yaw_seeds(cfg: TwinConfig, train_yaw_deg: tuple[float, float], n: int, start: int = 10_000_000,
                     margin_deg: float = 15.0) -> list[int]:
    """Seeds whose block yaw lies at least ``margin_deg`` outside the training range, modulo 180 deg.

    The block is a box grasped across its short side: at yaw and yaw + 180 deg it looks and is
    grasped the same, so a yaw 180 deg from the training range is not unseen. The bowl is a
    ring of ``bowl_segments`` walls, the same every 360/segments deg (22.5 for 16), so no bowl
    yaw is unseen by a 15 deg margin and it is left free."""
    lo, hi = train_yaw_deg
    centre, half = (lo + hi) / 2, (hi - lo) / 2 + margin_deg
    if half >= 90.0:
        raise ValueError(f"training yaw range {train_yaw_deg} plus a {margin_deg} deg margin leaves no unseen block yaw")
    return _seeds_where(cfg, n, start, lambda yaw: abs(block_yaw_offset_deg(yaw, centre)) > half)


def in_range_yaw_seeds(cfg: TwinConfig, train_yaw_deg: tuple[float, float], n: int,
                       start: int = 20_000_000) -> list[int]:
    """Seeds whose block yaw lies inside the training range (modulo 180 deg, as above): the
    control for ``unseen_yaw_seeds`` (a policy that fails here has not learned the task)."""
    lo, hi = train_yaw_deg
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    return _seeds_where(cfg, n, start, lambda yaw: abs(block_yaw_offset_deg(yaw, centre)) <= half)


def _seeds_where(cfg: TwinConfig, n: int, start: int, keep: Callable[[float], bool]) -> list[int]:
    """The first ``n`` seeds from ``start`` whose scene's block yaw passes ``keep``."""
    seeds, seed = [], start
    while len(seeds) < n:
        if seed - start > 10_000 + 1_000 * n:
            raise ValueError(f"only {len(seeds)} of {n} scenes from seed {start} have such a block yaw "
                             f"(is the yaw range empty?)")
        if keep(sample_scene(cfg.scene, seed).block_yaw):
            seeds.append(seed)
        seed += 1
    return seeds


def block_yaw_offset_deg(yaw_rad: float, centre_deg: float = 0.0) -> float:
    """Block yaw minus ``centre_deg``, wrapped to [-90, 90): the box's half-turn symmetry."""
    return float((np.degrees(yaw_rad) - centre_deg + 90.0) % 180.0 - 90.0)
