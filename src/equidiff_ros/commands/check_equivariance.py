"""`equidiff check equivariance`: the noise predictor's equivariance error over C4 and C8.

Prints one JSON line: ``preset``, ``policy``, ``c4_max_rel_err`` (exact for EquiDiff: ~1e-7),
``c8_max_rel_err`` (all non-identity elements; the odd ones resample the voxel grid at 45 deg),
``per_element``, and with ``--sampling`` the same for full DDIM sampling from rotated noise.
Random weights by default; ``--checkpoint`` measures a trained ``last.ckpt``.
"""

from __future__ import annotations

import json


def add_arguments(parser) -> None:
    parser.add_argument("--preset", default="compact", help="paper | compact | tiny (ignored with --checkpoint)")
    parser.add_argument("--policy", default="equidiff", choices=["equidiff", "baseline"])
    parser.add_argument("--control", default="absolute", choices=["absolute", "relative"])
    parser.add_argument("--checkpoint", default=None, help="a training checkpoint (last.ckpt) to measure instead")
    parser.add_argument("--batch", type=int, default=2, help="random observations per group element")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sampling", action="store_true", help="also measure DDIM sampling equivariance")


def run(args) -> int:
    import torch

    from equidiff_core.config import Workspace
    from equidiff_core.inference import CheckpointError
    from equidiff_core.models import equivariance
    from equidiff_core.normalizer import Normalizer
    from equidiff_core.policies import make_policy
    from equidiff_core.presets import get_preset
    from equidiff_core.training import load_policy_from_checkpoint

    torch.manual_seed(args.seed)
    if args.checkpoint:
        try:
            policy = load_policy_from_checkpoint(args.checkpoint)
        except CheckpointError as err:
            print(f"equidiff check equivariance: {err}", flush=True)
            return 2
    else:
        ws = Workspace()
        policy = make_policy(args.policy, get_preset(args.preset, control=args.control), ws)
        policy.set_normalizer(Normalizer.from_workspace(ws))
    policy.eval()
    report = equivariance.group_report(policy, batch=args.batch, seed=args.seed)
    out = {"preset": policy.preset.name, "policy": policy.name, "control": policy.preset.control,
           "group": f"C{policy.preset.group_order}", "c4_max_rel_err": report["c4_max_rel_err"],
           "c8_max_rel_err": report["c8_max_rel_err"], "per_element": report["per_element"]}
    if args.sampling:
        samp = equivariance.group_report(policy, batch=1, seed=args.seed, sampling=True)
        out["sampling_c4_max_rel_err"] = samp["c4_max_rel_err"]
        out["sampling_c8_max_rel_err"] = samp["c8_max_rel_err"]
    print(json.dumps(out), flush=True)
    return 0
