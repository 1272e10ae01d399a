"""`equidiff check conditioning`: does a policy look at its observation? Features and actions when the block moves.

    equidiff check conditioning gen/equidiff/policy.pt gen/baseline/policy.pt --demos gen/demos --episodes 10
    equidiff check conditioning --fresh equidiff baseline baseline:matched:torch --demos gen/demos   # at init

The first observation of each of ``--episodes`` demos, the block's voxels moved by ``--shift-vox``
voxels along +-x and +-y; per policy: the voxel encoder's relative feature change, the feature
spread across the demos' scenes, and how far the DDIM chunk's end follows the block
(``equidiff_core.benches.conditioning``). Prints one JSON line: ``{"policies": {label: {...}},
"demos", "shift_vox", "seed"}``.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path


def add_arguments(parser) -> None:
    parser.add_argument("policies", nargs="*", type=Path, help="exported policy.pt files")
    parser.add_argument(
        "--fresh",
        nargs="+",
        default=[],
        metavar="NAME[:WIDTH[:INIT]]",
        help="also measure freshly initialised policies (seeded, --preset): equidiff, baseline, or a baseline of "
        "another encoder width and init, e.g. baseline:128:torch; baseline:matched:torch is the baseline of the "
        "checkpoints trained before baseline_width existed",
    )
    parser.add_argument("--preset", default="compact", help="preset of --fresh policies")
    parser.add_argument("--demos", type=Path, required=True, help="demo bags (their first frames are measured)")
    parser.add_argument("--episodes", type=int, default=10, help="how many of the demos")
    parser.add_argument("--shift-vox", type=int, default=8, help="block displacement in voxels (8 = 5 cm)")
    parser.add_argument("--seed", type=int, default=0, help="DDIM noise and --fresh weights")


def run(args) -> int:
    import torch

    from equidiff_core.benches.conditioning import conditioning_response, first_frames
    from equidiff_core.config import ConfigError, Workspace
    from equidiff_core.dataset import find_episodes
    from equidiff_core.inference import CheckpointError, export_policy, load_inference_policy
    from equidiff_core.normalizer import Normalizer
    from equidiff_core.policies import make_policy
    from equidiff_core.presets import get_preset

    if not args.policies and not args.fresh:
        print("equidiff check conditioning: name policy files or --fresh policies", file=sys.stderr)
        return 2
    bags = find_episodes([args.demos])[: args.episodes]
    if not bags:
        print(f"equidiff check conditioning: no demos in {args.demos}", file=sys.stderr)
        return 2
    results = {}
    with tempfile.TemporaryDirectory(prefix="conditioning_") as tmp:
        subjects = {str(path): path for path in args.policies}
        for spec in args.fresh:
            try:
                name, overrides = _fresh_spec(spec)
                preset = get_preset(args.preset, **overrides)
            except (ValueError, ConfigError) as err:
                print(f"equidiff check conditioning: --fresh {spec}: {err}", file=sys.stderr)
                return 2
            torch.manual_seed(args.seed)
            ws = Workspace()
            policy = make_policy(name, preset, ws)
            policy.set_normalizer(Normalizer.from_workspace(ws))
            subjects[f"fresh {spec}"] = export_policy(policy, Path(tmp) / f"{len(subjects)}.pt")
        frames = None
        for label, path in subjects.items():
            try:
                policy = load_inference_policy(path, precision="fp32")
            except CheckpointError as err:
                print(f"equidiff check conditioning: {err}", file=sys.stderr)
                return 2
            frames = frames or first_frames(bags, policy.workspace.resolution)
            results[label] = conditioning_response(policy, frames, args.shift_vox, args.seed)
    print(json.dumps({"policies": results, "demos": len(bags), "shift_vox": args.shift_vox, "seed": args.seed}))
    return 0


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
