"""`equidiff bench twin`: what the twin main job costs this machine, and where the CPU goes.

    equidiff bench twin                         # 1 episode of 20 s sim, shipped checkpoint
    equidiff bench twin --standin --max-duration 10

Runs the main job (simulated time, all nodes as separate processes, or with ``--composed``
every node but twin_node in one process) for ``--episodes`` and
prints one JSON line: each process's CPU share during the episodes (CPU seconds per wall
second, 1.0 = one core: sim = twin_node, each camera, voxel, policy, franka, recorder, and
the supervisor = this process), the sim factor (sim seconds per wall second) and its
inverse ``wall_s_per_sim_s`` (the issue's cost: a 40 s episode takes that many times 40 s),
how the twin's wall time split between waiting for the cameras and for the policy, and the
CPU it ran on (name and whether it has AVX-512 / bf16: absolute numbers depend on it).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from equidiff_core.twin.config import EVALUATION_FIRST_SEED
from equidiff_ros.commands.twin_run import add_precision_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--episodes", type=int, default=1)
    parser.add_argument("--max-duration", type=float, default=20.0, help="sim seconds per episode")
    parser.add_argument("--seed", type=int, default=EVALUATION_FIRST_SEED)
    parser.add_argument("--checkpoint", type=Path, default=None, help="policy (default: the shipped one)")
    parser.add_argument("--standin", action="store_true", help="an untrained tiny stand-in policy")
    parser.add_argument("--latency-ms", type=float, default=100.0)
    add_precision_argument(parser)
    parser.add_argument(
        "--max-speed", type=float, default=1.0, help="at most this many sim seconds per wall second (0: unbounded)"
    )
    parser.add_argument(
        "--torch-threads",
        type=int,
        default=None,
        help="policy_node's torch threads (default: all cores on simulated time)",
    )
    parser.add_argument("--out", type=Path, default=None, help="output directory (default: a temporary one)")
    parser.add_argument(
        "--composed",
        action="store_true",
        help="every node but twin_node in one process (equidiff_ros.composed): its CPU share is reported as 'pipeline'",
    )


def run(args: argparse.Namespace) -> int:
    import tempfile

    from equidiff_core.machine import cpu_description
    from equidiff_core.twin.config import load_twin_job_configs
    from equidiff_core.twin.processes import NodeProcessError, cpu_seconds
    from equidiff_ros.commands.twin_run import resolve_policy
    from equidiff_ros.twin import (
        SupervisorError,
        TwinStack,
        run_policy_episode,
    )

    configs = load_twin_job_configs(None, None)
    out = args.out or Path(tempfile.mkdtemp(prefix="bench_twin_"))
    out.mkdir(parents=True, exist_ok=True)
    args.smoke, args.attach = False, False
    policy_path, label = resolve_policy(args, out, configs.lab.workspace, configs.twin)
    try:
        with TwinStack(
            out,
            configs.lab_path,
            configs.twin_path,
            policy=str(policy_path),
            task="bench_twin",
            seed=args.seed,
            precision=args.precision,
            latency_s=args.latency_ms / 1000,
            max_speed=args.max_speed,
            torch_threads=args.torch_threads,
            composed=args.composed,
        ) as stack:
            procs = {n.name: n.popen.pid for n in stack.group.nodes}
            cpu0 = {name: cpu_seconds(pid) for name, pid in procs.items()}
            me0, wall0, sim0 = time.process_time(), time.monotonic(), stack.sup.now_ns() / 1e9
            waits0 = dict(stack.sup.twin().get("wait_s", {}))
            records = [run_policy_episode(stack, args.seed + i, args.max_duration) for i in range(args.episodes)]
            wall, sim = time.monotonic() - wall0, stack.sup.now_ns() / 1e9 - sim0
            shares = {name: round((cpu_seconds(pid) - cpu0[name]) / wall, 3) for name, pid in procs.items()}
            shares["supervisor"] = round((time.process_time() - me0) / wall, 3)
            waits = {k: round(v - waits0.get(k, 0.0), 1) for k, v in stack.sup.twin().get("wait_s", {}).items()}
    except (NodeProcessError, SupervisorError, FileNotFoundError) as err:
        print(f"equidiff bench twin: {err}", file=sys.stderr)
        return 1
    inference = sorted(v for r in records for v in r.inference_ms)
    result = {
        "cpu_share": dict(sorted(shares.items(), key=lambda kv: -kv[1])),
        "cpu_share_total": round(sum(shares.values()), 2),
        "sim_factor": round(sim / wall, 3),
        "wall_s_per_sim_s": round(wall / sim, 2) if sim > 0 else None,
        "sim_s": round(sim, 1),
        "wall_s": round(wall, 1),
        "twin_wait_s": waits,  # wall seconds the sim stood still waiting for each
        "inference_p50_ms": inference[len(inference) // 2] if inference else None,
        "episodes": len(records),
        "chunks": sum(r.chunks for r in records),
        "dropped_cycles": sum(r.dropped_cycles for r in records),
        "latency_budget_ms": args.latency_ms,
        "max_speed": args.max_speed,
        "torch_threads": stack.torch_threads,
        "precision": args.precision,
        "policy": label,
        "composed": args.composed,
        **cpu_description(),
    }
    print(json.dumps(result))
    return 0
