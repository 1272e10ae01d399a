"""The twin's in-process jobs (no ROS, sim clock): ``equidiff twin evaluate`` (the main job's episodes) and
``equidiff twin replay-chunks`` (a live run's chunks replayed open loop). Their commands' help texts say more;
the episodes themselves are ``twin.evaluate``."""

from __future__ import annotations

import json
import math
import time

import numpy as np

from equidiff_core.bags import BagError, find_bags
from equidiff_core.benches.stats import success_rate
from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.inference import load_inference_policy
from equidiff_core.twin.config import load_twin_config
from equidiff_core.twin.demos import DirectRecorder
from equidiff_core.twin.evaluate import evaluate_policy, replay_chunks
from equidiff_core.twin.shipped import SHIPPED_CHECKPOINT


def run_evaluation(args) -> int:
    """``equidiff twin evaluate`` for its parsed arguments: the episodes, then one JSON line."""
    if args.episodes < 1:
        raise SystemExit("--episodes must be at least 1")
    checkpoint = args.checkpoint or SHIPPED_CHECKPOINT
    if not checkpoint.is_file():
        raise SystemExit(f"no checkpoint at {checkpoint}")
    lab = load_lab_config(args.lab_config or default_config_dir() / "lab.yaml")
    cfg = load_twin_config(args.twin_config)
    max_duration = args.max_duration or cfg.episode.max_duration_s
    policy = load_inference_policy(checkpoint, device=args.device, precision=args.precision)
    seeds = range(args.seed, args.seed + args.episodes)
    rec = DirectRecorder(cfg, lab)
    try:
        policy.warmup()  # first-call costs (seconds of compilation) out of the wall time
        t0 = time.monotonic()
        episodes = evaluate_policy(
            policy,
            cfg,
            lab,
            seeds,
            max_duration,
            recorder=rec,
            latency_s=args.latency_ms / 1000,
            execute_steps=args.execute_steps,
            log=lambda s: print(s, flush=True),
        )
        wall_s = time.monotonic() - t0
    finally:
        rec.close()
    print(
        json.dumps(
            {
                "episodes": len(episodes),
                "success": sum(e.success for e in episodes),
                "success_rate": success_rate([e.success for e in episodes]),
                "reached": sum(e.reached for e in episodes),
                "lifted": sum(e.lifted for e in episodes),
                "successful_seeds": [e.seed for e in episodes if e.success],
                "checkpoint": str(checkpoint),
                "latency_budget_ms": args.latency_ms,
                "max_duration_s": max_duration,
                "execute_steps": args.execute_steps,
                "wall_s": round(wall_s, 1),
            }
        ),
        flush=True,
    )
    return 0


def _finite_or_none(reduce, values: list[float]) -> float | None:
    """``reduce`` over the episodes that had recorded TCP poses to compare with (None: none had)."""
    finite = [v for v in values if math.isfinite(v)]
    return round(float(reduce(finite)), 1) if finite else None


def run_chunk_replay(args) -> int:
    """``equidiff twin replay-chunks`` for its parsed arguments: every bag replayed, then one JSON line."""
    bags = find_bags(args.bags)
    if not bags:
        raise SystemExit(f"no bags in {', '.join(map(str, args.bags))}")
    lab = load_lab_config(args.lab_config or default_config_dir() / "lab.yaml")
    cfg = load_twin_config(args.twin_config)
    t0 = time.monotonic()
    try:
        episodes = replay_chunks(
            bags, cfg, lab, args.latency_ms / 1000, args.max_duration, log=lambda s: print(s, flush=True)
        )
    except BagError as err:
        raise SystemExit(str(err)) from None
    print(
        json.dumps(
            {
                "episodes": len(episodes),
                "recorded_success": sum(e.recorded_success is True for e in episodes),
                "replayed_success": sum(e.success for e in episodes),
                "same_outcome": sum(e.recorded_success == e.success for e in episodes),
                "tcp_gap_mean_mm": _finite_or_none(np.mean, [e.tcp_gap_mean_mm for e in episodes]),
                "tcp_gap_p95_mm_worst": _finite_or_none(np.max, [e.tcp_gap_p95_mm for e in episodes]),
                "wall_s": round(time.monotonic() - t0, 1),
            }
        )
    )
    return 0
