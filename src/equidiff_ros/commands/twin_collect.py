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
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--episodes", type=int, required=True)
    parser.add_argument("--out", type=Path, required=True, help="directory for the episode bags")
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


def _collect_ros(args, lab_path: Path, twin_path: Path, cfg_override) -> list[tuple[int, bool, str]]:
    from equidiff_core.episode import run_episode
    from equidiff_ros.twin import LiveExpert, LiveTwin, TwinStack

    results = []
    twin_cfg_path = twin_path
    if cfg_override is not None:  # the nodes read YAML: write the narrowed config next to the bags
        import yaml

        from equidiff_core.config import to_dict

        twin_cfg_path = args.out / "twin_collect.yaml"
        twin_cfg_path.write_text(yaml.safe_dump(to_dict(cfg_override), sort_keys=False))
    with TwinStack(
        args.out, lab_path, twin_cfg_path, policy=None, domain_id=args.domain, task=args.task, seed=args.seed
    ) as stack:
        world = LiveTwin(stack)
        for i in range(args.episodes):
            seed = args.seed + i
            result = run_episode(
                world,
                LiveExpert(stack),
                seed,
                float("inf"),
                stack.cfg.success.hold_s,
                keep=lambda ok: ok or args.keep_failures,
                note="scripted expert",
            )
            results.append((seed, result.success, result.bag))
            print(
                f"[collect] {i + 1}/{args.episodes} seed {seed}: {'success' if result.success else 'failure'} "
                f"{result.bag or '(discarded)'}",
                flush=True,
            )
    return results


def run(args: argparse.Namespace) -> int:
    from equidiff_core.config import ConfigError
    from equidiff_core.twin.config import load_twin_job_configs

    try:
        configs = load_twin_job_configs(args.lab_config, args.twin_config)
    except ConfigError as err:
        print(f"equidiff twin collect: {err}", file=sys.stderr)
        return 2
    lab_path, twin_path, lab, cfg = configs.lab_path, configs.twin_path, configs.lab, configs.twin
    override = cfg.with_yaw_range(tuple(args.yaw_range)) if args.yaw_range else None
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    try:
        if args.direct:
            from equidiff_core.twin.demos import collect_direct

            results = collect_direct(
                override or cfg,
                lab,
                args.out,
                range(args.seed, args.seed + args.episodes),
                task=args.task,
                keep_failures=args.keep_failures,
                log=lambda s: print(s, flush=True),
            )
        else:
            results = _collect_ros(args, lab_path, twin_path, override)
    except KeyboardInterrupt:
        print("[collect] interrupted", file=sys.stderr)
        return 130
    except Exception as err:
        from equidiff_core.twin.processes import NodeProcessError
        from equidiff_ros.twin import SupervisorError

        if isinstance(err, (NodeProcessError, SupervisorError)):
            print(f"equidiff twin collect: {err}", file=sys.stderr)
            return 1
        raise
    ok = sum(1 for _, s, _ in results if s)
    import json

    print(
        json.dumps(
            {
                "episodes": len(results),
                "successes": ok,
                "kept": sum(1 for *_, b in results if b),
                "out": str(args.out),
                "seconds": round(time.monotonic() - t0, 1),
                "mode": "direct" if args.direct else "ros",
            }
        )
    )
    return 0
