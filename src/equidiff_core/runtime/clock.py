"""Time for code that runs in the lab (the wall clock) and in the twin (simulated time).

In the twin, time is ROS 2 simulated time: twin_node publishes ``/clock`` and every node runs
with ``use_sim_time``, so a node's clock stands still while the sim waits for the pipeline.
Loops that tick at a rate (franka_node's control loop) must then tick in that time, not on
the wall clock: ticking by the wall clock while the sim waits spends the CPU that the
pipeline it waits for needs. ``Clock`` is what such a loop is given; the ROS side wraps a
node's clock in a ``PolledClock`` (``equidiff_ros.common.node_clock``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Protocol


class Clock(Protocol):
    def now_ns(self) -> int:
        """Nanoseconds of this clock (the wall clock's epoch, or simulated time)."""

    def sleep_until(self, t_ns: int, stop: threading.Event) -> bool:
        """Block until ``now_ns() >= t_ns``; False when ``stop`` was set first."""


class WallClock:
    """The system clock (a real robot's time)."""

    def now_ns(self) -> int:
        return time.time_ns()

    def sleep_until(self, t_ns: int, stop: threading.Event) -> bool:
        delay = (t_ns - time.time_ns()) / 1e9
        return not stop.wait(delay) if delay > 0 else not stop.is_set()


class PolledClock:
    """A clock that advances by messages (ROS simulated time): sleeping polls it.

    rclpy's ``Clock.sleep_until`` cannot be interrupted and never returns if ``/clock``
    stops, so a node could not shut down while the sim is gone; a short wall-clock poll
    (1 ms by default, ~1 % of a core) stays responsive to ``stop`` whatever the clock does.

    ``stall_s``: a sleep raises ``TimeoutError`` once the clock has stood still that many wall
    seconds. None (the nodes' choice) waits on: a paused sim is not a dead one. A test or bench
    client sets it, so that a dead sim ends it with an error instead of a hang.
    """

    def __init__(self, now_ns: Callable[[], int], poll_s: float = 0.001, stall_s: float | None = None):
        self._now_ns = now_ns
        self.poll_s = poll_s
        self.stall_s = stall_s

    def now_ns(self) -> int:
        return self._now_ns()

    def sleep_until(self, t_ns: int, stop: threading.Event) -> bool:
        seen, seen_at = self._now_ns(), time.monotonic()
        while seen < t_ns:
            if stop.wait(self.poll_s):
                return False
            now = self._now_ns()
            if now != seen:
                seen, seen_at = now, time.monotonic()
            elif self.stall_s is not None and time.monotonic() - seen_at > self.stall_s:
                raise TimeoutError(
                    f"the simulated clock stood still at {now / 1e9:.3f} s for {self.stall_s:g} s of wall time "
                    "(no /clock: is the twin still running?)"
                )
        return not stop.is_set()
