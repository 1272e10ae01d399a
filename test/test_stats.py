"""Success rates with their intervals, and paired comparisons (`benches.stats`), against the textbook formulas."""

import math

import pytest

from equidiff_core.benches.stats import (
    paired_comparison,
    paired_outcomes,
    scenes_needed,
    success_rate,
    wilson_interval,
)


def _wilson_by_hand(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson's score interval, written out (Wilson 1927): the reference scipy's answer is checked against."""
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return centre - half, centre + half


@pytest.mark.parametrize(("k", "n"), [(12, 20), (6, 20), (0, 10), (10, 10), (40, 50), (1, 1)])
def test_wilson_interval_is_the_score_interval(k, n):
    low, high = wilson_interval(k, n)
    ref_low, ref_high = _wilson_by_hand(k, n)
    assert low == pytest.approx(ref_low, abs=1e-9) and high == pytest.approx(ref_high, abs=1e-9)
    assert 0.0 <= low <= k / n <= high <= 1.0


def test_twelve_of_twenty_is_about_39_to_78_percent():
    rate = success_rate([True] * 12 + [False] * 8)
    assert rate == {"n": 20, "successes": 12, "rate": 0.6, "ci95": [0.387, 0.781]}


def test_success_rate_of_no_roll_outs_says_so_instead_of_dividing_by_zero():
    assert success_rate([]) == {"n": 0, "successes": 0, "rate": None, "ci95": None}
    with pytest.raises(ValueError, match="0 <= successes <= n"):
        wilson_interval(3, 2)


def test_policies_that_never_disagree_differ_by_nothing():
    outcomes = [True, False, True, True, False]
    same = paired_comparison(outcomes, outcomes)
    assert same["difference"] == 0.0 and same["ci95"] == [0.0, 0.0] and same["p_value"] == 1.0
    assert same["significant"] is False and same["a_only"] == same["b_only"] == 0


def test_a_policy_that_solves_ten_more_of_fifty_scenes_is_more_than_chance():
    a = [True] * 30 + [False] * 20
    b = [False] * 10 + [True] * 20 + [False] * 20  # a solves every scene b solves, and 10 more
    result = paired_comparison(a, b)
    assert result["a_only"] == 10 and result["b_only"] == 0 and result["difference"] == 0.2
    assert result["p_value"] == pytest.approx(2 * 0.5**10, abs=1e-4)  # McNemar's exact test: 10 of 10 one way
    low, high = result["ci95"]
    assert 0.0 < low < 0.2 < high and result["significant"] is True
    # the same counts spread both ways (12 against 2) is a smaller difference and a larger p
    mixed = paired_comparison(
        [True] * 12 + [False] * 2 + [True] * 18 + [False] * 18, [False] * 12 + [True] * 2 + [True] * 18 + [False] * 18
    )
    assert mixed["difference"] == 0.2 and mixed["p_value"] > result["p_value"]


def test_two_to_one_on_three_scenes_is_not_distinguishable_from_chance():
    result = paired_comparison([True, True, False], [False, False, True])
    assert result["significant"] is False and result["ci95"][0] < 0 < result["ci95"][1]


def test_the_bootstrap_interval_is_the_same_from_run_to_run():
    a, b = [True, False] * 25, [False, True, True, False, False] * 10
    assert paired_comparison(a, b) == paired_comparison(a, b)


def test_paired_outcomes_pair_by_seed_and_refuse_unequal_lists():
    a, b = paired_outcomes({3: True, 1: False, 2: True}, {2: False, 3: True, 9: True})
    assert a == [True, True] and b == [False, True]  # seeds 2 and 3, in seed order
    with pytest.raises(ValueError, match="same scenes"):
        paired_comparison([True], [True, False])


def test_scenes_needed_follows_the_discordant_share():
    # 20 points apart with the policies disagreeing on 30 % of the scenes: about 50 scenes
    n = scenes_needed(0.2, 0.3)
    assert 45 <= n <= 55
    assert scenes_needed(0.2, 0.5) > n > scenes_needed(0.3, 0.3)  # more disagreement or a smaller gap: more scenes
    with pytest.raises(ValueError):
        scenes_needed(0.4, 0.3)  # a difference larger than the share of scenes they disagree on is impossible
