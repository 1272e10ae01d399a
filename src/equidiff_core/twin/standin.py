"""An *untrained* policy file for smoke-testing the main job's plumbing when no trained one exists.

Its weights are random; only its normaliser is fitted (to scripted-expert trajectories of the
twin task, so its outputs stay in the workspace). Everything that reports on it says so.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import geometry
from ..config import Workspace
from .config import TwinConfig
from .expert import plan_pick_place, tcp_pose
from .scene import sample_scene

STANDIN_LABEL = "untrained stand-in (random weights; plumbing smoke test only)"


def expert_actions(cfg: TwinConfig, seeds=range(8), dt: float = 0.2) -> np.ndarray:
    """(N, 10) absolute actions along scripted-expert plans (no simulation needed)."""
    out = []
    ex = cfg.expert
    for seed in seeds:
        p = sample_scene(cfg.scene, seed)
        block = tcp_pose((*p.block_xy, cfg.scene.block_size[2] / 2), p.block_yaw) @ np.diag([1, -1, -1, 1])
        bowl = geometry.make_pose(geometry.rotz(p.bowl_yaw), np.array([*p.bowl_xy, 0.0]))
        plan = plan_pick_place(
            tcp_pose(ex.ready_position, 0.0), ex.open_width, block, bowl, cfg.scene.block_size[2], ex
        )
        for t in np.arange(0.0, plan.duration, dt):
            pose, width = plan.target_at(t)
            out.append(geometry.pose_to_action(pose, np.asarray(width)))
    return np.asarray(out, dtype=np.float32)


def make_standin_policy(
    path: str | Path,
    workspace: Workspace,
    preset: str = "tiny",
    policy: str = "equidiff",
    cfg: TwinConfig | None = None,
    seed: int = 0,
) -> Path:
    import torch

    from ..policy.diffusion import make_policy
    from ..policy.file import export_policy
    from ..policy.normalizer import Normalizer
    from ..policy.presets import get_preset

    torch.manual_seed(seed)
    actions = expert_actions(cfg or TwinConfig())
    model = make_policy(policy, get_preset(preset), workspace)
    model.set_normalizer(Normalizer.fit(actions, actions, workspace))
    return export_policy(model, path)
