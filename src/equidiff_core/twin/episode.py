"""One episode, one sequence, wherever it runs (ROS-free).

    home -> reset the scene -> settle -> start recording -> act, judging success -> stop: keep or discard

``run_episode`` is that sequence. *Where* it runs is an ``EpisodeWorld``: the live twin over
ROS (``equidiff_ros.twin.world``) or the in-process twin (``twin.demos``). *Who* acts is an
``Actor``: the policy through the live graph or in-process (``twin.direct_execution.DirectPolicy``), or
the scripted expert streaming its plan. So ``equidiff twin run``, ``twin collect`` (both paths),
``bench twin`` and the in-process evaluation (``twin evaluate``, ``bench generalization``,
``bench chunking``) share one answer to
"home first", "success must hold for hold_s without a break" (``SuccessHold``), "a stalled
episode ends at once and keeps its bag" and "a failure is kept or discarded".
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

__all__ = ["Actor", "EpisodeResult", "EpisodeWorld", "SuccessHold", "run_episode"]


class SuccessHold:
    """The task counts as solved once it has been successful for ``hold_s`` without a break.

    The one judge of "success held" for every episode loop (live supervisor, expert demos,
    in-process evaluation): a lapse restarts the hold, so a block that bounces out of the bowl
    is not a success."""

    def __init__(self, hold_s: float):
        self.hold_s = float(hold_s)
        self.since: float | None = None  # time the current unbroken success began

    def update(self, success: bool, now_s: float) -> bool:
        """Report the success test's result at ``now_s``; True once it has held ``hold_s``."""
        if not success:
            self.since = None
            return False
        if self.since is None:
            self.since = now_s
        return now_s - self.since >= self.hold_s


class EpisodeWorld(Protocol):
    """Where an episode runs: the arm, the scene, the clock, the success test and the recorder."""

    def home(self) -> None:
        """Bring the arm to the ready pose (after acknowledging a stop it holds for, saying so)."""

    def reset_scene(self, seed: int) -> None:
        """Place the objects as ``seed`` draws them."""

    def settle(self, seconds: float) -> None:
        """Let ``seconds`` of the episode clock pass (cameras and voxels show the new scene)."""

    def now_s(self) -> float:
        """The episode clock: simulated time in the twin."""

    def success(self) -> bool:
        """The task's success test now (the scene's, not the actor's opinion)."""

    def start_recording(self) -> str:
        """Open the episode's bag; its path ('' when this world records nothing)."""

    def stop_recording(self, keep: bool, success: bool, note: str) -> None:
        """Close the bag with its outcome and ``note`` (``keep``) or delete it."""


class Actor(Protocol):
    """Who acts during the episode."""

    def begin(self) -> float:
        """Start acting; returns the clock time the episode's duration counts from."""

    def advance(self) -> None:
        """Act until the next instant success is judged."""

    def judging(self) -> bool:
        """Whether success counts now (the scripted expert: once its plan is done)."""

    def done(self) -> bool:
        """Nothing is left to do before the time limit (the expert's plan and its extra time)."""

    def stalled(self) -> str:
        """Why the episode cannot go on ('' while it can): a stage of the pipeline did not deliver."""

    def end(self) -> None:
        """Stop acting and hold the arm where it is (called whatever happened)."""


@dataclass
class EpisodeResult:
    seed: int
    success: bool
    duration_s: float  # from the actor's start to the start of the held success (or to the end)
    stalled: str  # '' unless the episode ended because a stage did not deliver
    bag: str  # '' when nothing was recorded or the bag was discarded


def run_episode(
    world: EpisodeWorld,
    actor: Actor,
    seed: int,
    max_duration_s: float,
    hold_s: float,
    settle_s: float = 0.6,
    keep: Callable[[bool], bool] = lambda success: True,
    note: str = "",
) -> EpisodeResult:
    """The sequence in the module doc; ``keep(success)`` decides whether the bag stays.

    The bag is closed (kept as a failure, or discarded as ``keep`` says) whatever happens while
    acting, an exception included, so nothing recorded is lost silently."""
    world.home()
    world.reset_scene(seed)
    world.settle(settle_s)
    bag = world.start_recording()
    hold = SuccessHold(hold_s)
    success, stalled = False, ""
    start = end = world.now_s()
    try:
        start = actor.begin()
        while world.now_s() - start < max_duration_s and not actor.done():
            stalled = actor.stalled()
            if stalled:
                break
            if actor.judging() and hold.update(world.success(), world.now_s()):
                success = True
                break
            actor.advance()
        end = world.now_s()
    except BaseException:
        # keep what was recorded, marked as interrupted; if the world itself failed (a node
        # died), closing fails too, and the original error is the one that says why
        with contextlib.suppress(Exception):
            actor.end()
        with contextlib.suppress(Exception):
            world.stop_recording(True, False, f"seed={seed} interrupted")
        raise
    actor.end()
    kept = keep(success)
    words = [f"seed={seed}", note, f"stalled: {stalled}" if stalled else ""]
    world.stop_recording(kept, success, " ".join(w for w in words if w))
    duration = (hold.since if success else end) - start
    return EpisodeResult(seed, success, round(duration, 2), stalled, bag if kept else "")
