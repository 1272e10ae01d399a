"""How near a policy's weights land, through few-step timestep schedules, to their own DDIM-16 chunk.

    PYTHONPATH=src python scripts/sampler_gap.py checkpoints/twin_compact/policy.pt --demos DEMO... [--frames 110]

On ``--frames`` frames spread evenly over the demos (the observation policy_node would feed, the centred crop),
each sampler denoises the same ``--noises`` noise draws (``predict_samples`` with the same seed draws the same
rows whatever the sampler) and is compared with the policy's own sampler: the mean distance of the executed
steps' TCP positions (the preset's ``n_action_steps``) and of their gripper widths, in millimetres. A sampler
with no gap takes the teacher's chunk; the open loop cannot say more (the closed loop: ``equidiff bench steps``).
One JSON line per sampler, nearest first: the default samplers are every four-step schedule from t = 90 ending
at t = 0, 2 or 4 on a grid (how ``training.distill.STUDENT_TIMESTEPS`` was chosen: docs/denoising_steps.md,
"Which four timesteps"), then the evenly spaced four steps from t = 90 and DDIM-8 with the "leading" spacing.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from equidiff_core.data.dataset import DemoDataset, load_episodes
from equidiff_core.data.episode_arrays import DatasetConfig
from equidiff_core.policy.inference import load_inference_policy

GRID = [(90, a, b, c) for a in (36, 42, 48, 54, 60) for b in (6, 9, 12, 15, 18, 24) for c in (0, 2, 4) if c < b]
OTHERS = [(90, 65, 40, 15), (90, 78, 66, 54, 42, 30, 18, 6)]  # evenly spaced from 90; DDIM-8 "leading"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("policy", type=Path, help="a policy file (its own sampler is the reference)")
    parser.add_argument("--demos", type=Path, nargs="+", required=True, help="demo bags or folders")
    parser.add_argument("--frames", type=int, default=110, help="frames, spread evenly over the demos")
    parser.add_argument("--noises", type=int, default=4, help="noise draws per frame, the same for every sampler")
    parser.add_argument(
        "--schedules", nargs="+", default=None, help="timesteps as 90,60,12,0 (default: the grid and two others)"
    )
    args = parser.parse_args()
    schedules = [tuple(int(t) for t in s.split(",")) for s in args.schedules] if args.schedules else GRID + OTHERS

    reference = load_inference_policy(args.policy)
    samplers = {s: load_inference_policy(args.policy, timesteps=s) for s in schedules}
    episodes, _ = load_episodes(args.demos, DatasetConfig())
    frames = DemoDataset(episodes, DatasetConfig())
    picked = np.linspace(0, len(frames) - 1, min(args.frames, len(frames))).round().astype(int)
    steps = reference.preset.n_action_steps
    gaps = {s: {"position": [], "width": []} for s in schedules}
    for seed, i in enumerate(picked):
        frame = frames[int(i)]
        voxels, ee = frame["voxels"].numpy()[-1], frame["ee"].numpy()[-1]
        ref = reference.predict_samples(voxels, ee, args.noises, seed=seed)[:, :steps]
        for s, policy in samplers.items():
            out = policy.predict_samples(voxels, ee, args.noises, seed=seed)[:, :steps]
            gaps[s]["position"].append(1000 * np.linalg.norm(out[..., :3] - ref[..., :3], axis=-1).mean())
            gaps[s]["width"].append(1000 * np.abs(out[..., 9] - ref[..., 9]).mean())
    rows = [
        {
            "timesteps": list(s),
            "steps": len(s),
            "position_gap_mm": round(float(np.mean(g["position"])), 2),
            "width_gap_mm": round(float(np.mean(g["width"])), 2),
        }
        for s, g in gaps.items()
    ]
    common = {"policy": str(args.policy), "frames": len(picked), "noises": args.noises, "executed_steps": steps}
    for row in sorted(rows, key=lambda r: r["position_gap_mm"] + r["width_gap_mm"]):
        print(json.dumps({**row, **common}))


if __name__ == "__main__":
    main()
