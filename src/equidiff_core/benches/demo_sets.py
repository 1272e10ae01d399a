"""The benches' demos: narrow-yaw scripted-expert demos recorded once into ``OUT/demos`` (or given), checked
against the yaw range the bench claims, and cut into nested subsets (the first 10 of the first 20 of 40)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ..data.bags import find_bags, read_meta
from ..data.dataset import find_episodes
from ..twin.demos import collect_direct
from ..twin.scene import recorded_block_yaw_range, same_yaw_range


def count_demos(folder: Path) -> int:
    return len(find_episodes([folder]))


def ensure_demos(
    demos_dir: Path | None, out: Path, n: int, train_cfg, lab, seed: int, log: Callable[[str], None] = print
) -> tuple[Path, int]:
    """(folder, number of demos): ``demos_dir`` as given, else ``out/demos`` holding at least ``n`` demos,
    recorded now from seeds ``seed`` on (``twin.demos.collect_direct``, failures dropped) unless an earlier
    call recorded them."""
    if demos_dir is not None:
        return demos_dir, count_demos(demos_dir)
    demos_dir = out / "demos"
    if demos_dir.is_dir() and count_demos(demos_dir) >= n:
        return demos_dir, count_demos(demos_dir)
    results = collect_direct(train_cfg, lab, demos_dir, range(seed, seed + 10 * n), log=log, stop_after=n)
    return demos_dir, sum(1 for _, ok, _ in results if ok)


def demos_off_range(folder: Path, train_yaw: tuple[float, float]) -> tuple[list[str], int]:
    """Bags in ``folder`` whose metadata records another block yaw range than ``train_yaw``
    ("bag: range"), and how many bags record none (recorded before episodes kept it)."""
    wrong, unrecorded = [], 0
    for bag in find_bags([folder]):
        recorded = recorded_block_yaw_range(read_meta(bag).extra)
        if recorded is None:
            unrecorded += 1
        elif not same_yaw_range(recorded, train_yaw):
            wrong.append(f"{bag.name}: {recorded[0]:g} to {recorded[1]:g} deg")
    return wrong, unrecorded


def nested_subsets(folder: Path, counts: list[int]) -> dict[int, list[Path]]:
    """count -> the first ``count`` episodes of ``folder`` in name order (the recording order, seed by seed),
    so each subset holds every smaller one; ValueError when the folder holds fewer than the largest count."""
    episodes = sorted(find_episodes([folder]), key=lambda p: p.name)
    if counts and len(episodes) < max(counts):
        raise ValueError(f"{folder} holds {len(episodes)} demos, the bench needs {max(counts)}")
    return {n: episodes[:n] for n in sorted(set(counts))}
