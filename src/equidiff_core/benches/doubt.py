"""How well each doubt signal (``policy.doubt``) predicts that a roll-out fails: the measurement behind
the default signal (docs/results/doubt.md).

``roll_out_doubt`` rolls a policy out in-process (``twin.evaluate.evaluate_policy``) drawing K samples per
observation, runs the first, and keeps per chunk the free signal (disagreement with the previous chunk's
remainder) and the spread of the first 2, 4, ... K samples, so every candidate is measured on the same
roll-outs. ``episode_scores`` reduces each episode's chunks to one score per candidate (their max, or a
high quantile), ``auroc`` says how well a score separates failures from successes.
``run_doubt_check`` (``equidiff check doubt``) measures the signal over a policy's own demos and can store
that calibration in the policy file, for policy_node's gate.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.stats import mannwhitneyu

from ..policy.doubt import calibrate_doubt, sample_spread
from . import BenchError

logger = logging.getLogger(__name__)


def auroc(failure_scores: Iterable[float], success_scores: Iterable[float]) -> float | None:
    """The probability that a failed episode scores higher than a successful one (ties count half):
    the Mann-Whitney U over n_failures * n_successes. None when either group is empty."""
    fail, ok = list(failure_scores), list(success_scores)
    if not fail or not ok:
        return None
    return float(mannwhitneyu(fail, ok, alternative="two-sided").statistic / (len(fail) * len(ok)))


def auroc_ci95(failure_scores, success_scores, resamples: int = 2000, seed: int = 0) -> tuple[float, float] | None:
    """A percentile bootstrap 95 % interval of ``auroc`` (failures and successes resampled apart:
    scipy.stats.bootstrap over the two samples). None when either group has fewer than two."""
    from scipy.stats import bootstrap

    fail, ok = np.asarray(list(failure_scores), float), np.asarray(list(success_scores), float)
    if len(fail) < 2 or len(ok) < 2:
        return None
    res = bootstrap(
        (fail, ok),
        auroc,
        vectorized=False,
        n_resamples=resamples,
        method="percentile",
        rng=np.random.default_rng(seed),
    )
    return round(float(res.confidence_interval.low), 3), round(float(res.confidence_interval.high), 3)


def chunk_signals(disagreement_m: float, samples: np.ndarray, sample_counts: Iterable[int]) -> dict[str, float]:
    """One chunk's candidates: ``disagreement`` and ``spread_K`` of the first K samples for each K."""
    out = {"disagreement": disagreement_m}
    for k in sample_counts:
        if 2 <= k <= len(samples):
            out[f"spread_{k}"] = sample_spread(samples[:k])
    return out


def episode_scores(chunks: list[dict[str, float]], quantile: float = 1.0) -> dict[str, float]:
    """Each candidate's ``quantile`` (1: the max) over an episode's chunks, NaNs (no value for that chunk) left
    out; NaN when the episode has none."""
    names = {name for chunk in chunks for name in chunk}
    scores = {}
    for name in sorted(names):
        values = [c[name] for c in chunks if name in c and math.isfinite(c[name])]
        scores[name] = float(np.quantile(values, quantile)) if values else math.nan
    return scores


def roll_out_doubt(
    policy,
    cfg,
    lab,
    seeds: Iterable[int],
    samples: int,
    max_duration_s: float,
    latency_s: float,
    log: Callable[[str], None],
    on_episode: Callable[[dict], None],
    recorder=None,
) -> None:
    """Roll ``policy`` out on each seed's scene with ``samples`` samples per observation; ``on_episode`` gets
    {seed, success, duration_s, chunks: [{stamp_ns, disagreement, spread_2, ...}]} after each episode."""
    from ..twin.demos import DirectRecorder
    from ..twin.evaluate import evaluate_policy

    counts = [k for k in (2, 4, 8, 16) if k <= samples]
    chunks: list[dict] = []

    def on_doubt(seed, doubt, drawn):
        chunks.append({"stamp_ns": doubt.stamp_ns, **chunk_signals(doubt.disagreement_m, drawn, counts)})

    rec = recorder or DirectRecorder(cfg, lab)  # one renderer for every episode (a new one per episode grows)
    try:
        for seed in seeds:
            chunks.clear()
            (episode,) = evaluate_policy(
                policy,
                cfg,
                lab,
                [seed],
                max_duration_s,
                log=log,
                recorder=rec,
                latency_s=latency_s,
                doubt_samples=samples,
                on_doubt=on_doubt,
            )
            record = {"seed": seed, "success": episode.success, "duration_s": episode.duration_s}
            on_episode({**record, "chunks": list(chunks)})
    finally:
        if recorder is None:
            rec.close()


@dataclass(frozen=True)
class DoubtCheckSettings:
    """``equidiff check doubt``'s settings: its flags, same names (the command's help says more)."""

    policy: Path  # the exported policy file
    demos: tuple[Path, ...]  # its training demos (bags, packed episodes or folders of them)
    episodes: int  # at most this many of them (0: all)
    signal: str
    samples: int
    write: Path | None  # store the calibration in a copy of the policy file here (may be ``policy``)
    force: bool  # replace an existing ``write``
    threads: int = 1


def run_doubt_check(settings: DoubtCheckSettings, log: Callable[[str], None] = logger.info) -> dict:
    """The doubt signal of a policy over its demos (``policy.doubt.calibrate_doubt``): its quantiles, the frames and
    episodes, and where the calibration was stored (``write``). BenchError (status 2) for bad input."""
    from ..data.dataset import find_episodes, load_episodes
    from ..policy.file import CheckpointError, with_doubt_calibration
    from ..policy.inference import load_inference_policy
    from ..runtime.output_files import refuse_existing

    if settings.write is not None and settings.write != settings.policy:
        refuse_existing(settings.write, settings.force)  # before the work, not after
    if settings.write == settings.policy and not settings.force:
        raise BenchError(f"--write {settings.write} would replace the policy file itself: add --force", 2)
    try:
        policy = load_inference_policy(settings.policy)
    except CheckpointError as err:
        raise BenchError(str(err), 2) from err
    paths = find_episodes(settings.demos)
    if settings.episodes:
        paths = paths[: settings.episodes]
    if not paths:
        raise BenchError(f"no episodes in {', '.join(map(str, settings.demos))}", 2)
    episodes, skipped = load_episodes(paths, log=log)
    if not episodes:
        raise BenchError(f"no readable episode in {', '.join(map(str, settings.demos))}", 2)
    torch.set_num_threads(settings.threads)
    try:
        calibration = calibrate_doubt(policy, episodes, settings.signal, settings.samples, log)
    except ValueError as err:
        raise BenchError(str(err), 2) from err
    result = {
        "policy": str(settings.policy),
        "signal": calibration.signal,
        "samples": calibration.samples,
        "episodes": calibration.episodes,
        "skipped": len(skipped),
        "frames": len(calibration.values_m),
        "quantiles_m": {f"q{q:g}": round(calibration.threshold(q), 5) for q in (0.5, 0.9, 0.95, 0.99, 1.0)},
        "written": None,
    }
    if settings.write is not None:
        with_doubt_calibration(settings.policy, calibration.as_dict(), settings.write, force=settings.force)
        result["written"] = str(settings.write)
    return result
