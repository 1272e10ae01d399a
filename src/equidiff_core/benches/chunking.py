"""Whole chunks vs replace vs execution horizon vs real-time chunking, by latency, in the in-process twin
(``equidiff bench chunking``; the command's help text defines the modes and the JSON keys)."""

from __future__ import annotations

import json
import time

from equidiff_core.benches.stats import paired_comparison, paired_outcomes, success_rate
from equidiff_core.chunk import AnswerSchedule, steps_to_publish
from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.inference import load_inference_policy
from equidiff_core.machine import cpu_model
from equidiff_core.twin.chunking import ChunkingProbe
from equidiff_core.twin.config import load_twin_config
from equidiff_core.twin.demos import DirectRecorder
from equidiff_core.twin.evaluate import evaluate_policy
from equidiff_core.twin.shipped import SHIPPED_CHECKPOINT

MODES = ("whole", "replace", "horizon", "rtc")


def _paired_against_default(outcomes: dict, latencies, modes) -> dict:
    """Each mode against the execution horizon (the default) at the same latency, scene by scene."""
    paired = {}
    for latency_ms in latencies:
        base = f"horizon_{latency_ms:g}ms"
        for mode in modes:
            label = f"{mode}_{latency_ms:g}ms"
            if mode != "horizon" and base in outcomes:
                paired[f"{label}_vs_{base}"] = paired_comparison(*paired_outcomes(outcomes[label], outcomes[base]))
    return paired


def run_chunking_bench(args) -> int:
    """``equidiff bench chunking`` for its parsed arguments: every mode at every latency, one JSON line."""
    if args.seeds < 1 or args.duration <= 0 or any(ms < 0 for ms in args.latencies):
        raise SystemExit("equidiff bench chunking: need --seeds >= 1, --duration > 0 and latencies >= 0")
    checkpoint = args.checkpoint or SHIPPED_CHECKPOINT
    if not checkpoint.is_file():
        raise SystemExit(f"no checkpoint at {checkpoint}")
    lab = load_lab_config(args.lab_config or default_config_dir() / "lab.yaml")
    cfg = load_twin_config(args.twin_config)
    policy = load_inference_policy(checkpoint, device=args.device)
    preset = policy.preset
    try:
        k = AnswerSchedule(args.execute_steps, preset.n_action_steps, 1).steps
    except ValueError as err:
        raise SystemExit(f"equidiff bench chunking: {err}") from err
    available = preset.horizon - preset.n_obs_steps + 1
    seeds = list(range(args.seed, args.seed + args.seeds))
    result: dict = {}
    outcomes: dict[str, dict[int, bool]] = {}  # label -> seed -> solved, for the paired comparisons
    t0 = time.monotonic()
    rec = DirectRecorder(cfg, lab)
    try:
        policy.warmup()
        for latency_ms in args.latencies:
            for mode in args.modes:
                label = f"{mode}_{latency_ms:g}ms"
                if mode == "replace":
                    schedule = {"execute_steps": 1, "publish_steps": 0, "rtc": False}
                elif mode == "whole":
                    schedule = {"execute_steps": k, "publish_steps": 0, "rtc": False}
                else:
                    schedule = {
                        "execute_steps": k,
                        "rtc": mode == "rtc",
                        "publish_steps": steps_to_publish(k, latency_ms / 1000, preset.dt, available),
                    }
                probe = ChunkingProbe()
                episodes = evaluate_policy(
                    policy,
                    cfg,
                    lab,
                    seeds,
                    args.duration,
                    recorder=rec,
                    latency_s=latency_ms / 1000,
                    probe=probe,
                    threads=args.threads or None,  # 0: the threads the CLI chose from the idle cores
                    log=lambda s, w=label: print(f"[{w}] {s}", flush=True),
                    **schedule,
                )
                rate = success_rate([e.success for e in episodes])
                result[f"{label}_success"] = rate["rate"]
                result[f"{label}_success_ci95"] = rate["ci95"]
                outcomes[label] = {e.seed: e.success for e in episodes}
                result[f"{label}_lifted"] = round(sum(e.lifted for e in episodes) / len(episodes), 3)
                result.update({f"{label}_{key}": value for key, value in probe.summary().items()})
                result[f"{label}_publish_steps"] = schedule["publish_steps"] or preset.n_action_steps
    finally:
        rec.close()
    result.update(
        {
            "paired": _paired_against_default(outcomes, args.latencies, args.modes),
            "execute_steps": k,
            "seeds": seeds,
            "episode_s": args.duration,
            "latencies_ms": list(args.latencies),
            "checkpoint": str(checkpoint),
            "preset": preset.name,
            "cpu": cpu_model(),
            "wall_s": round(time.monotonic() - t0, 1),
        }
    )
    print(json.dumps(result), flush=True)
    return 0
