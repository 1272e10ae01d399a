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


@dataclass(frozen=True)
class EvalEpisode:
    seed: int
    success: bool
    duration_s: float
    observations: int
    block_yaw_deg: float


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
                    if sim.success()["success"]:
                        success_since = sim.time if success_since is None else success_since
                        if sim.time - success_since >= cfg.success.hold_s:
                            ok = True
                            break
                    else:
                        success_since = None
            results.append(EvalEpisode(seed, ok, round(sim.time - t0, 2), n_obs,
                                       round(float(np.degrees(poses.block_yaw)), 1)))
            log(f"[eval] seed {seed} (block yaw {np.degrees(poses.block_yaw):+.0f} deg): "
                f"{'success' if ok else 'failure'} after {sim.time - t0:.1f} s sim, {n_obs} observations")
    finally:
        if recorder is None:
            rec.close()
    return results


def unseen_yaw_seeds(cfg: TwinConfig, train_yaw_deg: tuple[float, float], n: int, start: int = 10_000_000,
                     margin_deg: float = 15.0) -> list[int]:
    """Seeds whose block *and* bowl yaw (full-circle draw) lie at least ``margin_deg`` outside the training range."""
    from .scene import sample_scene

    lo, hi = train_yaw_deg
    centre, half = (lo + hi) / 2, (hi - lo) / 2 + margin_deg

    def unseen(yaw_rad: float) -> bool:
        d = (np.degrees(yaw_rad) - centre + 180) % 360 - 180
        return abs(d) > half

    seeds, seed = [], start
    while len(seeds) < n:
        p = sample_scene(cfg.scene, seed)
        if unseen(p.block_yaw) and unseen(p.bowl_yaw):
            seeds.append(seed)
        seed += 1
    return seeds
