"""Success rates with their uncertainty, and paired comparisons of policies rolled out on the same scenes.

Every bench that reports a success rate reports it through ``success_rate``: the rate, n and the Wilson 95 %
score interval (scipy's ``binomtest``), which stays inside [0, 1] and keeps its coverage at small n and at
rates near 0 or 1, where the normal approximation does not. Two policies rolled out on the same scenes are
compared scene by scene with ``paired_comparison``: McNemar's exact test on the scenes where they disagree,
and a paired bootstrap interval of the difference (resampling scenes, as the spread between scene sets is the
uncertainty that matters). ``scenes_needed`` is how the benches' default scene counts were chosen.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import stats

CONFIDENCE = 0.95
# The benches' default scenes per policy and condition: ``scenes_needed(0.2, share)`` at the largest share of
# scenes on which the benches' policies disagreed, rounded up (docs/evaluation_scheme.md says how it was chosen).
SCENES_PER_CELL = 100
# resamples of the paired bootstrap, and its fixed seed: the same outcomes give the same interval
BOOTSTRAP_RESAMPLES = 10_000
BOOTSTRAP_SEED = 0


def wilson_interval(successes: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """The Wilson score interval of ``successes`` out of ``n`` (n >= 1)."""
    if n < 1 or not 0 <= successes <= n:
        raise ValueError(f"need 0 <= successes <= n and n >= 1, got {successes} of {n}")
    ci = stats.binomtest(successes, n).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)


def success_rate(outcomes: Sequence[bool]) -> dict:
    """``{"n", "successes", "rate", "ci95": [low, high]}`` of roll-out outcomes (rate and interval None for none)."""
    n, k = len(outcomes), int(sum(bool(o) for o in outcomes))
    if n == 0:
        return {"n": 0, "successes": 0, "rate": None, "ci95": None}
    low, high = wilson_interval(k, n)
    return {"n": n, "successes": k, "rate": round(k / n, 3), "ci95": [round(low, 3), round(high, 3)]}


def paired_comparison(a: Sequence[bool], b: Sequence[bool]) -> dict:
    """Policy ``a`` against ``b``, outcome by outcome on the same scenes (same order).

    ``difference`` is a's rate minus b's; ``ci95`` its paired bootstrap percentile interval over scenes;
    ``p_value`` McNemar's exact two-sided test (a binomial test of the scenes only a solved against those
    only b solved; 1.0 when they never disagree); ``a_only`` / ``b_only`` those discordant counts."""
    if len(a) != len(b):
        raise ValueError(f"paired outcomes need the same scenes: {len(a)} against {len(b)}")
    x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    n = len(x)
    if n == 0:
        return {"n": 0, "difference": None, "ci95": None, "p_value": None, "a_only": 0, "b_only": 0}
    a_only, b_only = int(((x == 1) & (y == 0)).sum()), int(((x == 0) & (y == 1)).sum())
    difference = float(x.mean() - y.mean())
    if a_only + b_only == 0:  # every resample gives 0: scipy's bootstrap refuses a degenerate sample
        low = high = 0.0
        p_value = 1.0
    else:
        ci = stats.bootstrap(
            (x, y),
            lambda u, v, axis=-1: u.mean(axis=axis) - v.mean(axis=axis),
            paired=True,
            confidence_level=CONFIDENCE,
            n_resamples=BOOTSTRAP_RESAMPLES,
            method="percentile",
            rng=np.random.default_rng(BOOTSTRAP_SEED),
        ).confidence_interval
        low, high = float(ci.low), float(ci.high)
        p_value = float(stats.binomtest(a_only, a_only + b_only, 0.5).pvalue)
    return {
        "n": n,
        "difference": round(difference, 3),
        "ci95": [round(low, 3), round(high, 3)],
        "p_value": float(f"{p_value:.3g}"),  # significant digits: a small p must not print as 0
        "significant": p_value < 1 - CONFIDENCE,
        "a_only": a_only,
        "b_only": b_only,
    }


def paired_outcomes(a: dict[int, bool], b: dict[int, bool]) -> tuple[list[bool], list[bool]]:
    """Outcomes by scene seed -> two lists over the seeds both rolled out, in seed order."""
    seeds = sorted(set(a) & set(b))
    return [a[s] for s in seeds], [b[s] for s in seeds]


def scenes_needed(
    difference: float, discordant_share: float, confidence: float = CONFIDENCE, power: float = 0.8
) -> int:
    """Scenes a paired comparison needs to tell a true ``difference`` in success from chance, two-sided at
    ``confidence`` with probability ``power``, when the policies disagree on ``discordant_share`` of the scenes
    (the normal approximation of McNemar's test: the per-scene difference has variance share - difference²)."""
    if not 0 < abs(difference) <= discordant_share <= 1:
        raise ValueError(f"need 0 < |difference| <= discordant share <= 1, got {difference} and {discordant_share}")
    z = stats.norm.ppf(1 - (1 - confidence) / 2) + stats.norm.ppf(power)
    return math.ceil(z**2 * (discordant_share - difference**2) / difference**2)
