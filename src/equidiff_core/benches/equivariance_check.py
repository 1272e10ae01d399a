"""C4 and 45 deg equivariance errors of every inference path on twin-like scenes (``equidiff check equivariance``;
the command's help text lists the subjects and the JSON keys; the measurement is ``models.equivariance``).
``run_equivariance_check`` takes its ``EquivarianceSettings`` and returns the JSON line as a dict, or raises
``BenchError``."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import torch

from equidiff_core.benches import BenchError
from equidiff_core.config import Workspace
from equidiff_core.models import equivariance
from equidiff_core.policy.diffusion import make_policy
from equidiff_core.policy.file import CheckpointError, CheckpointFormatError, export_policy, read_policy_file
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.policy.normalizer import Normalizer
from equidiff_core.policy.presets import get_preset
from equidiff_core.runtime.machine import cpu_description
from equidiff_core.training.loop import load_policy_from_checkpoint
from equidiff_core.twin.config import load_twin_config


@dataclass(frozen=True)
class EquivarianceSettings:
    """``equidiff check equivariance``'s settings: its flags, same names (the command's help says more)."""

    preset: str  # the random-weight policy's preset (ignored with ``checkpoint``)
    policy: str  # equidiff or baseline (ignored with ``checkpoint``)
    control: str  # absolute or relative
    checkpoint: str | None  # a training last.ckpt or an exported policy.pt, as given (None: random weights)
    scenes: int  # twin-like scenes per group element
    timestep: int  # the diffusion step at which the denoiser is compared
    seed: int


def load_subjects(settings: EquivarianceSettings, export_dir):
    """(training-time policy or None, path of its exported policy file); CheckpointError for a bad file."""
    if not settings.checkpoint:
        ws = Workspace()
        policy = make_policy(settings.policy, get_preset(settings.preset, control=settings.control), ws)
        policy.set_normalizer(Normalizer.from_workspace(ws))
        return policy.eval(), export_policy(policy, export_dir / "policy.pt")
    try:
        config, _ = read_policy_file(settings.checkpoint)
    except CheckpointFormatError:  # not an exported file: a training checkpoint (or an error saying why not)
        policy = load_policy_from_checkpoint(settings.checkpoint)
        return policy.eval(), export_policy(policy, export_dir / "policy.pt")
    if config.get("policy") == "baseline":  # exported baseline weights are its training-time weights
        return load_policy_from_checkpoint(settings.checkpoint).eval(), settings.checkpoint
    return None, settings.checkpoint  # an exported EquiDiff holds expanded plain filters, no escnn weights


def run_equivariance_check(settings: EquivarianceSettings) -> dict:
    """The errors of every subject: the check's JSON line; BenchError (exit status 2) for a bad checkpoint."""
    torch.manual_seed(settings.seed)
    with tempfile.TemporaryDirectory(prefix="check_equivariance_") as tmp:
        try:
            policy, exported = load_subjects(settings, Path(tmp))
            fp32 = load_inference_policy(exported, precision="fp32", jit=True)
            bf16 = load_inference_policy(exported, precision="bf16", jit=True)
        except CheckpointError as err:
            raise BenchError(str(err), 2) from err
    preset, workspace = fp32.preset, fp32.workspace
    voxels, ee = equivariance.twin_scenes(
        preset, workspace, settings.scenes, settings.seed, scene=load_twin_config().scene
    )

    def measure(subject):
        return equivariance.measure(subject, voxels, ee, timestep=settings.timestep, seed=settings.seed)

    out = {
        "preset": preset.name,
        "policy": fp32.name,
        "control": preset.control,
        "weights": settings.checkpoint or "random",
        "weights_sha256": fp32.weights_sha256,  # of the plain weights checked (verified at load), or "unhashed"
        "scenes": settings.scenes,
        "timestep": settings.timestep,
        "escnn": measure(equivariance.TrainingModel(policy)) if policy is not None else None,
        "exported_fp32": measure(equivariance.ExportedModel(fp32)),
        "exported_bf16": measure(equivariance.ExportedModel(bf16)),
    }
    if fp32.name != "baseline":
        torch.manual_seed(settings.seed)
        baseline = make_policy("baseline", preset, workspace)
        baseline.set_normalizer(fp32.normalizer)
        out["baseline"] = {"weights": "random", **measure(equivariance.TrainingModel(baseline))}
    out["cpu"] = cpu_description()
    return out
