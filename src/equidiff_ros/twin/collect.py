"""Scripted-expert demonstrations recorded in the twin (``equidiff twin collect``): through the ROS stack, or
in-process on the sim clock (``--direct``, ``equidiff_core.twin.demos``)."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from equidiff_core.config import ConfigError, dump_yaml, to_dict
from equidiff_core.runtime.output_files import write_output_text
from equidiff_core.twin.config import load_twin_job_configs
from equidiff_core.twin.demos import collect_direct
from equidiff_core.twin.episode import run_episode
from equidiff_core.twin.processes import NodeProcessError
from equidiff_ros.twin.stack import TwinStack
from equidiff_ros.twin.supervisor import SupervisorError
from equidiff_ros.twin.world import LiveExpert, LiveTwin


def _collect_ros(args, lab_path: Path, twin_path: Path, cfg_override) -> list[tuple[int, bool, str]]:
    results = []
    twin_cfg_path = twin_path
    if cfg_override is not None:  # the nodes read YAML: the narrowed config next to the bags, this call's replacing any
        twin_cfg_path = args.out / "twin_collect.yaml"
        write_output_text(twin_cfg_path, dump_yaml(to_dict(cfg_override), sort_keys=False), force=True)
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


def run_collect(args) -> int:
    """``equidiff twin collect`` for its parsed arguments: record, print one JSON line; the exit status."""
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
    except (NodeProcessError, SupervisorError) as err:
        print(f"equidiff twin collect: {err}", file=sys.stderr)
        return 1
    ok = sum(1 for _, s, _ in results if s)
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
