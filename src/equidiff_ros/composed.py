"""equidiff_composed: several of our nodes in one process, spun by one MultiThreadedExecutor
(the pattern of ros2/examples ``composed.py``).

    equidiff_composed --nodes camera_front=camera_node,camera_left=camera_node,voxel_node,franka_node \\
        --ros-args --params-file params.yaml -r policy_node:/franka/command_chunk:=/twin/policy_chunk

Each node is the same class its own executable runs (``NAME=KIND``: a node named NAME of that
kind, so one kind can run several times, e.g. one camera_node per camera; a bare KIND is named
after it), reading its parameters by its name from ``--params-file`` (ROS 2's format:
``voxel_node: {ros__parameters: {...}}``; ``-p`` would give every node the same value); a remap
meant for one node is prefixed with its name. The twin starts its pipeline this way with
``equidiff twin run --composed`` (twin_node stays a process of its own: its 1 kHz loop must not
share a GIL).
Whether that saves CPU is measured by ``equidiff bench twin --composed`` (docs/twin.md).
"""

from __future__ import annotations

import functools
import importlib
import sys

from equidiff_ros.runner import run_nodes

# node kind (its executable) -> (module, class): the nodes that may share a process
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
usage: equidiff_composed --nodes [NAME=]KIND[,[NAME=]KIND...] [--ros-args ...]   (kinds: {", ".join(COMPOSABLE)})
"""
)


def parse_nodes(argv: list[str]) -> tuple[list[tuple[str, str]], list[str]]:
    """((name, kind) of each node, the remaining arguments) from ``--nodes a,name=b`` anywhere
    before ``--ros-args``."""
    ros_at = argv.index("--ros-args") if "--ros-args" in argv else len(argv)
    own, ros = argv[:ros_at], argv[ros_at:]
    if "--nodes" not in own or own.index("--nodes") + 1 >= len(own):
        raise ValueError("--nodes [NAME=]KIND[,...] is required")
    i = own.index("--nodes")
    nodes = [tuple(n.split("=", 1)) if "=" in n else (n, n) for n in own[i + 1].split(",") if n]
    unknown = [kind for _name, kind in nodes if kind not in COMPOSABLE]
    names = [name for name, _kind in nodes]
    if unknown or not nodes or len(set(names)) != len(names) or not all(names):
        raise ValueError(
            f"--nodes: {', '.join(unknown) or 'repeated, empty or no names'}; composable: {', '.join(COMPOSABLE)}"
        )
    return nodes, own[:i] + own[i + 2 :] + ros


def main(args=None) -> int:
    argv = sys.argv[1:] if args is None else list(args)
    if "-h" in argv or "--help" in argv:
        print(USAGE)
        return 0
    try:
        nodes, rest = parse_nodes(argv)
    except ValueError as err:
        print(f"equidiff_composed: {err}", file=sys.stderr)
        return 2
    modules = {kind: importlib.import_module(COMPOSABLE[kind][0]) for _name, kind in nodes}
    builders = [functools.partial(getattr(modules[kind], COMPOSABLE[kind][1]), node_name=name) for name, kind in nodes]
    startup_errors = tuple({err for m in modules.values() for err in m.STARTUP_ERRORS})
    return run_nodes("equidiff_composed", USAGE, builders, startup_errors, [sys.argv[0], *rest], multithreaded=True)


if __name__ == "__main__":
    sys.exit(main())
