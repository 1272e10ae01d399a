"""When the twin's sim may take its next step on simulated time (ROS-free, unit-tested).

On simulated time the sim runs in lockstep with the pipeline, so the closed loop sees a lab
machine's timing however slow this one is:

* **Camera frames.** At each frame instant (a multiple of the cameras' period) the sim
  publishes the state for the cameras and does not step on until every registered camera
  has taken it (``twin.shared_state``). Rendering then overlaps the sim's next steps.
* **Policy chunks.** While an episode runs (``await_from(start)``), the chunk answering
  each frame taken at t >= start must reach the robot by t + L, L being the declared latency budget:
  the sim does not pass t + L until a chunk stamped t or later has arrived on
  ``/franka/command_chunk``. The twin's supervisor holds each chunk until t + L, so it takes
  effect then, exactly as on a machine whose inference plus transport takes L. An observation
  the policy announces it will not answer (``/policy/skipped``: no robot state near it, a
  failed inference) owes nothing: on a lab machine the robot would go on without that chunk
  too. Without this a divergence stop deadlocked: franka_node's franky call to restart the
  motion waits for the sim to step, and the sim waited for a chunk the policy could not make
  without franka_node's state. The episode's start is a stamp, not the moment its message
  arrives, so that the frames the sim owes are exactly those the supervisor's gate passes
  chunks for; a start that arrives after its first frame was taken is reported as late.
* **Stalls.** A wait longer than ``stall_timeout_s`` of wall time is a stall: it is recorded
  naming the stage that did not deliver (camera, voxel node, policy) and the wait is given
  up, so a dead or hung node never hangs the sim.

Time is counted in 1 ms ticks (franky-sim's step), so stamps are exact integers of ns.
"""

from __future__ import annotations

import collections
import threading
from dataclasses import dataclass

NS_PER_TICK = 1_000_000


@dataclass(frozen=True)
class LockstepConfig:
    frame_period_ticks: int  # camera frames: 200 at 5 Hz
    latency_ticks: int  # L, the latency budget: 100 = 0.1 s
    stall_timeout_s: float = 30.0  # wall seconds a wait may last before it counts as a stall
    keepalive_s: float = 0.3  # libfranka times out after 1 s without a state (robots.franky.sim.keep_alive)
    max_speed: float = 1.0  # at most this many sim seconds per wall second (0: as fast as it goes)
    clock_period_ticks: int = 5  # /clock every 5 ms of sim time (franka_node's 200 Hz control loop)

    def __post_init__(self):
        if self.frame_period_ticks < 1 or self.latency_ticks < 0 or self.clock_period_ticks < 1:
            raise ValueError(
                f"lockstep needs a frame period >= 1 ms, a latency >= 0 and a clock period >= 1 ms: {self}"
            )


class Lockstep:
    """The policy side of the lockstep: which frames still wait for their chunk."""

    def __init__(self, config: LockstepConfig):
        self.config = config
        self._lock = threading.Lock()
        self._await_from_ns = -1  # frames stamped from here on are owed a chunk; -1: none (between episodes)
        self._last_frame_ns = -1
        self._pending: collections.deque[int] = collections.deque()  # frame ticks whose chunk is owed
        self._chunk_stamp_ns = -1  # newest chunk stamp seen on /franka/command_chunk
        self._voxel_stamp_ns = -1  # newest /voxels stamp (only to name a stalled stage)
        self._skipped: set[int] = set()  # observation stamps the policy will not answer
        self.stalls: list[str] = []

    # -- inputs (ROS callbacks, any thread) --------------------------------------------------
    def await_from(self, start_ns: int) -> bool:
        """Owe a chunk to each frame stamped at or after ``start_ns`` (an episode's start); -1: owe
        nothing (its debts are void). False when the start came late: a frame at or after it was
        taken already, and is not owed."""
        with self._lock:
            self._await_from_ns = int(start_ns)
            if start_ns < 0:
                self._pending.clear()
                self._skipped.clear()
                return True
            return self._last_frame_ns < start_ns

    @property
    def awaiting(self) -> bool:
        return self._await_from_ns >= 0

    def on_chunk(self, stamp_ns: int) -> None:
        with self._lock:
            self._chunk_stamp_ns = max(self._chunk_stamp_ns, int(stamp_ns))

    def on_skipped(self, stamp_ns: int) -> None:
        with self._lock:
            if self._await_from_ns >= 0:
                self._skipped.add(int(stamp_ns))

    def on_voxels(self, stamp_ns: int) -> None:
        with self._lock:
            self._voxel_stamp_ns = max(self._voxel_stamp_ns, int(stamp_ns))

    # -- the sim loop's side -----------------------------------------------------------------
    def is_frame_tick(self, tick: int) -> bool:
        return tick % self.config.frame_period_ticks == 0

    def frame_taken(self, tick: int) -> None:
        """The cameras took the frame of ``tick``: from the episode's start on, its chunk is owed by tick + L."""
        with self._lock:
            self._last_frame_ns = tick * NS_PER_TICK
            if 0 <= self._await_from_ns <= self._last_frame_ns:
                self._pending.append(tick)

    def chunk_blocker(self, tick: int) -> str:
        """Why the sim may not step past ``tick`` ('' when it may): a chunk due by now is missing."""
        with self._lock:
            while self._pending and (
                self._pending[0] * NS_PER_TICK <= self._chunk_stamp_ns
                or self._pending[0] * NS_PER_TICK in self._skipped
            ):
                self._skipped.discard(self._pending.popleft() * NS_PER_TICK)
            if not self._pending or tick < self._pending[0] + self.config.latency_ticks:
                return ""
            frame = self._pending[0]
            if self._voxel_stamp_ns < frame * NS_PER_TICK:
                return f"voxel_node: no /voxels for the camera frame at t={frame / 1000:.3f} s"
            return f"policy_node: no chunk for the observation at t={frame / 1000:.3f} s"

    def give_up_oldest(self, why: str) -> None:
        """A stall: stop waiting for the oldest owed chunk and record why."""
        with self._lock:
            if self._pending:
                self._pending.popleft()
            self.stalls.append(why)

    def record_stall(self, why: str) -> None:
        with self._lock:
            self.stalls.append(why)
