"""`equidiff check equivariance`: C4 and 45 deg equivariance errors on twin-like scenes, every inference path.

EquiDiff is exactly C4-equivariant and only approximately C8 (a 3^3 kernel on a cubic grid is
exact under 90 deg rotations, not 45 deg ones); this command measures both, on scenes built
from the twin's objects (``models.equivariance.twin_scenes``), for the denoiser output at one
diffusion step and for the full DDIM-sampled actions from fixed noise.

Prints one JSON line: ``preset``, ``policy``, ``control``, ``weights`` (``random`` or the
checkpoint's path), ``scenes``, ``timestep``, ``cpu`` and, per subject, ``{"denoiser": S,
"sampling": S}`` with S = ``{"c4_max_rel_err" (90/180/270 deg), "rot45_max_rel_err" (45/135/225/315
deg), "per_element"}``:

* ``escnn``: the training-time model (escnn for EquiDiff; null for an exported EquiDiff file,
  which holds no escnn weights);
* ``exported_fp32`` / ``exported_bf16``: the exported plain-torch policy (``inference``), traced,
  as the policy node runs it (bf16 is emulated, hence slow, on CPUs without native bf16);
* ``baseline``: DiffPo-C with random weights, same preset and normaliser, in the same run, so the
  contrast is visible (absent when the subject is the baseline already).

Random weights by default; ``--checkpoint`` measures a training ``last.ckpt`` or an exported ``policy.pt``.
"""

from __future__ import annotations

import json
import sys


def add_arguments(parser) -> None:
    parser.add_argument("--preset", default="compact", help="paper | compact | tiny (ignored with --checkpoint)")
    parser.add_argument(
        "--policy", default="equidiff", choices=["equidiff", "baseline"], help="ignored with --checkpoint"
    )
    parser.add_argument("--control", default="absolute", choices=["absolute", "relative"])
    parser.add_argument("--checkpoint", default=None, help="a training checkpoint (last.ckpt) or exported policy.pt")
    parser.add_argument("--scenes", type=int, default=2, help="twin-like scenes per group element")
    parser.add_argument("--timestep", type=int, default=10, help="diffusion step at which the denoiser is compared")
    parser.add_argument("--seed", type=int, default=0)


def load_subjects(args, export_dir):
    """(training-time policy or None, path of its exported policy file); CheckpointError for a bad file."""
    from equidiff_core.config import Workspace
    from equidiff_core.inference import CheckpointError, export_policy, read_policy_file
    from equidiff_core.normalizer import Normalizer
    from equidiff_core.policies import make_policy
    from equidiff_core.presets import get_preset
    from equidiff_core.training import load_policy_from_checkpoint

    if not args.checkpoint:
        ws = Workspace()
        policy = make_policy(args.policy, get_preset(args.preset, control=args.control), ws)
        policy.set_normalizer(Normalizer.from_workspace(ws))
        return policy.eval(), export_policy(policy, export_dir / "policy.pt")
    try:
        config, _ = read_policy_file(args.checkpoint)
    except CheckpointError:  # not an exported file: a training checkpoint (or an error saying why not)
        policy = load_policy_from_checkpoint(args.checkpoint)
        return policy.eval(), export_policy(policy, export_dir / "policy.pt")
    if config.get("policy") == "baseline":  # exported baseline weights are its training-time weights
        return load_policy_from_checkpoint(args.checkpoint).eval(), args.checkpoint
    return None, args.checkpoint  # an exported EquiDiff holds expanded plain filters, no escnn weights


def run(args) -> int:
    import tempfile
    from pathlib import Path

    import torch

    from equidiff_core.inference import CheckpointError, load_inference_policy
    from equidiff_core.machine import cpu_description
    from equidiff_core.models import equivariance
    from equidiff_core.policies import make_policy
    from equidiff_core.twin.config import load_twin_config

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
