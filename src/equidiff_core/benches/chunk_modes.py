"""Whole chunks vs replace vs execution horizon vs real-time chunking, by latency, in the in-process twin
(``equidiff bench chunking``; the command's help text defines the modes and the JSON keys).
``run_chunking_bench`` takes its ``ChunkingSettings`` and returns the JSON line as a dict, or raises
``BenchError``; its progress goes to this module's logger."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

from equidiff_core.benches import BenchError
from equidiff_core.benches.stats import paired_comparison, paired_outcomes, success_rate
from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.runtime.machine import cpu_model
from equidiff_core.twin.chunking import ChunkingProbe
from equidiff_core.twin.config import load_twin_config
from equidiff_core.twin.demos import DirectRecorder
from equidiff_core.twin.evaluate import evaluate_policy
from equidiff_core.twin.shipped import SHIPPED_CHECKPOINT
from equidiff_core.wire.chunk import AnswerSchedule, steps_to_publish

MODES = ("whole", "replace", "horizon", "rtc")

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ChunkingSettings:
    """``equidiff bench chunking``'s settings: its flags, same names (the command's help says more)."""

    checkpoint: Path | None  # policy.pt (None: the shipped checkpoint)
    seeds: int  # episodes per mode and latency, the same scenes for all
    seed: int  # the first scene seed
    duration: float  # sim seconds per episode
    latencies: tuple[float, ...]  # latency budgets, ms
    modes: tuple[str, ...]  # of MODES
    execute_steps: int  # k for horizon and rtc (0: the preset's n_action_steps)
    device: str  # the policy's: cpu, cuda or auto
    threads: int  # torch intra-op threads (0: the threads the CLI chose from the idle cores)
    lab_config: Path | None  # lab.yaml (None: the installed one)
    twin_config: Path | None  # twin.yaml (None: the installed one)


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


def run_chunking_bench(settings: ChunkingSettings) -> dict:
    """Every mode at every latency: the bench's JSON line. BenchError (exit status 1) for settings it cannot
    run with or a missing checkpoint."""
    if settings.seeds < 1 or settings.duration <= 0 or any(ms < 0 for ms in settings.latencies):
        raise BenchError("need --seeds >= 1, --duration > 0 and latencies >= 0")
    checkpoint = settings.checkpoint or SHIPPED_CHECKPOINT
    if not checkpoint.is_file():
        raise BenchError(f"no checkpoint at {checkpoint}")
    lab = load_lab_config(settings.lab_config or default_config_dir() / "lab.yaml")
    cfg = load_twin_config(settings.twin_config)
    policy = load_inference_policy(checkpoint, device=settings.device)
    preset = policy.preset
    try:
        k = AnswerSchedule(settings.execute_steps, preset.n_action_steps, 1).steps
    except ValueError as err:
        raise BenchError(str(err)) from err
    available = preset.horizon - preset.n_obs_steps + 1
    seeds = list(range(settings.seed, settings.seed + settings.seeds))
    result: dict = {}
    outcomes: dict[str, dict[int, bool]] = {}  # label -> seed -> solved, for the paired comparisons
    t0 = time.monotonic()
    rec = DirectRecorder(cfg, lab)
    try:
        policy.warmup()
        for latency_ms in settings.latencies:
            for mode in settings.modes:
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
                    settings.duration,
                    recorder=rec,
                    latency_s=latency_ms / 1000,
                    probe=probe,
                    threads=settings.threads or None,  # 0: the threads the CLI chose from the idle cores
                    log=lambda s, w=label: logger.info(f"[{w}] {s}"),
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
            "paired": _paired_against_default(outcomes, settings.latencies, settings.modes),
            "execute_steps": k,
            "seeds": seeds,
            "episode_s": settings.duration,
            "latencies_ms": list(settings.latencies),
            "checkpoint": str(checkpoint),
            "preset": preset.name,
            "cpu": cpu_model(),
            "wall_s": round(time.monotonic() - t0, 1),
        }
    )
    return result
