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

from pathlib import Path

from equidiff_core.benches.conditioning import ConditioningSettings, run_conditioning_check
from equidiff_ros.commands import print_result


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
    settings = ConditioningSettings(
        policies=tuple(args.policies),
        fresh=tuple(args.fresh),
        preset=args.preset,
        demos=args.demos,
        episodes=args.episodes,
        shift_vox=args.shift_vox,
        seed=args.seed,
    )
    return print_result(run_conditioning_check(settings), "check conditioning")
