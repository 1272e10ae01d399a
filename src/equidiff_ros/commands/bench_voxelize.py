"""`equidiff bench voxelize`: time fusing 3 clouds of 300k points into the 64³ grid, against open3d.

Prints ONE JSON line: ``median_ms``, ``p95_ms`` (our voxeliser, wall clock, camera-frame
clouds in, grid out), ``open3d_median_ms`` (only
``open3d.geometry.VoxelGrid.create_from_point_cloud_within_bounds`` on the same points,
already transformed to the base frame and converted to an open3d cloud outside the timing,
so the baseline is flattered, not us) and ``speedup_vs_open3d``; also ``cpu_median_ms``
(process CPU time per call: what the call costs when other work shares the cores),
``reference_ms`` (the straightforward ``voxelize_reference``), ``reference_equal`` (the
grid equals it bit for bit), the input's size and the machine's load average.

The input is a synthetic scene ray-cast from the three cameras of ``config/lab.yaml``
(table, boxes, room walls, depth noise growing with range), so the share of points inside
the workspace and their spatial coherence look like a real RealSense frame; ``--scene
uniform`` instead scatters points uniformly around the workspace (random memory access,
the worst case for every implementation).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from equidiff_core.benches.voxelize import VoxelizeSettings, run_voxelize_bench
from equidiff_ros.commands import print_result


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--points", type=int, default=300_000, help="points per camera (default 300000)")
    parser.add_argument("--repeats", type=int, default=50, help="timed calls of our voxeliser")
    parser.add_argument("--open3d-repeats", type=int, default=5, help="timed calls of open3d (slow)")
    parser.add_argument("--scene", choices=("raycast", "uniform"), default="raycast")
    parser.add_argument("--lab-config", default=None, help="lab.yaml (default: the installed one)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-open3d", action="store_true", help="skip the open3d baseline")


def run(args: argparse.Namespace) -> int:
    settings = VoxelizeSettings(
        points=args.points,
        repeats=args.repeats,
        open3d_repeats=args.open3d_repeats,
        scene=args.scene,
        lab_config=None if args.lab_config is None else Path(args.lab_config),
        seed=args.seed,
        open3d=not args.no_open3d,
    )
    result = run_voxelize_bench(settings)
    print_result(result)
    return 0 if result["reference_equal"] else 1  # 1: the grid differs from the reference
