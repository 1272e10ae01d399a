"""Scenes inside and outside the training range of block yaws, and success broken down by yaw.

Used by ``bench generalization`` with ``evaluate.evaluate_policy``: which seeds to roll out,
and what EquiDiff's rotational symmetry covers of each episode's yaw.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from .config import TwinConfig
from .scene import sample_scene

if TYPE_CHECKING:  # evaluate imports this module's names back for its callers
    from .evaluate import EvalEpisode


def unseen_yaw_seeds(
    cfg: TwinConfig, train_yaw_deg: tuple[float, float], n: int, start: int = 10_000_000, margin_deg: float = 15.0
) -> list[int]:
    """Seeds whose block yaw lies at least ``margin_deg`` outside the training range, modulo 180 deg.

    The block is a box grasped across its short side: at yaw and yaw + 180 deg it looks and is
    grasped the same, so a yaw 180 deg from the training range is not unseen. The bowl is a
    ring of ``bowl_segments`` walls, the same every 360/segments deg (22.5 for 16), so no bowl
    yaw is unseen by a 15 deg margin and it is left free."""
    lo, hi = train_yaw_deg
    centre, half = (lo + hi) / 2, (hi - lo) / 2 + margin_deg
    if half >= 90.0:
        raise ValueError(
            f"training yaw range {train_yaw_deg} plus a {margin_deg} deg margin leaves no unseen block yaw"
        )
    return _seeds_where(cfg, n, start, lambda yaw: abs(block_yaw_offset_deg(yaw, centre)) > half)


def in_range_yaw_seeds(
    cfg: TwinConfig, train_yaw_deg: tuple[float, float], n: int, start: int = 20_000_000
) -> list[int]:
    """Seeds whose block yaw lies inside the training range (modulo 180 deg, as above): the
    control for ``unseen_yaw_seeds`` (a policy that fails here has not learned the task)."""
    lo, hi = train_yaw_deg
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    return _seeds_where(cfg, n, start, lambda yaw: abs(block_yaw_offset_deg(yaw, centre)) <= half)


def _seeds_where(cfg: TwinConfig, n: int, start: int, keep: Callable[[float], bool]) -> list[int]:
    """The first ``n`` seeds from ``start`` whose scene's block yaw passes ``keep``."""
    seeds, seed = [], start
    while len(seeds) < n:
        if seed - start > 10_000 + 1_000 * n:
            raise ValueError(
                f"only {len(seeds)} of {n} scenes from seed {start} have such a block yaw (is the yaw range empty?)"
            )
        if keep(sample_scene(cfg.scene, seed).block_yaw):
            seeds.append(seed)
        seed += 1
    return seeds


def block_yaw_offset_deg(yaw_rad: float, centre_deg: float = 0.0) -> float:
    """Block yaw minus ``centre_deg``, wrapped to [-90, 90): the box's half-turn symmetry."""
    return float((np.degrees(yaw_rad) - centre_deg + 90.0) % 180.0 - 90.0)


def _distance_to_multiple(x_deg: float, period_deg: float) -> float:
    """|x| to the nearest multiple of ``period_deg`` (degrees)."""
    r = x_deg % period_deg
    return min(r, period_deg - r)


# offset bins (degrees from the training range's centre, modulo the box's half turn) of yaw_breakdown
OFFSET_BINS_DEG = ((0, 15), (15, 30), (30, 45), (45, 60), (60, 75), (75, 90))


def yaw_breakdown(episodes: list[EvalEpisode], train_yaw_deg: tuple[float, float]) -> dict:
    """Success by what EquiDiff's symmetry covers, from each episode's block yaw offset to the training
    range's centre (modulo 180 deg: the box's half turn):

    * ``mod90``: ``within`` where the offset lies within the range's half-width of a multiple of 90 deg
      (C4, exact on the voxel grid, maps the block into the training range), ``outside`` the rest;
    * ``mod45``: the same about multiples of 45 deg (C8's other elements, only approximate on the grid);
    * ``by_offset_deg``: |offset| in 15-degree bins.

    Each entry: ``{"episodes", "solved"}``. The scene's other parts (block position, bowl, the arm's
    start) are not rotated with the block, so a covered yaw is not the same scene as a trained one."""
    lo, hi = train_yaw_deg
    centre, half = (lo + hi) / 2, (hi - lo) / 2

    def tally(keep) -> dict:
        chosen = [e for e in episodes if keep(e)]
        return {"episodes": len(chosen), "solved": sum(e.success for e in chosen)}

    def offset(e: EvalEpisode) -> float:
        return abs((e.block_yaw_deg - centre + 90.0) % 180.0 - 90.0)

    result = {}
    for label, period in (("mod90", 90.0), ("mod45", 45.0)):
        result[label] = {
            "within": tally(lambda e, p=period: _distance_to_multiple(offset(e), p) <= half),
            "outside": tally(lambda e, p=period: _distance_to_multiple(offset(e), p) > half),
        }
    result["by_offset_deg"] = {
        f"{a}-{b}": tally(lambda e, a=a, b=b: a <= offset(e) < b or (b == 90 and offset(e) == 90))
        for a, b in OFFSET_BINS_DEG
    }
    return result
