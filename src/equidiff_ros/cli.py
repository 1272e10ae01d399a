"""`equidiff`: one CLI for the offline tools (train, dataset, bags, bench, check, viz), the twin and the lab.

Each leaf command lives in its own module under ``equidiff_ros.commands`` exposing
``add_arguments(parser)`` and ``run(args) -> int``; it is imported only when invoked, so
``equidiff train`` never imports rclpy and ``equidiff --help`` imports nothing heavy.
"""

from __future__ import annotations

import argparse
import faulthandler
import importlib
import os
import signal
import sys

from equidiff_core.runtime.jobs import error_message
from equidiff_core.runtime.machine import default_threads_to_idle_cores

# (command path) -> (module, one-line help)
COMMANDS: dict[tuple[str, ...], tuple[str, str]] = {
    ("train",): ("train", "train EquiDiff or the baseline from recorded bags"),
    ("distill",): ("distill", "distil a trained policy into a few-step DDIM sampler, a policy file of its own"),
    ("dataset", "stats"): ("dataset_stats", "episodes, durations, steps and action ranges of bags"),
    ("dataset", "revoxelize"): ("dataset_revoxelize", "rebuild the bags' voxels from their clouds with new extrinsics"),
    ("dataset", "pack"): ("dataset_pack", "one compressed .episode.npz per bag: train without the bags"),
    ("bags", "repair"): ("bags_repair", "recover the messages of a bag whose recorder was killed"),
    ("replay",): ("replay", "publish a recorded bag into the live ROS graph"),
    ("viz",): ("viz", "rerun visualisation of the live graph, or convert bags to .rrd"),
    ("check", "equivariance"): ("check_equivariance", "measure the noise predictor's C4/C8 equivariance error"),
    ("check", "conditioning"): (
        "check_conditioning",
        "does a policy look at its observation? its features and actions when the block moves",
    ),
    ("check", "doubt"): (
        "check_doubt",
        "the policy's doubt over its own demos: the doubt gate's threshold, stored in the policy file",
    ),
    ("bench", "voxelize"): ("bench_voxelize", "time voxelising 3 x 300k points against open3d"),
    ("bench", "policy"): ("bench_policy", "time the encoder, one denoising step and DDIM-16"),
    ("bench", "train"): ("bench_train", "training samples/s on the CPU and on CUDA, same run"),
    ("bench", "overfit"): ("bench_overfit", "can a policy fit two demos? its samples against each demo's trajectory"),
    ("bench", "control"): ("bench_control", "tracking, safety and latency of the franka node on franky-sim"),
    ("bench", "generalization"): (
        "bench_generalization",
        "EquiDiff vs the baseline with and without rotation augmentation on unseen object yaw",
    ),
    ("bench", "demos"): (
        "bench_demos",
        "sample efficiency: EquiDiff vs the baseline trained on 10, 20 and 40 demos (success per count, PNG)",
    ),
    ("bench", "corrections"): (
        "bench_corrections",
        "one round of corrections in the twin: takeovers, fine-tuning, against more demos (PNG)",
    ),
    ("bench", "safety"): ("bench_safety", "fault campaign against franky-sim through franka_node (one JSON line)"),
    ("bench", "chunking"): (
        "bench_chunking",
        "replace vs execution horizon vs real-time chunking by latency, in the twin",
    ),
    ("bench", "steps"): (
        "bench_steps",
        "success against DDIM denoising steps in the twin, with inference time and chunk-boundary velocity change",
    ),
    ("bench", "twin"): ("bench_twin", "where the twin's CPU goes: each process's share and wall s per sim s"),
    ("bench", "images"): ("bench_images", "what recording the cameras' colour images costs: bytes and CPU per frame"),
    ("twin", "collect"): ("twin_collect", "record scripted-expert demonstrations in the digital twin"),
    ("twin", "run"): ("twin_run", "the main job: evaluate a policy end to end in the digital twin"),
    ("twin", "evaluate"): ("twin_evaluate", "the main job's episodes in-process on the sim clock (no ROS)"),
    ("twin", "replay-chunks"): (
        "twin_replay_chunks",
        "a live twin run's policy chunks replayed open loop in-process: does the arm end the same way?",
    ),
    ("export", "lerobot"): ("export_lerobot", "export bags to a LeRobot dataset"),
    ("calibrate", "cameras"): (
        "calibrate",
        "camera extrinsics from a ChArUco board on the hand (hand-eye + joint refinement)",
    ),
    ("lab",): ("lab_ui", "the operator loop: one screen and single keys for episodes, policy, homing and stops"),
    ("lab", "record"): ("lab_record", "start / keep as success or failure / discard the recorder's episode"),
    ("lab", "ack"): (
        "lab_ack",
        "let the arm go on after a robot error or divergence stop (it never resumes by itself)",
    ),
    ("lab", "home"): ("lab_home", "glide the arm slowly to the home pose (refused while a stop awaits ack)"),
    ("lab", "policy"): ("lab_policy", "enable, pause or resume the policy"),
    ("lab", "status"): ("lab_status", "robot state, episode, policy state and teleop takeover, from the live graph"),
    ("cameras", "list"): ("cameras_list", "connected RealSense serials, firmware and USB links vs lab.yaml"),
    ("calibrate", "check"): (
        "calibrate_check",
        "each camera's alignment in mm against the other clouds and the fingertips",
    ),
}

# (group) -> what its subcommands are for; a group with its own command (`equidiff lab`) says that command's help
GROUPS: dict[str, str] = {
    "dataset": "inspect, pack and re-voxelise recorded episodes for training",
    "bags": "recover recorded bags that a killed recorder left unfinished",
    "check": "check what a trained policy learned: its equivariance and whether it looks at its observation",
    "bench": "measure speed, control, safety and learning: the benchmarks behind the documented figures",
    "twin": "the digital twin: record expert demonstrations and evaluate policies in simulation",
    "export": "convert recorded bags to other dataset formats",
    "calibrate": "find and check the cameras' extrinsics",
    "cameras": "the RealSense cameras connected to this machine",
}


def _load(module: str):
    return importlib.import_module(f"equidiff_ros.commands.{module}")


def build_parser(argv: list[str]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="equidiff", description=__doc__.splitlines()[0])
    root = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    groups: dict[str, tuple[argparse.ArgumentParser, argparse._SubParsersAction]] = {}
    group_names = {path[0] for path in COMMANDS if len(path) > 1}
    for path, (module, help_text) in COMMANDS.items():
        has_own = path[0] in group_names and (path[0],) in COMMANDS  # `equidiff lab` and `lab record`
        if path[0] not in group_names:
            leaf = root.add_parser(path[0], help=help_text, description=help_text)
        else:
            if path[0] not in groups:
                own = COMMANDS[(path[0],)][1] if has_own else GROUPS[path[0]]
                group = root.add_parser(path[0], help=own, description=own)
                subs = group.add_subparsers(dest="subcommand", metavar="SUBCOMMAND", required=not has_own)
                groups[path[0]] = (group, subs)
            group, subs = groups[path[0]]
            leaf = group if len(path) == 1 else subs.add_parser(path[1], help=help_text, description=help_text)
        leaf.set_defaults(_module=module)
        if len(path) == 1 and has_own and argv[1:2] and (path[0], argv[1]) in COMMANDS:
            continue  # one of the group's subcommands runs, not the group's own command
        if list(path) == argv[: len(path)]:
            try:
                _load(module).add_arguments(leaf)
            except ModuleNotFoundError as err:
                if err.name != f"equidiff_ros.commands.{module}":
                    raise
                leaf.set_defaults(_missing=True)
    return parser


def report_error(command: str, err: BaseException) -> int | None:
    """Print ``err`` as ``equidiff <command>: <message>`` on stderr and return its exit status
    (``error_message``); None, printing nothing, for an error that is a bug."""
    known = error_message(err)
    if known is None:
        return None
    message, status = known
    print(f"equidiff {command}: {message}", file=sys.stderr)
    return status


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    # `kill -USR1 <pid>` prints every thread's stack: where a long job (twin run, train) is stuck
    try:
        faulthandler.register(signal.SIGUSR1, file=sys.__stderr__, all_threads=True)
    except (AttributeError, ValueError, OSError):  # no real stderr (embedded, closed): no dumps then
        pass
    # The twin's cameras render headless (EGL); MuJoCo reads this once, when first imported, and
    # some commands import it before the cameras' module could set it (calibrate check --twin).
    os.environ.setdefault("MUJOCO_GL", "egl")
    default_threads_to_idle_cores()  # before any command imports torch
    args = build_parser(argv).parse_args(argv)
    if getattr(args, "_missing", False):
        print(f"equidiff: '{' '.join(argv[:2])}' is not available in this build", file=sys.stderr)
        return 2
    try:
        return int(_load(args._module).run(args) or 0)
    except Exception as err:
        # A job's error, a bad config file or value, or an output that exists already (--force replaces it)
        # are the user's to fix: one message, not a traceback
        command = " ".join(v for v in (args.command, getattr(args, "subcommand", None)) if v)
        status = report_error(command, err)
        if status is None:
            raise
        return status


if __name__ == "__main__":
    sys.exit(main())
