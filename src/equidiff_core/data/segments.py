"""Who was driving the arm at each observation of an episode: a demonstration, the policy, or the operator
correcting it, and when the policy's doubt gate asked for help.

A bag recorded while a policy runs (``equidiff lab``, the twin) holds ``/policy/state`` (latched: ``running``,
or ``paused <reason>``) and ``/teleop/active`` (latched: true while the operator's SpaceMouse has the arm).
From those two topics each observation stamp gets a ``FrameSource``:

* ``OPERATOR``: the SpaceMouse had the arm (a takeover: its commands are the expert's correction);
* ``POLICY``: the policy was running and the operator was not driving;
* ``HOLD``: the policy was paused and nobody drove (the arm held: after the gate's alarm, before a takeover);
* ``DEMO``: a bag without ``/policy/state`` at all: a demonstration, every frame the expert's.

A gate alarm is a pause whose reason starts with ``policy.doubt.HELP_REASON`` (policy_node pauses itself so
when its doubt signal crosses the calibrated threshold: docs/doubt.md). Training weighs samples by the source of their current frame
(``SourceWeights``); ``dataset stats`` counts them.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from ..policy.doubt import HELP_REASON
from ..wire.rosmsg import NS_PER_S
from ..wire.topics import TOPIC_POLICY_STATE, TOPIC_TELEOP_ACTIVE

# what policy_node's /policy/state says when its doubt gate holds the arm: "paused <HELP_REASON>: <why>"
GATE_PAUSE_PREFIX = f"paused {HELP_REASON}"
RUNNING = "running"


class FrameSource(enum.IntEnum):
    """Where an observation's commanded action came from (stored as uint8 in packed episodes)."""

    DEMO = 0
    POLICY = 1
    OPERATOR = 2
    HOLD = 3


@dataclass(frozen=True)
class SourceWeights:
    """How much a training sample counts, by the source of its current frame, relative to a demonstration's 1.

    The defaults follow HG-DAgger (Kelly et al., 2019): the operator's corrections count as demonstrations, the
    policy's own frames and the held ones are left out (weight 0: not sampled at all), since nothing says the
    policy was right before the operator stepped in. Sirius (Liu et al., RSS 2023) weighs interventions up
    and keeps the policy's frames at a lower weight; both are a flag away (``equidiff train
    --intervention-weight``, ``--policy-frame-weight``)."""

    intervention: float = 1.0
    policy: float = 0.0

    def __post_init__(self):
        for name in ("intervention", "policy"):
            value = getattr(self, name)
            if not (np.isfinite(value) and 0.0 <= value <= 100.0):
                raise ValueError(f"{name} weight must be within [0, 100], got {value}")

    def of(self, sources: np.ndarray) -> np.ndarray:
        """(N,) float32 weights of frames with these ``FrameSource`` codes."""
        table = np.zeros(len(FrameSource), np.float32)
        table[FrameSource.DEMO] = 1.0
        table[FrameSource.OPERATOR] = self.intervention
        table[FrameSource.POLICY] = self.policy
        return table[np.asarray(sources, dtype=np.intp)]


def _latched_at(log_ns: np.ndarray, values: list, stamps_ns: np.ndarray, before):
    """The latest value logged at or before each stamp; ``before`` where none was yet."""
    k = np.searchsorted(log_ns, stamps_ns, side="right") - 1
    return [values[i] if i >= 0 else before for i in k]


def frame_sources(episode, stamps_ns: np.ndarray) -> np.ndarray:
    """(N,) uint8 ``FrameSource`` of each observation stamp of ``episode`` (a ``data.bags.Episode`` that decoded
    /policy/state and /teleop/active where the bag has them)."""
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    out = np.full(len(stamps_ns), FrameSource.DEMO, np.uint8)
    if TOPIC_POLICY_STATE not in episode:
        return out
    state = episode[TOPIC_POLICY_STATE]
    running = _latched_at(state.log_ns, [m.data == RUNNING for m in state.messages], stamps_ns, False)
    if TOPIC_TELEOP_ACTIVE in episode:
        teleop = episode[TOPIC_TELEOP_ACTIVE]
        driving = _latched_at(teleop.log_ns, [bool(m.data) for m in teleop.messages], stamps_ns, False)
    else:
        driving = [False] * len(stamps_ns)
    for i, (run, drive) in enumerate(zip(running, driving, strict=True)):
        out[i] = FrameSource.OPERATOR if drive else FrameSource.POLICY if run else FrameSource.HOLD
    return out


def gate_alarms_ns(episode) -> np.ndarray:
    """(K,) log times at which the policy paused itself because its doubt gate fired."""
    if TOPIC_POLICY_STATE not in episode:
        return np.zeros(0, np.int64)
    state = episode[TOPIC_POLICY_STATE]
    fired, previous = [], None
    for t, msg in zip(state.log_ns, state.messages, strict=True):
        if msg.data.startswith(GATE_PAUSE_PREFIX) and msg.data != previous:
            fired.append(int(t))
        previous = msg.data
    return np.asarray(fired, dtype=np.int64)


def source_seconds(sources: np.ndarray, obs_period_ns: int) -> dict[str, float]:
    """Seconds of each source, counting each observation as one period."""
    period_s = obs_period_ns / NS_PER_S
    counts = np.bincount(np.asarray(sources, dtype=np.intp), minlength=len(FrameSource))
    return {source.name.lower(): round(float(counts[source]) * period_s, 3) for source in FrameSource}


__all__ = [
    "GATE_PAUSE_PREFIX",
    "FrameSource",
    "SourceWeights",
    "frame_sources",
    "gate_alarms_ns",
    "source_seconds",
]
