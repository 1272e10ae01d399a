"""How smoothly chunks are executed: what ``equidiff bench chunking`` measures in the in-process evaluation.

``ChunkingProbe`` watches franka_node's own ``Controller`` in ``evaluate.evaluate_policy``: every
chunk as it arrives and every command it streams (after the safety filter), on the sim clock.

* **Boundary velocity discontinuity** (m/s): at each accepted chunk, the largest change of the
  commanded TCP velocity between consecutive control periods around the switch: v_i - v_{i-1}
  and v_{i+1} - v_i, v_j = (p_j - p_{j-1}) / dt, tick i the first that follows the new chunk
  (it starts the new trajectory where the command is; tick i + 1 has the new chunk's
  velocity). A new chunk that continues the running motion changes it no more than a knot
  inside a chunk does; one that disagrees jerks the arm.
* **Commanded jerk** (m/s^3): the third difference of the commanded TCP position sampled at
  ``JERK_HZ`` (the rate at which the evaluation's arm receives targets, ``direct_execution.COMMAND_HZ``).
* **Mode switches**: consecutive accepted chunks whose published steps at the same times lie
  more than ``mode_switch_m`` apart somewhere: the new chunk plans another way (another grasp,
  another approach), not a small correction. The overlap is what both published: 7 steps for
  replace, ceil(L/dt) + 1 around the switch for the horizon (the steps due before the new chunk
  arrives, which RTC pins to the previous chunk by construction).
* **Standstill at chunk boundaries** (s): at each accepted chunk switch, how long the commanded
  TCP stands still around it (``control.metrics.standstill_at_switches``: position below 1 mm/s
  and orientation below 0.005 rad/s between control ticks, or franka_node's watchdog holding).
  A chunk that runs out before the next one arrives leaves the command at its last step until
  then: the stop-and-go the execution horizon exists to remove. The episode ends once the task
  is judged done, so every switch counted is one while the task is not finished.
"""

from __future__ import annotations

import numpy as np

from ..control.metrics import standstill_at_switches, standstill_summary
from ..wire.chunk import PoseChunk

JERK_HZ = 50.0
MODE_SWITCH_M = 0.03


class ChunkingProbe:
    def __init__(self, mode_switch_m: float = MODE_SWITCH_M):
        self.mode_switch_m = float(mode_switch_m)
        self.boundary_dv: list[float] = []  # m/s, every episode's
        self.jerk: list[float] = []  # m/s^3
        self.standstill: list[float] = []  # s, at every chunk switch of every episode
        self.episode_s = 0.0  # commanded time over all episodes
        self.pairs = 0  # consecutive accepted chunks that overlap in time
        self.mode_switches = 0
        self.start_episode(None)

    def start_episode(self, seed) -> None:
        self._times: list[int] = []
        self._positions: list[np.ndarray] = []
        self._rotations: list[np.ndarray] = []
        self._holding: list[bool] = []
        self._switch_ns: list[int] = []
        self._previous: PoseChunk | None = None

    def chunk(self, now_ns: int, chunk: PoseChunk, accepted: bool) -> None:
        """A chunk reached the controller at ``now_ns`` (accepted or rejected by its checks)."""
        if not accepted:
            return
        previous, self._previous = self._previous, chunk
        if previous is None:
            return  # the episode's first chunk starts from rest: no switch between chunks
        self._switch_ns.append(int(now_ns))
        _, i_new, i_old = np.intersect1d(chunk.times_ns, previous.times_ns, return_indices=True)
        if len(i_new):
            gap = np.linalg.norm(chunk.poses[i_new, :3, 3] - previous.poses[i_old, :3, 3], axis=1).max()
            self.pairs += 1
            self.mode_switches += int(gap > self.mode_switch_m)

    def command(self, command) -> None:
        """franka_node's Controller streamed ``command`` (``control.controller.Command``)."""
        self._times.append(int(command.stamp_ns))
        self._positions.append(np.array(command.target.pose[:3, 3]))
        self._rotations.append(np.array(command.target.pose[:3, :3]))
        self._holding.append(bool(command.holding))

    def end_episode(self) -> None:
        if len(self._times) < 4:
            return
        t = np.asarray(self._times, dtype=np.int64)
        p = np.asarray(self._positions)
        period_s = float(np.median(np.diff(t))) / 1e9
        self.episode_s += (t[-1] - t[0]) / 1e9
        self.standstill.extend(
            standstill_at_switches(
                t / 1e9, p, np.asarray(self._switch_ns) / 1e9, np.asarray(self._rotations), np.asarray(self._holding)
            )
        )
        velocity = np.diff(p, axis=0) / period_s  # velocity[j]: from tick j to tick j + 1
        for switch in self._switch_ns:
            i = int(np.searchsorted(t, switch, side="left"))  # the first tick that follows the new chunk
            if 2 <= i < len(t) - 1:
                # The tick at the switch starts the new trajectory where the command is (moved on by
                # its own velocity), the next one takes up the new chunk's velocity: the larger of
                # the two changes (a stand-still at the switch shows in the first).
                changes = velocity[i - 1 : i + 1] - velocity[i - 2 : i]
                self.boundary_dv.append(float(np.linalg.norm(changes, axis=1).max()))
        every = max(1, round(1.0 / (JERK_HZ * period_s)))
        sampled = p[::every]
        if len(sampled) >= 4:
            h = every * period_s
            self.jerk.extend((np.linalg.norm(np.diff(sampled, n=3, axis=0), axis=1) / h**3).tolist())

    def summary(self) -> dict:
        def p95(values):
            return round(float(np.percentile(values, 95)), 4) if values else None

        return {
            "boundary_dv_p95_mps": p95(self.boundary_dv),
            "jerk_p95_mps3": p95(self.jerk),
            "mode_switches": self.mode_switches,
            "mode_switch_rate": round(self.mode_switches / self.pairs, 3) if self.pairs else None,
            "chunk_switches": len(self.boundary_dv),
            **standstill_summary(self.standstill, self.episode_s),
        }
