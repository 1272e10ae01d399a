"""C4 and 45 deg equivariance errors of every inference path on twin-like scenes (``equidiff check equivariance``;
the command's help text lists the subjects and the JSON keys; the measurement is ``models.equivariance``)."""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import torch

from equidiff_core.config import Workspace
from equidiff_core.inference import (
    CheckpointError,
    CheckpointFormatError,
    export_policy,
    load_inference_policy,
    read_policy_file,
)
from equidiff_core.machine import cpu_description
from equidiff_core.models import equivariance
from equidiff_core.normalizer import Normalizer
from equidiff_core.policies import make_policy
from equidiff_core.presets import get_preset
from equidiff_core.training import load_policy_from_checkpoint
from equidiff_core.twin.config import load_twin_config


def load_subjects(args, export_dir):
    """(training-time policy or None, path of its exported policy file); CheckpointError for a bad file."""
    if not args.checkpoint:
        ws = Workspace()
        policy = make_policy(args.policy, get_preset(args.preset, control=args.control), ws)
        policy.set_normalizer(Normalizer.from_workspace(ws))
        return policy.eval(), export_policy(policy, export_dir / "policy.pt")
    try:
        config, _ = read_policy_file(args.checkpoint)
    except CheckpointFormatError:  # not an exported file: a training checkpoint (or an error saying why not)
        policy = load_policy_from_checkpoint(args.checkpoint)
        return policy.eval(), export_policy(policy, export_dir / "policy.pt")
    if config.get("policy") == "baseline":  # exported baseline weights are its training-time weights
        return load_policy_from_checkpoint(args.checkpoint).eval(), args.checkpoint
    return None, args.checkpoint  # an exported EquiDiff holds expanded plain filters, no escnn weights


def run_equivariance_check(args) -> int:
    """``equidiff check equivariance`` for its parsed arguments: one JSON line; 2 for a bad checkpoint."""
    torch.manual_seed(args.seed)
    with tempfile.TemporaryDirectory(prefix="check_equivariance_") as tmp:
        try:
            policy, exported = load_subjects(args, Path(tmp))
            fp32 = load_inference_policy(exported, precision="fp32", jit=True)
            bf16 = load_inference_policy(exported, precision="bf16", jit=True)
        except CheckpointError as err:
            print(f"equidiff check equivariance: {err}", file=sys.stderr, flush=True)
            return 2
    preset, workspace = fp32.preset, fp32.workspace
    voxels, ee = equivariance.twin_scenes(preset, workspace, args.scenes, args.seed, scene=load_twin_config().scene)

    def measure(subject):
        return equivariance.measure(subject, voxels, ee, timestep=args.timestep, seed=args.seed)

    out = {
        "preset": preset.name,
        "policy": fp32.name,
        "control": preset.control,
        "weights": args.checkpoint or "random",
        "weights_sha256": fp32.weights_sha256,  # of the plain weights checked (verified at load), or "unhashed"
        "scenes": args.scenes,
        "timestep": args.timestep,
        "escnn": measure(equivariance.TrainingModel(policy)) if policy is not None else None,
        "exported_fp32": measure(equivariance.ExportedModel(fp32)),
        "exported_bf16": measure(equivariance.ExportedModel(bf16)),
    }
    if fp32.name != "baseline":
        torch.manual_seed(args.seed)
        baseline = make_policy("baseline", preset, workspace)
        baseline.set_normalizer(fp32.normalizer)
        out["baseline"] = {"weights": "random", **measure(equivariance.TrainingModel(baseline))}
    out["cpu"] = cpu_description()
    print(json.dumps(out), flush=True)
    return 0
