"""Where the twin's CPU goes (``equidiff bench twin``): each process's share and wall seconds per sim second."""

from __future__ import annotations

import json
import sys
import time

from equidiff_core.runtime.machine import cpu_description
from equidiff_core.runtime.output_files import staged_dir
from equidiff_core.twin.config import load_twin_job_configs
from equidiff_core.twin.processes import NodeProcessError, cpu_seconds
from equidiff_core.twin.shipped import resolve_policy
from equidiff_ros.twin.stack import TwinStack
from equidiff_ros.twin.supervisor import SupervisorError
from equidiff_ros.twin.world import run_policy_episode


def run_twin_bench(args) -> int:
    """``equidiff bench twin`` for its parsed arguments: one JSON line; the exit status."""
    configs = load_twin_job_configs(None, None)
    # --out: a new folder, refused if it holds anything (unless --force), landing once the episodes ran
    with staged_dir(args.out, force=args.force, prefix="bench_twin_") as staged:
        out = staged.path
        policy_path, label = resolve_policy(
            out, configs.lab.workspace, configs.twin, checkpoint=args.checkpoint, standin=args.standin
        )
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
            staged.discard()
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
