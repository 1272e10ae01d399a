"""How well each doubt signal (``policy.doubt``) predicts that a roll-out fails: the measurement behind
the default signal (docs/results/doubt.md).

``roll_out_doubt`` rolls a policy out in-process (``twin.evaluate.evaluate_policy``) drawing K samples per
observation, runs the first, and keeps per chunk the free signal (disagreement with the previous chunk's
remainder) and the spread of the first 2, 4, ... K samples, so every candidate is measured on the same
roll-outs. ``episode_scores`` reduces each episode's chunks to one score per candidate (their max, or a
high quantile), ``auroc`` says how well a score separates failures from successes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

import numpy as np
from scipy.stats import mannwhitneyu

from ..policy.doubt import sample_spread


def auroc(failure_scores: Iterable[float], success_scores: Iterable[float]) -> float | None:
    """The probability that a failed episode scores higher than a successful one (ties count half):
    the Mann-Whitney U over n_failures * n_successes. None when either group is empty."""
    fail, ok = list(failure_scores), list(success_scores)
    if not fail or not ok:
        return None
    return float(mannwhitneyu(fail, ok, alternative="two-sided").statistic / (len(fail) * len(ok)))


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
    from ..twin.evaluate import evaluate_policy

    counts = [k for k in (2, 4, 8, 16) if k <= samples]
    chunks: list[dict] = []

    def on_doubt(seed, doubt, drawn):
        chunks.append({"stamp_ns": doubt.stamp_ns, **chunk_signals(doubt.disagreement_m, drawn, counts)})

    for seed in seeds:
        chunks.clear()
        (episode,) = evaluate_policy(
            policy,
            cfg,
            lab,
            [seed],
            max_duration_s,
            log=log,
            recorder=recorder,
            latency_s=latency_s,
            doubt_samples=samples,
            on_doubt=on_doubt,
        )
        on_episode({"seed": seed, "success": episode.success, "duration_s": episode.duration_s, "chunks": list(chunks)})
