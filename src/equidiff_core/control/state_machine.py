"""The safety controller's states, the events that move it between them, and the one table that does.

``Controller`` (and its ``stops.HeldState`` half) never sets a state: its methods raise an
``Event`` and ``Controller._fire`` looks ``(state, event)`` up in ``TRANSITIONS``, moves to the
state found there and applies its ``Action`` to the trajectory. A pair missing from the table is
a bug (``IllegalTransition``), never a silent move; operator calls that may come at any time
(a chunk, ``go_home``, ``acknowledge``, ``require_acknowledgement``) ask ``permits`` first and
are refused otherwise.

Three states await an operator (``AWAITING_OPERATOR``): every chunk is refused there and the
only ways out are the acknowledgement's events, so nothing resumes on its own. The states
operators see are fewer (``STATUS``: what /franka/status, /diagnostics and ``equidiff lab``
show): the arm held for an acknowledgement while streaming or not both read ``awaiting_ack``,
both homings ``homing``.

docs/control.md draws ``TRANSITIONS`` with ``mermaid_diagram()``, and a test keeps the two equal.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum


class SafetyState(Enum):
    HOLDING = "holding"  # streaming, holding a pose; the next chunk is followed
    TRACKING = "tracking"  # streaming a chunk's trajectory (the watchdog counts from its last step)
    HOMING = "homing"  # streaming go_home's glide; chunks are refused until it arrives
    AWAITING_ACK = "awaiting_ack"  # streaming, holding where the arm is; chunks refused until acknowledged
    STOPPED = "stopped"  # nothing streamed (the robot stopped, the arm ran away again, or the TCP is outside)
    FAULTED = "faulted"  # an acknowledged recovery failed; nothing streamed, the next acknowledgement retries
    MOVING_HOME = "moving_home"  # acknowledged with the TCP outside: the robot's planned move home, then streaming


class Event(Enum):
    STARTED = "started"  # streaming started where the arm is
    STARTED_OUTSIDE = "started outside"  # the TCP is outside the box or cone: nothing may be streamed
    HOLD_REQUESTED = "hold requested"  # require_acknowledgement: an operator must look first
    CHUNK_ACCEPTED = "chunk accepted"
    CHUNK_REJECTED = "chunk rejected"
    WATCHDOG_EXPIRED = "watchdog expired"  # no new chunk within watchdog_timeout_s of the last one's final step
    HOME_REQUESTED = "home requested"  # go_home
    HOME_REACHED = "home reached"  # go_home's glide ran to its end
    TICK_FAILED = "tick failed"  # a bug in a tick: hold rather than stream stale targets
    ROBOT_STOPPED = "robot stopped"  # user stop, reflex, lost connection, robot error
    DIVERGED = "diverged"  # tracking error, joint speed, a joint moving into its limit
    DIVERGED_OUTSIDE = "diverged outside"  # ... and the TCP ended outside the box or cone: no streaming from there
    ACKNOWLEDGED = "acknowledged"  # an acknowledgement with nothing to recover
    ACK_REFUSED = "ack refused"  # the user stop is still pressed
    RECOVERED = "recovered"  # the acknowledgement recovered the robot and streaming started again
    RECOVERED_OUTSIDE = "recovered outside"  # recovered, but the TCP is outside: it moves home first
    RECOVERY_FAILED = "recovery failed"
    MOVED_HOME = "moved home"  # the planned move home ended and streaming started
    MOVE_HOME_FAILED = "move home failed"


class Action(Enum):
    """What a transition does to the commanded trajectory (the robot itself is the caller's business)."""

    NONE = "none"
    FOLLOW = "follow"  # follow the trajectory the caller just scheduled
    HOLD = "hold"  # drop the trajectory, hold the last command
    HOLD_MEASURED = "hold measured"  # drop the trajectory, hold where the arm is (the shortest stop)
    HOLD_HOME = "hold home"  # drop the trajectory, hold the home pose
    RESEED = "reseed"  # streaming (re)started: drop the trajectory, command the measured pose


@dataclass(frozen=True)
class Transition:
    target: SafetyState
    action: Action


S, E, A = SafetyState, Event, Action  # short names for the table below
_STREAMING_STOPS = {
    E.HOLD_REQUESTED: Transition(S.AWAITING_ACK, A.HOLD),
    E.ROBOT_STOPPED: Transition(S.STOPPED, A.HOLD),
    E.DIVERGED: Transition(S.AWAITING_ACK, A.RESEED),
    # Streaming seeded outside would pull the arm back in unasked (every command is kept inside):
    # it stays stopped, and the acknowledgement moves it home first.
    E.DIVERGED_OUTSIDE: Transition(S.STOPPED, A.HOLD),
}
_ACKNOWLEDGEMENT = {
    E.ACK_REFUSED: None,  # stays
    E.RECOVERED: Transition(S.HOLDING, A.RESEED),
    E.RECOVERED_OUTSIDE: Transition(S.MOVING_HOME, A.NONE),
    E.RECOVERY_FAILED: Transition(S.FAULTED, A.NONE),
}


def _table() -> dict[tuple[SafetyState, Event], Transition]:
    rows: dict[SafetyState, dict[Event, Transition | None]] = {
        S.HOLDING: {
            E.STARTED: Transition(S.HOLDING, A.RESEED),
            E.STARTED_OUTSIDE: Transition(S.STOPPED, A.NONE),
            E.CHUNK_ACCEPTED: Transition(S.TRACKING, A.FOLLOW),
            E.HOME_REQUESTED: Transition(S.HOMING, A.FOLLOW),
            **_STREAMING_STOPS,
        },
        S.TRACKING: {
            E.CHUNK_ACCEPTED: Transition(S.TRACKING, A.FOLLOW),
            E.WATCHDOG_EXPIRED: Transition(S.HOLDING, A.HOLD_MEASURED),
            E.HOME_REQUESTED: Transition(S.HOMING, A.FOLLOW),
            E.TICK_FAILED: Transition(S.HOLDING, A.HOLD),
            **_STREAMING_STOPS,
        },
        S.HOMING: {
            # The glide ends at a known instant: its arrival, not the watchdog, ends it.
            E.HOME_REACHED: Transition(S.HOLDING, A.HOLD_HOME),
            E.HOME_REQUESTED: Transition(S.HOMING, A.FOLLOW),
            E.TICK_FAILED: Transition(S.HOLDING, A.HOLD),
            **_STREAMING_STOPS,
        },
        S.AWAITING_ACK: {
            E.ACKNOWLEDGED: Transition(S.HOLDING, A.NONE),  # it holds already
            E.HOLD_REQUESTED: None,  # the newest reason replaces the last
            E.ROBOT_STOPPED: Transition(S.STOPPED, A.HOLD),
            # Running away again while held: streaming stays stopped (the robot holds itself).
            E.DIVERGED: Transition(S.STOPPED, A.HOLD),
        },
        S.STOPPED: {**_ACKNOWLEDGEMENT, E.HOLD_REQUESTED: None},
        # Awaits an acknowledgement anyway: a hold request changes nothing.
        S.FAULTED: dict(_ACKNOWLEDGEMENT),
        S.MOVING_HOME: {
            E.MOVED_HOME: Transition(S.HOLDING, A.RESEED),
            E.MOVE_HOME_FAILED: Transition(S.FAULTED, A.NONE),
            E.ROBOT_STOPPED: Transition(S.STOPPED, A.NONE),
            E.HOLD_REQUESTED: Transition(S.STOPPED, A.NONE),  # the move home waits for a new acknowledgement
        },
    }
    table = {}
    for state, events in rows.items():
        events.setdefault(E.CHUNK_REJECTED, None)  # a rejected chunk changes nothing, whatever the state
        for event, transition in events.items():
            table[state, event] = transition or Transition(state, A.NONE)
    return table


# (state, event) -> (next state, action). A pair that is not here cannot happen (IllegalTransition).
TRANSITIONS: dict[tuple[SafetyState, Event], Transition] = _table()

# The states that stream a trajectory: the arm may move, the watchdog (or the glide's arrival) is armed.
MOVING = frozenset({S.TRACKING, S.HOMING})
# The states the loop does not stream in: it only polls the robot (or moves it home).
NOT_STREAMING = frozenset({S.STOPPED, S.FAULTED, S.MOVING_HOME})
# The states only an acknowledgement leaves: every chunk and go_home are refused.
AWAITING_OPERATOR = frozenset({S.AWAITING_ACK, S.STOPPED, S.FAULTED})

# What operators see (/franka/status "state", /diagnostics, `equidiff lab`): unchanged strings.
STATUS: dict[SafetyState, str] = {
    S.HOLDING: "holding",
    S.TRACKING: "moving",
    S.HOMING: "homing",
    S.AWAITING_ACK: "awaiting_ack",
    S.STOPPED: "awaiting_ack",
    S.FAULTED: "faulted",
    S.MOVING_HOME: "homing",
}
STATES = ("moving", "holding", "homing", "awaiting_ack", "faulted")
INITIAL = S.HOLDING  # before start(): nothing is streamed yet, and start() seeds the hold


class IllegalTransition(RuntimeError):
    """An event the table has no transition for in the current state (a bug in the controller)."""


def permits(state: SafetyState, event: Event) -> bool:
    return (state, event) in TRANSITIONS


def next_transition(state: SafetyState, event: Event) -> Transition:
    try:
        return TRANSITIONS[state, event]
    except KeyError:
        raise IllegalTransition(f"no transition for '{event.value}' in state {state.name}") from None


def mermaid_diagram() -> str:
    """``TRANSITIONS`` as a Mermaid ``stateDiagram-v2`` block (docs/control.md), one edge per pair
    of states, labelled ``event / action`` (the action left out when there is none)."""
    edges: dict[tuple[SafetyState, SafetyState], list[str]] = {}
    for (state, event), transition in TRANSITIONS.items():
        label = event.value if transition.action is A.NONE else f"{event.value} / {transition.action.value}"
        edges.setdefault((state, transition.target), []).append(label)
    lines = ["stateDiagram-v2", f"    [*] --> {INITIAL.name}"]
    lines += [f"    {state.name} : {STATUS[state]}" for state in SafetyState]
    lines += [f"    {a.name} --> {b.name} : {', '.join(labels)}" for (a, b), labels in edges.items()]
    return "\n".join(lines) + "\n"
