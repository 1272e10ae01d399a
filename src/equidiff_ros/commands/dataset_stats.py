"""`equidiff dataset stats BAGS...`: episodes, durations, steps, samples, action ranges, and the corrections of a
policy's roll-outs (docs/corrections.md).

Bad bags (truncated, killed recordings, damaged bytes caught by a CRC, missing topics) are
listed with the reason and make the command exit 1, so a script never trains on a silently
shrunken or altered set; so does a folder with no episodes at all. Bags stored without CRCs read,
and are counted as "unchecked".
"""

from __future__ import annotations

import json
import sys

from equidiff_core.data.dataset import dataset_stats
from equidiff_core.data.episode_arrays import DatasetConfig
from equidiff_core.perception.observation import STATE_TOLERANCE_S


def add_arguments(parser) -> None:
    parser.add_argument("bags", nargs="+", help="bag directories, or folders holding bag directories")
    parser.add_argument("--horizon", type=int, default=DatasetConfig.horizon)
    parser.add_argument("--n-obs-steps", type=int, default=DatasetConfig.n_obs_steps)
    parser.add_argument("--n-action-steps", type=int, default=DatasetConfig.n_action_steps)
    parser.add_argument(
        "--tolerance",
        type=float,
        default=STATE_TOLERANCE_S,
        help=f"max |ee pose / joint state stamp - voxel stamp| in seconds (default {STATE_TOLERANCE_S})",
    )
    parser.add_argument("--resolution", type=int, default=DatasetConfig.resolution)
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


def _fmt_range(lo, hi) -> str:
    if lo is None:
        return "-"
    names = ("x", "y", "z")
    parts = [f"{n} [{a:+.3f}, {b:+.3f}]" for n, a, b in zip(names, lo[:3], hi[:3])]
    parts.append(f"width [{lo[9]:.3f}, {hi[9]:.3f}]")
    return "  ".join(parts)


def run(args) -> int:
    cfg = DatasetConfig(
        horizon=args.horizon,
        n_obs_steps=args.n_obs_steps,
        n_action_steps=args.n_action_steps,
        state_tolerance_s=args.tolerance,
        resolution=args.resolution,
    )
    stats = dataset_stats(args.bags, cfg)
    if not stats["episodes"] and not stats["skipped"]:  # "0 episodes" is not a dataset: say so, fail
        print(f"equidiff dataset stats: no episodes (bag directories) in {' '.join(args.bags)}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(stats))
    else:
        print(f"{'episode':<32} {'task':<16} {'ok':<5} {'dur s':>7} {'steps':>6} {'samples':>8} {'dropped':>8}")
        for r in stats["episodes"]:
            name = r["path"].rstrip("/").split("/")[-1]
            ok = "-" if r["success"] is None else ("yes" if r["success"] else "no")
            print(
                f"{name:<32} {r['task'][:16]:<16} {ok:<5} {r['duration_s']:>7.1f} {r['steps']:>6} "
                f"{r['samples']:>8} {r['dropped_steps']:>8}"
            )
        t = stats["total"]
        print(f"{'total':<32} {'':<16} {'':<5} {t['duration_s']:>7.1f} {t['steps']:>6} {t['samples']:>8}")
        print(f"{t['episodes']} episodes; action range: {_fmt_range(t['action_min'], t['action_max'])}")
        if t["episodes_with_corrections"] or t["gate_alarms"]:
            print(
                f"{t['episodes_with_corrections']} episodes with corrections ({t['correction_s']:.1f} s of the "
                f"operator's correction, {t['policy_s']:.1f} s of the policy); {t['gate_alarms']} gate alarms"
            )
        if t["unchecked"]:
            print(f"{t['unchecked']} episodes UNCHECKED: their bags carry no CRCs (written before bags did)")
        for s in stats["skipped"]:
            print(f"SKIPPED {s['path']}: {s['reason']}")
    return 1 if stats["skipped"] else 0
