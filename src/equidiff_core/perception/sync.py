"""Approximate-time matching of N message streams, their staleness, and phase-locked publishing (no ROS).

message_filters' ApproximateTimeSynchronizer is not on PyPI and is callback-driven; the
voxel node instead needs "the newest complete set, when my 5 Hz timer fires", so this is a
small pull-style matcher: each stream keeps its last few (stamp, item) pairs; a *match* is
one item per stream whose stamps lie within ``slop`` of each other. ``newest()`` returns the
match whose oldest stamp is the most recent (the freshest complete view), and each match is
handed out once: a later call returns a match only if it contains newer data.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

T = TypeVar("T")


@dataclass(frozen=True)
class Match(Generic[T]):
    items: dict[str, T]  # stream name -> item
    stamps_ns: dict[str, int]

    @property
    def newest_ns(self) -> int:
        return max(self.stamps_ns.values())

    @property
    def oldest_ns(self) -> int:
        return min(self.stamps_ns.values())

    @property
    def spread_ns(self) -> int:
        return self.newest_ns - self.oldest_ns


class ApproximateTimeMatcher(Generic[T]):
    """Match the newest items of ``names`` whose stamps differ by at most ``slop_ns``."""

    def __init__(self, names: Sequence[str], slop_ns: int, queue_size: int = 5):
        if not names:
            raise ValueError("at least one stream name is required")
        if len(set(names)) != len(names):
            raise ValueError(f"stream names must be unique, got {list(names)}")
        if slop_ns < 0:
            raise ValueError(f"slop must be >= 0, got {slop_ns} ns")
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        self.names = tuple(names)
        self.slop_ns = int(slop_ns)
        self._queues: dict[str, deque[tuple[int, T]]] = {n: deque(maxlen=queue_size) for n in names}
        self._last_key: tuple[int, ...] | None = None
        self._last_newest_ns: int | None = None

    def add(self, name: str, stamp_ns: int, item: T) -> None:
        """Queue an item; items arriving out of order are slotted in by stamp."""
        if name not in self._queues:
            raise KeyError(f"unknown stream {name!r}; streams: {list(self.names)}")
        q = self._queues[name]
        if q and stamp_ns < q[-1][0]:
            items = sorted([*q, (int(stamp_ns), item)], key=lambda e: e[0])
            q.clear()
            q.extend(items[-q.maxlen :])
        else:
            q.append((int(stamp_ns), item))

    def latest_stamp(self, name: str) -> int | None:
        q = self._queues[name]
        return q[-1][0] if q else None

    def ages_ns(self, now_ns: int) -> dict[str, int | None]:
        """Age of each stream's newest item (None: nothing received yet)."""
        return {n: (None if (s := self.latest_stamp(n)) is None else now_ns - s) for n in self.names}

    def stale(self, now_ns: int, max_age_ns: int) -> list[str]:
        """Streams with nothing received, or whose newest item is older than ``max_age_ns``."""
        return [n for n, age in self.ages_ns(now_ns).items() if age is None or age > max_age_ns]

    def newest(self) -> Match[T] | None:
        """The freshest match not handed out before and newer than the last one, or None."""
        match = self.peek()
        if match is None:
            return None
        key = tuple(match.stamps_ns[n] for n in self.names)
        if key == self._last_key or (self._last_newest_ns is not None and match.newest_ns <= self._last_newest_ns):
            return None
        self._last_key, self._last_newest_ns = key, match.newest_ns
        return match

    def peek(self) -> Match[T] | None:
        """The freshest match (largest oldest stamp), whether handed out before or not."""
        if any(not q for q in self._queues.values()):
            return None
        # Try every queued item as the oldest member of the set, freshest first; each other
        # stream then needs an item in [pivot, pivot + slop] (the one nearest the pivot).
        pivots = sorted(((s, n, it) for n, q in self._queues.items() for s, it in q), key=lambda e: -e[0])
        for pivot_ns, pivot_name, pivot_item in pivots:
            items: dict[str, Any] = {pivot_name: pivot_item}
            stamps = {pivot_name: pivot_ns}
            for name, q in self._queues.items():
                if name == pivot_name:
                    continue
                best = None
                for s, it in q:
                    if pivot_ns <= s <= pivot_ns + self.slop_ns and (best is None or s < best[0]):
                        best = (s, it)
                if best is None:
                    break
                stamps[name], items[name] = best
            else:
                return Match({n: items[n] for n in self.names}, {n: stamps[n] for n in self.names})
        return None

    def clear(self) -> None:
        for q in self._queues.values():
            q.clear()


class PublishPacer:
    """Picks frames to publish at ``hz``, phase-locked to the wall clock.

    A frame is due at the first arrival after each multiple of the period (minus a quarter
    period of tolerance), so camera nodes in separate processes, or on separate machines
    with synchronised clocks, publish frames captured within one device frame of each other:
    the voxel node's approximate-time matching then finds tight sets. A source that already
    delivers at ``hz`` (twin, replay) gets every frame through.
    """

    def __init__(self, hz: float):
        if not hz > 0:
            raise ValueError(f"publish rate must be positive, got {hz} Hz")
        self.period = 1.0 / hz
        self.tolerance = 0.25 * self.period
        self.next_due = 0.0

    def wait_s(self, now: float) -> float:
        """Seconds until the next grid time: an on-demand source (the twin renders when read)
        waits this long, then reads, so its frames are captured on the grid too."""
        return max(0.0, self.next_due - now)

    def due(self, now: float) -> bool:
        if now < self.next_due - self.tolerance:
            return False
        self.next_due = (math.floor((now + self.tolerance) / self.period) + 1) * self.period
        return True
