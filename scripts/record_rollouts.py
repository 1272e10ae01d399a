"""A policy's own roll-outs in the twin, every episode recorded, the scripted expert taking over a lost one.

    PYTHONPATH=src python scripts/record_rollouts.py POLICY.pt OUT_DIR --seed 5000 --episodes 24

The corrections round of ``bench corrections`` (``twin.corrections.corrected_rollouts``: in-process, on the sim
clock, the live stack's execution, the round's episode length and latency budget by default) for any policy file
and any scenes. The bags
hold the policy's frames and the expert's; ``equidiff distill --demos`` takes them beside the demos, so the
student learns the teacher's answers at the states its own closed loop reaches (docs/denoising_steps.md). Writes
OUT_DIR/*.mcap bags and OUT_DIR.json (one line per episode: seed, success, takeover).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path

from equidiff_core.benches.corrections import CorrectionsSettings
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.runtime.output_files import OutputExistsError, refuse_existing, write_output_text
from equidiff_core.twin.config import load_twin_job_configs
from equidiff_core.twin.corrections import LostRule, corrected_rollouts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("policy", type=Path, help="the policy file rolled out")
    parser.add_argument("out", type=Path, help="a new folder for the bags")
    parser.add_argument("--seed", type=int, default=5000, help="first scene seed (then +1 each)")
    parser.add_argument("--episodes", type=int, default=24)
    # the corrections round's own defaults, so that these roll-outs are that round's for another policy
    parser.add_argument("--max-duration", type=float, default=CorrectionsSettings.max_duration, help="seconds")
    parser.add_argument("--latency-ms", type=float, default=CorrectionsSettings.latency_ms)
    parser.add_argument("--lab-config", type=Path, default=None)
    parser.add_argument("--twin-config", type=Path, default=None)
    args = parser.parse_args()
    summary = args.out.with_name(args.out.name + ".json")
    for target in (args.out, summary):
        try:
            refuse_existing(target)
        except OutputExistsError:
            parser.error(f"{target} exists: name a new OUT_DIR")
    configs = load_twin_job_configs(args.lab_config, args.twin_config)
    policy = load_inference_policy(args.policy, device="cpu")
    seeds = range(args.seed, args.seed + args.episodes)
    episodes = corrected_rollouts(
        policy, configs.twin, configs.lab, seeds, args.out, LostRule(), args.max_duration, args.latency_ms / 1000
    )
    write_output_text(summary, json.dumps([asdict(e) for e in episodes], indent=1))


if __name__ == "__main__":
    main()
