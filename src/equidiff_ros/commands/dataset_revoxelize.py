"""`equidiff dataset revoxelize BAGS... --lab new_lab.yaml --out DIR`: demos re-voxelised after a recalibration.

Each bag's /voxels are rebuilt from its recorded camera clouds (recorder ``record_clouds``,
on by default) with the cameras and extrinsics of ``--lab``, exactly as voxel_node would have
fused them (``perception.fusion.CloudFusion``). The new extrinsics replace the cameras' transforms in
``/tf_static`` and are written into the episode's metadata (``extra.extrinsics.<camera>``);
every other topic and metadata entry is copied. One new bag per input under ``--out`` (same
name; where two inputs share one, their paths below the common folder: ``day1__pick_0000``).
A bag without clouds of every camera is reported and skipped (exit 1).

DIR is written beside itself and renamed into place once every bag is done: an existing DIR is
refused (exit 2) unless ``--force``, which replaces it only then.
"""

from __future__ import annotations

import sys
from pathlib import Path

from equidiff_core.config import load_lab_config
from equidiff_core.data.bags import find_bags
from equidiff_core.perception.fusion import revoxelize_bags
from equidiff_core.runtime.output_files import OutputExistsError
from equidiff_ros.commands import add_force_argument


def add_arguments(parser) -> None:
    parser.add_argument("bags", nargs="+", help="bag directories, or folders holding bag directories")
    parser.add_argument("--lab", type=Path, required=True, help="the lab YAML with the new extrinsics")
    parser.add_argument("--out", type=Path, required=True, help="directory for the re-voxelised bags")
    parser.add_argument(
        "--slop", type=float, default=0.1, help="max stamp spread of a set of clouds, s (voxel_node's slop_s)"
    )
    add_force_argument(parser)


def run(args) -> int:
    lab = load_lab_config(args.lab)
    bags = find_bags(args.bags)
    if not bags:
        print(f"equidiff dataset revoxelize: no bags in {args.bags}", file=sys.stderr)
        return 1
    try:
        reports, failed = revoxelize_bags(bags, args.out, lab, slop_s=args.slop, force=args.force)
    except OutputExistsError as err:
        print(f"equidiff dataset revoxelize: {err}", file=sys.stderr)
        return 2
    for bag, reason in failed:
        print(f"FAILED {bag}: {reason}", file=sys.stderr)
    for report in reports:
        clouds = ", ".join(f"{name} {n}" for name, n in report.clouds.items())
        print(
            f"{report.path.name}: {report.grids} grids (replacing {report.replaced}) from clouds {clouds} -> {report.path}"
        )
    return 1 if failed else 0
