"""`equidiff twin collect`: scripted-expert demonstrations in the digital twin, recorded to bags.

    equidiff twin collect --episodes 20 --out demos/            # through ROS, like a human operator
    equidiff twin collect --episodes 40 --out demos/ --direct   # in-process, faster than real time
    equidiff twin collect --episodes 30 --out demos/ --yaw-range -30 30   # narrow object yaw

Default (ROS) path: the same nodes as a teleoperated session (twin_node, three camera_nodes
with backend twin, voxel_node, franka_node, recorder_node) on a private ROS_DOMAIN_ID; the
expert plans grasp-lift-place from the sim state and publishes one-point /franka/command_chunk
targets at 20 Hz exactly like teleop_node, and recorder_node writes one bag per episode, so
the demos are byte-for-byte the kind a human would record. ``--direct`` runs sim, cameras,
voxeliser and expert in this process with the sim clock and writes the same topics with the
same EpisodeWriter (no recorder_node, no real-time requirement): for benchmarks and quick data.
Every bag's metadata carries task, success and the scene seed.

DIR is a work folder: each call adds its bags, numbered after those already there (a bag is never
overwritten), so it is not refused and takes no --force. With --yaw-range the ROS path writes the
narrowed twin.yaml its nodes read to DIR/twin_collect.yaml, whole, replacing an earlier call's.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from equidiff_ros.twin.collect import run_collect


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--episodes", type=int, required=True)
    parser.add_argument(
        "--out", type=Path, required=True, help="directory for the episode bags (a work folder: bags are added)"
    )
    parser.add_argument("--seed", type=int, default=0, help="first scene seed (then +1 per episode)")
    parser.add_argument("--direct", action="store_true", help="in-process, sim clock (no ROS nodes)")
    parser.add_argument(
        "--yaw-range",
        type=float,
        nargs=2,
        default=None,
        metavar=("LO", "HI"),
        help="object yaw range in degrees (default: twin.yaml's, the full circle)",
    )
    parser.add_argument("--keep-failures", action="store_true", help="keep failed episodes (success=false)")
    parser.add_argument("--task", default="twin_block_in_bowl")
    parser.add_argument("--domain", type=int, default=None)
    parser.add_argument("--lab-config", type=Path, default=None)
    parser.add_argument("--twin-config", type=Path, default=None)


def run(args: argparse.Namespace) -> int:
    return run_collect(args)
