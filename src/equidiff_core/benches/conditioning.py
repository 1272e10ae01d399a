"""Does a policy condition on its observation? The standard checks behind docs/model.md's baseline diagnosis.

A policy that ignores its voxels can still reach a fair noise loss: it predicts the average motion of
the demos. Two measurements tell it apart from one that looks:

* **features when the block moves**: the block's voxels (found by the twin block's colour) are moved
  by ``shift_vox`` voxels along +x, -x, +y and -y; the relative change of the voxel encoder's output
  ``||f(moved) - f(orig)|| / ||f(orig)||`` (and of each layer's, ``feature_change_by_layer``), beside
  how much that output varies across the scenes of different demos (``feature_spread``);
* **actions when the block moves**: the DDIM chunk from the same noise for both observations; how far
  the chunk's last step moves along the block's displacement, as a fraction of it (``action_follow``:
  1 for a chunk that ends where the moved block now is, 0 for one that does not look).

Frames are the first observation of each demo (the arm at its start pose, the block somewhere in the
region); the same frames, shifts and noise for every policy, so the numbers compare across policies.
``run_conditioning_check`` takes its ``ConditioningSettings`` and returns the JSON line as a dict, or raises
``BenchError``.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from equidiff_core.benches import BenchError
from equidiff_core.config import ConfigError, Workspace
from equidiff_core.data.dataset import find_episodes, load_episodes
from equidiff_core.data.episode_arrays import DatasetConfig
from equidiff_core.models.plain import EquiNoiseCore, to_escnn_layout
from equidiff_core.policy.augment import voxel_input
from equidiff_core.policy.diffusion import make_policy
from equidiff_core.policy.file import CheckpointError, export_policy
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.policy.normalizer import Normalizer
from equidiff_core.policy.presets import get_preset

# the twin block's colour (twin.config.SceneConfig.block_rgba: 0.85, 0.12, 0.1) as the cameras see it,
# shaded sides included: red at least 80 and twice green and blue; the bowl (blue), its mark (yellow:
# green close to red) and the table (brown: green ~0.8 red) fall outside
BLOCK_MIN_RED = 80
SHIFT_DIRECTIONS = ((1, 0), (-1, 0), (0, 1), (0, -1))


def block_mask(grid: np.ndarray) -> np.ndarray:
    """(R, R, R) bool: the occupied voxels of the uint8 grid (4, R, R, R) that have the block's colour."""
    occupied, r, g, b = grid[0] > 0, grid[1].astype(np.int32), grid[2].astype(np.int32), grid[3].astype(np.int32)
    return occupied & (r >= BLOCK_MIN_RED) & (r >= 2 * g) & (r >= 2 * b)


def move_block(grid: np.ndarray, shift: tuple[int, int, int]) -> np.ndarray | None:
    """The grid with the block's voxels moved by ``shift`` voxels (their old cells emptied, what they land
    on overwritten); None when no block is visible or it would leave the grid."""
    mask = block_mask(grid)
    idx = np.argwhere(mask)
    if len(idx) == 0:
        return None
    new = idx + np.asarray(shift)
    if new.min() < 0 or new.max() >= grid.shape[1]:
        return None
    values = grid[:, idx[:, 0], idx[:, 1], idx[:, 2]]
    moved = grid.copy()
    moved[:, idx[:, 0], idx[:, 1], idx[:, 2]] = 0
    moved[:, new[:, 0], new[:, 1], new[:, 2]] = values
    return moved


@torch.no_grad()
def layer_features(policy, grid: np.ndarray) -> list[np.ndarray]:
    """The voxel encoder's activations after each ReLU for one uint8 grid (4, R, R, R), of an
    ``policy.inference.InferencePolicy`` (fp32); the last is what the observation embedding (EquiDiff) or the
    U-Net's condition (baseline) gets."""
    vox = voxel_input(torch.from_numpy(np.ascontiguousarray(grid))[None], policy.preset.crop, "center")
    vox = vox.to(device=policy.device, dtype=policy.dtype)
    if policy.pad_channels:  # the fp32 CPU path pads the first convolution's input channels
        vox = torch.cat([vox, vox.new_zeros((1, policy.pad_channels, *vox.shape[2:]))], dim=1)
    net = policy.net
    x = to_escnn_layout(vox) if isinstance(net, EquiNoiseCore) else vox
    layers = []
    for module in net.encoder:
        x = module(x)
        if isinstance(module, torch.nn.ReLU):
            layers.append(x.flatten().float().cpu().numpy())
    return layers


def voxel_features(policy, grid: np.ndarray) -> np.ndarray:
    """The voxel encoder's output (``layer_features``' last)."""
    return layer_features(policy, grid)[-1]


def _relative_change(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(b - a) / max(np.linalg.norm(a), 1e-12))


@dataclass(frozen=True)
class Frame:
    grid: np.ndarray  # uint8 (4, R, R, R)
    ee: np.ndarray  # (10,) the gripper state


def first_frames(bags, resolution: int, log=None) -> list[Frame]:
    """The first observation of each episode in ``bags`` (bag folders or folders of them)."""
    episodes, _ = load_episodes(bags, DatasetConfig(resolution=resolution), log)
    return [Frame(ep.grid(0, resolution), ep.ee[0].astype(np.float32)) for ep in episodes]


def conditioning_response(policy, frames: list[Frame], shift_vox: int = 8, seed: int = 0) -> dict:
    """How ``policy`` (an fp32 ``policy.inference.InferencePolicy``) responds when the block moves; see the module doc."""
    if not frames:
        raise ValueError("no frames to measure on")
    voxel_m = policy.workspace.voxel_size
    per_frame = [layer_features(policy, f.grid) for f in frames]
    feats = [layers[-1] for layers in per_frame]
    mean = np.mean(feats, axis=0)
    spread = float(np.mean([np.linalg.norm(f - mean) for f in feats]) / max(np.linalg.norm(mean), 1e-12))
    changes, by_layer, follows, shifts_m, skipped = [], [], [], [], 0
    for frame, layers0 in zip(frames, per_frame):
        a0 = policy.predict(frame.grid, frame.ee, seed=seed)
        for dx, dy in SHIFT_DIRECTIONS:
            moved = move_block(frame.grid, (dx * shift_vox, dy * shift_vox, 0))
            if moved is None:
                skipped += 1
                continue
            layers1 = layer_features(policy, moved)
            by_layer.append([_relative_change(a, b) for a, b in zip(layers0, layers1)])
            changes.append(by_layer[-1][-1])
            a1 = policy.predict(moved, frame.ee, seed=seed)
            d = np.array([dx, dy], float) * shift_vox * voxel_m
            end_shift = a1[-1, :2] - a0[-1, :2]
            follows.append(float(end_shift @ d / (d @ d)))
            shifts_m.append(float(np.linalg.norm(end_shift)))
    if not changes:
        raise ValueError("the block was visible in none of the frames (or every shift left the grid)")
    return {
        "frames": len(frames),
        "moves": len(changes),
        "moves_skipped": skipped,
        "shift_m": round(shift_vox * voxel_m, 4),
        "feature_norm": round(float(np.mean([np.linalg.norm(f) for f in feats])), 5),
        "feature_change_block_moved": round(float(np.mean(changes)), 5),
        # the same after each conv's ReLU, first to last: where the block's signal fades
        "feature_change_by_layer": [float(f"{v:.2g}") for v in np.mean(by_layer, axis=0)],
        "feature_spread_across_scenes": round(spread, 5),
        "action_follow": round(float(np.mean(follows)), 3),
        "action_end_shift_m": round(float(np.mean(shifts_m)), 4),
    }


@dataclass(frozen=True)
class ConditioningSettings:
    """``equidiff check conditioning``'s settings: its arguments, same names (the command's help says more)."""

    policies: tuple[Path, ...]  # exported policy.pt files
    fresh: tuple[str, ...]  # untrained policies to build: NAME[:WIDTH[:INIT]]
    preset: str  # the preset of the ``fresh`` policies
    demos: Path  # demo bags (their first frames are measured)
    episodes: int  # how many of the demos
    shift_vox: int  # block displacement, voxels
    seed: int  # DDIM noise and the ``fresh`` weights


def run_conditioning_check(settings: ConditioningSettings) -> dict:
    """Every policy's response: the check's JSON line; BenchError (exit status 2) for bad input."""
    if not settings.policies and not settings.fresh:
        raise BenchError("name policy files or --fresh policies", 2)
    bags = find_episodes([settings.demos])[: settings.episodes]
    if not bags:
        raise BenchError(f"no demos in {settings.demos}", 2)
    results = {}
    with tempfile.TemporaryDirectory(prefix="conditioning_") as tmp:
        subjects = {str(path): path for path in settings.policies}
        for spec in settings.fresh:
            try:
                name, overrides = _fresh_spec(spec)
                preset = get_preset(settings.preset, **overrides)
            except (ValueError, ConfigError) as err:
                raise BenchError(f"--fresh {spec}: {err}", 2) from err
            torch.manual_seed(settings.seed)
            ws = Workspace()
            policy = make_policy(name, preset, ws)
            policy.set_normalizer(Normalizer.from_workspace(ws))
            subjects[f"fresh {spec}"] = export_policy(policy, Path(tmp) / f"{len(subjects)}.pt")
        frames = None
        for label, path in subjects.items():
            try:
                policy = load_inference_policy(path, precision="fp32")
            except CheckpointError as err:
                raise BenchError(str(err), 2) from err
            frames = frames or first_frames(bags, policy.workspace.resolution)
            results[label] = conditioning_response(policy, frames, settings.shift_vox, settings.seed)
            results[label]["weights_sha256"] = policy.weights_sha256  # verified at load, or "unhashed"
    return {"policies": results, "demos": len(bags), "shift_vox": settings.shift_vox, "seed": settings.seed}


def _fresh_spec(spec: str) -> tuple[str, dict]:
    """ "baseline:128:he" -> ("baseline", preset overrides); width "matched": the parameter-matched channels."""
    name, *rest = spec.split(":")
    if name not in ("equidiff", "baseline") or len(rest) > 2 or (rest and name != "baseline"):
        raise ValueError("expected equidiff, baseline or baseline:WIDTH[:INIT]")
    overrides = {}
    if rest:
        overrides["baseline_width"] = None if rest[0] == "matched" else int(rest[0])
    if len(rest) == 2:
        overrides["baseline_init"] = rest[1]
    return name, overrides
