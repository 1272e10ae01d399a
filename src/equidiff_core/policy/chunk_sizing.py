"""How many steps each chunk carries and how many run before the next answer: policy_node's rule, ROS-free.

A chunk bridges the observation-to-arrival latency L (``wire.chunk.LatencyEstimate``: fixed, off, or
measured online): it carries k + ceil(L/dt) + 1 steps, at most what the horizon predicts, where k
(``execute_steps``) is how many steps run before the next observation is answered. With
``n_action_steps`` set or L off, every chunk carries ``n_action_steps``; with ``execute_steps`` 0
while bridging, k follows L (``wire.chunk.bridging_execute_steps``).
"""

from __future__ import annotations

from ..wire.chunk import (
    AnswerSchedule,
    LatencyEstimate,
    bridging_execute_steps,
    max_bridged_latency_s,
    steps_to_publish,
)
from .presets import PolicyPreset


class ChunkSizing:
    """``n_steps`` (0: the preset's), ``execute_steps`` (0: all of them, fewer when L needs it),
    ``latency_s`` and ``transport_s`` as policy_node's parameters of those names take them."""

    def __init__(self, preset: PolicyPreset, n_steps: int, execute_steps: int, latency_s, transport_s):
        self.n_action_steps = int(n_steps) or int(preset.n_action_steps)
        if not 1 <= self.n_action_steps <= preset.horizon:
            raise ValueError(f"n_action_steps must be within 1..{preset.horizon}, got {self.n_action_steps}")
        self.dt_ns = round(preset.dt * 1e9)
        self.answers = AnswerSchedule(execute_steps, self.n_action_steps, self.dt_ns)
        self.available_steps = preset.horizon - preset.n_obs_steps + 1  # predicted from the observation on
        self.latency = LatencyEstimate(latency_s, transport_s)  # L: fixed, off, or measured online
        self.fixed_steps = bool(n_steps) or self.latency.off  # n_action_steps per chunk, whatever L
        # execute_steps 0 while bridging: all n_action_steps, fewer when L is too long for them
        self.adaptive_steps = not execute_steps and not self.fixed_steps
        self.max_bridged_s = max_bridged_latency_s(
            1 if self.adaptive_steps else self.answers.steps, preset.dt, self.available_steps
        )
        self.latency.initial_s = self.max_bridged_s  # until measured: the most the chunks can bridge

    def latency_s(self) -> float:
        """The latency L chunks are sized for (0 when off: nothing is bridged)."""
        value = self.latency.value_s
        return 0.0 if value is None else value

    def publish_steps(self) -> int:
        if self.fixed_steps:
            return self.n_action_steps
        return steps_to_publish(self.answers.steps, self.latency_s(), self.dt_ns / 1e9, self.available_steps)

    def record_latency(self, seconds: float) -> None:
        """One observation's measured latency (auto), then k for the new estimate."""
        self.latency.add(seconds)
        self.follow_latency()

    def follow_latency(self) -> None:
        """With ``execute_steps`` 0 while bridging: k for the current L."""
        if self.adaptive_steps:
            self.answers.steps = bridging_execute_steps(
                self.n_action_steps, self.latency_s(), self.dt_ns / 1e9, self.available_steps
            )

    def describe(self) -> str:
        if self.fixed_steps:
            return f"{self.n_action_steps} steps per chunk (latency_s off or n_action_steps set)"
        if self.latency.auto:
            return (
                f"enough steps to bridge the measured observation-to-arrival latency (latency_s auto, "
                f"{self.latency.transport_s * 1000:.0f} ms transport allowance; until measured, "
                f"{self.publish_steps()} steps, the most the horizon allows)"
            )
        return f"{self.publish_steps()} steps per chunk (latency_s {self.latency_s()} s)"
