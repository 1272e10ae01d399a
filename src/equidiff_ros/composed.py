"""equidiff_composed: several of our nodes in one process, spun by one MultiThreadedExecutor
(the pattern of ros2/examples ``composed.py``).

    equidiff_composed --nodes camera_node,voxel_node,franka_node,recorder_node \\
        --ros-args --params-file params.yaml -r policy_node:/franka/command_chunk:=/twin/policy_chunk

Each node is the same class its own executable runs, under its own name, reading its
parameters by that name from ``--params-file`` (ROS 2's format: ``voxel_node:
{ros__parameters: {...}}``; ``-p`` would give every node the same value); a remap meant for one
node is prefixed with its name. The twin starts its pipeline this way with ``equidiff twin run
--composed`` (twin_node stays a process of its own: its 1 kHz loop must not share a GIL).
Whether that saves CPU is measured by ``equidiff bench twin --composed`` (docs/twin.md).
"""

from __future__ import annotations

import importlib
import sys

from equidiff_ros.runner import run_nodes

# node name -> (module, class): the nodes that may share a process
COMPOSABLE = {
    "camera_node": ("equidiff_ros.camera_node", "CameraNode"),
    "voxel_node": ("equidiff_ros.voxel_node", "VoxelNode"),
    "franka_node": ("equidiff_ros.franka_node", "FrankaNode"),
    "recorder_node": ("equidiff_ros.recorder_node", "RecorderNode"),
    "teleop_node": ("equidiff_ros.teleop_node", "TeleopNode"),
    "policy_node": ("equidiff_ros.policy_node", "PolicyNode"),
}

USAGE = (
    __doc__
    + f"""
usage: equidiff_composed --nodes NAME[,NAME...] [--ros-args ...]   (names: {", ".join(COMPOSABLE)})
"""
)


def parse_nodes(argv: list[str]) -> tuple[list[str], list[str]]:
    """(node names, the remaining arguments) from ``--nodes a,b`` anywhere before ``--ros-args``."""
    ros_at = argv.index("--ros-args") if "--ros-args" in argv else len(argv)
    own, ros = argv[:ros_at], argv[ros_at:]
    if "--nodes" not in own or own.index("--nodes") + 1 >= len(own):
        raise ValueError("--nodes NAME[,NAME...] is required")
    i = own.index("--nodes")
    names = [n for n in own[i + 1].split(",") if n]
    unknown = [n for n in names if n not in COMPOSABLE]
    if unknown or not names or len(set(names)) != len(names):
        raise ValueError(
            f"--nodes: {', '.join(unknown) or 'repeated or no names'}; composable: {', '.join(COMPOSABLE)}"
        )
    return names, own[:i] + own[i + 2 :] + ros


def main(args=None) -> int:
    argv = sys.argv[1:] if args is None else list(args)
    if "-h" in argv or "--help" in argv:
        print(USAGE)
        return 0
    try:
        names, rest = parse_nodes(argv)
    except ValueError as err:
        print(f"equidiff_composed: {err}", file=sys.stderr)
        return 2
    modules = [importlib.import_module(COMPOSABLE[n][0]) for n in names]
    builders = [getattr(m, COMPOSABLE[n][1]) for n, m in zip(names, modules)]

    def startup_errors() -> tuple[type[BaseException], ...]:
        return tuple({err for m in modules for err in m.startup_errors()})

    return run_nodes("equidiff_composed", USAGE, builders, startup_errors, [sys.argv[0], *rest], multithreaded=True)


if __name__ == "__main__":
    sys.exit(main())
