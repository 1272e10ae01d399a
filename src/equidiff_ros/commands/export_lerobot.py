"""`equidiff export lerobot BAGS... --out DIR`: episodes as a LeRobot dataset (format v3.0).

``equidiff_core.data.lerobot.export`` writes it (layout, features and encoder settings there):
``observation.state``, ``action``, ``observation.images.<camera>`` (the recorded JPEGs as AV1
mp4), ``observation.voxels`` (``--no-voxels`` to leave out). LeRobot 0.6.1 loads it with
``LeRobotDataset(repo_id, root=DIR)``. Prints one JSON line; exit 1 when a bag was skipped
(each named with its reason on stderr), 2 when nothing could be exported.

DIR is written beside itself and renamed into place once complete: an export that fails half-way
(a corrupt JPEG, Ctrl-C) leaves nothing behind, and an existing DIR is refused (exit 2) unless
``--force``, which replaces it only then.
"""

from __future__ import annotations

import json
import sys

from equidiff_core.data.episode_arrays import DatasetConfig
from equidiff_core.data.lerobot.export import ExportOptions, export_lerobot
from equidiff_core.data.lerobot.layout import ExportError
from equidiff_core.perception.observation import STATE_TOLERANCE_S
from equidiff_core.runtime.output_files import OutputExistsError
from equidiff_ros.commands import add_force_argument


def add_arguments(parser) -> None:
    parser.add_argument("bags", nargs="+", help="bag directories, or folders holding bag directories")
    parser.add_argument("--out", required=True, help="new dataset directory (replaced only with --force)")
    parser.add_argument("--no-voxels", action="store_true", help="leave the voxel grids out")
    parser.add_argument("--no-images", action="store_true", help="leave the camera images out")
    parser.add_argument("--robot-type", default="franka_fr3")
    parser.add_argument("--tolerance", type=float, default=STATE_TOLERANCE_S, help="state/voxel stamp tolerance, s")
    parser.add_argument(
        "--image-tolerance", type=float, default=None, help="image/voxel stamp tolerance, s (half a frame period)"
    )
    parser.add_argument("--resolution", type=int, default=DatasetConfig.resolution)
    parser.add_argument("--only-successful", action="store_true", help="skip episodes not marked success")
    add_force_argument(parser)


def run(args) -> int:
    def log(message: str) -> None:
        print(f"equidiff export lerobot: {message}", file=sys.stderr)

    options = ExportOptions(
        voxels=not args.no_voxels,
        images=not args.no_images,
        only_successful=args.only_successful,
        robot_type=args.robot_type,
        image_tolerance_s=args.image_tolerance,
    )
    config = DatasetConfig(resolution=args.resolution, state_tolerance_s=args.tolerance)
    try:
        report = export_lerobot(args.bags, args.out, options, config, log=log, force=args.force)
    except (ExportError, OutputExistsError) as err:
        log(str(err))
        return 2
    print(json.dumps(report.summary()))
    return 1 if report.skipped else 0
