"""The twin supervisor's gate: which policy chunks reach the robot, and when (ROS-free).

policy_node stays loaded and answering between episodes; only chunks answering observations
of the running episode pass. On simulated time each is held until its observation's stamp +
the latency budget L, so it takes effect when it would on a lab machine with that latency.
The gate also keeps the episode's figures: forward times, end-to-end latencies, the reasons
of observations the policy skipped, and its inference times.

Not thread-safe: the supervisor calls it under its lock. Chunks are opaque (ROS messages).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

NS_PER_S = 1_000_000_000


@dataclass
class GateRecord:
    """What passed the gate during one episode."""

    arrivals: list[float] = field(default_factory=list)  # clock seconds at which chunks were forwarded
    dropped: list[str] = field(default_factory=list)  # reasons of observations the policy skipped
    end_to_end_ms: list[float] = field(default_factory=list)  # forward time - observation stamp
    inference_ms: list[float] = field(default_factory=list)


class PolicyGate:
    """Open during an episode; ``latency_ns`` > 0 holds each chunk until its stamp + latency."""

    def __init__(self, latency_ns: int = 0):
        self.latency_ns = int(latency_ns)
        self.is_open = False
        self.open_ns = 0
        self.chunks_seen = 0  # gate or not: the policy is loaded and answering
        self.record = GateRecord()
        self._held: list[tuple[int, Any]] = []  # (stamp ns, chunk) waiting for stamp + latency

    def open(self, now_ns: int) -> None:
        """Pass chunks answering observations stamped from ``now_ns`` on; a fresh record."""
        self.record = GateRecord()
        self._held = []
        self.open_ns = int(now_ns)
        self.is_open = True

    def close(self) -> GateRecord:
        """Pass nothing more (held chunks are dropped); a copy of the episode's record."""
        self.is_open = False
        self._held = []
        r = self.record
        return GateRecord(list(r.arrivals), list(r.dropped), list(r.end_to_end_ms), list(r.inference_ms))

    def offer(self, chunk: Any, stamp_ns: int, now_ns: int) -> bool:
        """A chunk arrived: True to forward it now; otherwise it is held (released by ``due``)
        or ignored (between episodes, or answering an observation from before this episode)."""
        self.chunks_seen += 1
        if not self.is_open or stamp_ns < self.open_ns:
            return False
        if stamp_ns + self.latency_ns > now_ns:
            self._held.append((int(stamp_ns), chunk))
            return False
        return True

    def due(self, now_ns: int) -> list[tuple[int, Any]]:
        """The held (stamp ns, chunk) pairs whose time has come at ``now_ns``, oldest first."""
        due = [(s, c) for s, c in self._held if s + self.latency_ns <= now_ns]
        self._held = [(s, c) for s, c in self._held if s + self.latency_ns > now_ns]
        return due

    def forwarded(self, stamp_ns: int, now_ns: int) -> bool:
        """Record a chunk forwarded at ``now_ns``; False (do not forward) if the gate closed meanwhile."""
        if not self.is_open:
            return False
        self.record.arrivals.append(now_ns / NS_PER_S)
        self.record.end_to_end_ms.append((now_ns - stamp_ns) / 1e6)
        return True

    def skipped(self, stamp_ns: int, reason: str) -> None:
        """An observation the policy did not answer; ``executing`` (its last chunk still runs) is its
        execution schedule, not a drop."""
        if self.is_open and stamp_ns >= self.open_ns and reason != "executing":
            self.record.dropped.append(reason)

    def inference(self, ms: float) -> None:
        if self.is_open:
            self.record.inference_ms.append(ms)
