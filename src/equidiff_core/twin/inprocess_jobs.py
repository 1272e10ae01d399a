"""The twin's in-process jobs (no ROS, sim clock): ``equidiff twin evaluate`` (the main job's episodes) and
``equidiff twin replay-chunks`` (a live run's chunks replayed open loop). Their commands' help texts say more;
the episodes themselves are ``twin.evaluate``. Each takes its settings and returns its JSON line as a dict, or
raises ``TwinJobError``; the episodes' lines go to this module's logger."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from equidiff_core.benches.stats import success_rate
from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.data.bags import find_bags
from equidiff_core.data.mcap_reader import BagError
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.runtime.jobs import JobError
from equidiff_core.twin.config import load_twin_config
from equidiff_core.twin.demos import DirectRecorder
from equidiff_core.twin.evaluate import evaluate_policy, replay_chunks
from equidiff_core.twin.shipped import SHIPPED_CHECKPOINT

logger = logging.getLogger(__name__)


class TwinJobError(JobError):
    """An in-process twin job could not run (exit status 1): settings out of range, no checkpoint, no or
    unreadable bags."""


@dataclass(frozen=True)
class EvaluationSettings:
    """``equidiff twin evaluate``'s settings: its flags, same names (the command's help says more)."""

    episodes: int  # episodes, one scene seed each
    seed: int  # the first episode's scene seed (then +1 each)
    checkpoint: Path | None  # policy.pt (None: the shipped checkpoint)
    max_duration: float | None  # seconds per episode (None: twin.yaml's)
    latency_ms: float  # each chunk reaches the controller this long after its observation
    execute_steps: int  # answer every N-th observation (0: one per chunk)
    device: str  # the policy's: cpu, cuda or auto
    precision: str  # the policy's inference precision
    lab_config: Path | None  # lab.yaml (None: the installed one)
    twin_config: Path | None  # twin.yaml (None: the installed one)


@dataclass(frozen=True)
class ChunkReplaySettings:
    """``equidiff twin replay-chunks``' settings: its arguments, same names (the command's help says more)."""

    bags: tuple[Path, ...]  # twin episode bags, or folders of them
    latency_ms: float  # the live run's latency budget
    max_duration: float | None  # seconds per episode (None: twin.yaml's)
    lab_config: Path | None  # lab.yaml (None: the installed one)
    twin_config: Path | None  # twin.yaml (None: the installed one)


def run_evaluation(settings: EvaluationSettings) -> dict:
    """The episodes, then their summary (the command's JSON line)."""
    if settings.episodes < 1:
        raise TwinJobError("--episodes must be at least 1")
    checkpoint = settings.checkpoint or SHIPPED_CHECKPOINT
    if not checkpoint.is_file():
        raise TwinJobError(f"no checkpoint at {checkpoint}")
    lab = load_lab_config(settings.lab_config or default_config_dir() / "lab.yaml")
    cfg = load_twin_config(settings.twin_config)
    max_duration = settings.max_duration or cfg.episode.max_duration_s
    policy = load_inference_policy(checkpoint, device=settings.device, precision=settings.precision)
    seeds = range(settings.seed, settings.seed + settings.episodes)
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
            latency_s=settings.latency_ms / 1000,
            execute_steps=settings.execute_steps,
            log=logger.info,
        )
        wall_s = time.monotonic() - t0
    finally:
        rec.close()
    return {
        "episodes": len(episodes),
        "success": sum(e.success for e in episodes),
        "success_rate": success_rate([e.success for e in episodes]),
        "reached": sum(e.reached for e in episodes),
        "lifted": sum(e.lifted for e in episodes),
        "successful_seeds": [e.seed for e in episodes if e.success],
        "checkpoint": str(checkpoint),
        "latency_budget_ms": settings.latency_ms,
        "max_duration_s": max_duration,
        "execute_steps": settings.execute_steps,
        "wall_s": round(wall_s, 1),
    }


def _finite_or_none(reduce, values: list[float]) -> float | None:
    """``reduce`` over the episodes that had recorded TCP poses to compare with (None: none had)."""
    finite = [v for v in values if math.isfinite(v)]
    return round(float(reduce(finite)), 1) if finite else None


def run_chunk_replay(settings: ChunkReplaySettings) -> dict:
    """Every bag replayed, then their summary (the command's JSON line)."""
    bags = find_bags(settings.bags)
    if not bags:
        raise TwinJobError(f"no bags in {', '.join(map(str, settings.bags))}")
    lab = load_lab_config(settings.lab_config or default_config_dir() / "lab.yaml")
    cfg = load_twin_config(settings.twin_config)
    t0 = time.monotonic()
    try:
        episodes = replay_chunks(bags, cfg, lab, settings.latency_ms / 1000, settings.max_duration, log=logger.info)
    except BagError as err:
        raise TwinJobError(str(err)) from None
    return {
        "episodes": len(episodes),
        "recorded_success": sum(e.recorded_success is True for e in episodes),
        "replayed_success": sum(e.success for e in episodes),
        "same_outcome": sum(e.recorded_success == e.success for e in episodes),
        "tcp_gap_mean_mm": _finite_or_none(np.mean, [e.tcp_gap_mean_mm for e in episodes]),
        "tcp_gap_p95_mm_worst": _finite_or_none(np.max, [e.tcp_gap_p95_mm for e in episodes]),
        "wall_s": round(time.monotonic() - t0, 1),
    }
