"""The operator loop of ``equidiff lab``: what the screen shows, what each key does, the reset countdown.

ROS-free. The terminal UI (``equidiff_ros.lab_screen``) feeds an ``OperatorLoop`` what the
nodes publish (``observe``), the keys the operator presses (``press``) and the answers of the
service calls it made (``done``); each of these and the UI's periodic ``tick`` hands back the
``Request``s (service calls, run in order) that follow. ``render`` is the screen. How the nodes'
publications read (``NodeView``, franka_node's ``RobotStatus``) is ``lab.node_view``.

Rules a lab relies on (docs/lab.md, "The operator loop"):

* The policy never starts on its own: only ``p`` enables it. Every key that ends an episode,
  homes or acknowledges pauses a running policy first, so the arm holds until the operator
  hands it back.
* Ending an episode (keep or discard) homes the arm and starts the reset countdown; when it runs
  out the next episode starts by itself (``auto_start``) once the arm holds, or the screen says
  the loop is ready. ``s`` starts at once, ``c`` cancels.
* No episode starts while the arm is homing, holding for an acknowledgement or faulted.
* Discarding (and quitting mid-episode) asks for ``y``; any other key says no.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

from ..data.bags import find_bags
from ..policy.doubt import HELP_REASON
from ..wire import topics
from .node_view import (
    NodeView,
)

ROBOT_BLOCKS_START = {
    "homing": "the arm is homing: start once it holds",
    "awaiting_ack": "the arm holds until acknowledged: look at it, then a",
    "faulted": "franka_node could not recover: fix the cause (see the last fault), then a to try again",
}
CONFIRM_TIMEOUT_S = 10.0
DATASET_RECOUNT_S = 5.0
MESSAGES_SHOWN = 6
TRIGGER, SET_BOOL = "std_srvs/srv/Trigger", "std_srvs/srv/SetBool"

# request kind -> (what it does, service, type, request fields); `equidiff lab record|policy|home|ack` use it too
SERVICES: dict[str, tuple[str, str, str, dict]] = {
    "start": ("start an episode", topics.SERVICE_RECORDER_START, TRIGGER, {}),
    "success": ("keep the episode as a success", topics.SERVICE_RECORDER_STOP, TRIGGER, {}),
    "failure": ("keep the episode as a failure", topics.SERVICE_RECORDER_STOP_FAILURE, TRIGGER, {}),
    "discard": ("discard the episode", topics.SERVICE_RECORDER_DISCARD, TRIGGER, {}),
    "enable": ("run the policy", topics.SERVICE_POLICY_ENABLE, SET_BOOL, {"data": True}),
    "pause": ("pause the policy", topics.SERVICE_POLICY_ENABLE, SET_BOOL, {"data": False}),
    "home": ("home the arm", topics.SERVICE_FRANKA_HOME, TRIGGER, {}),
    "ack": ("acknowledge the stop", topics.SERVICE_FRANKA_ACKNOWLEDGE, TRIGGER, {}),
}


@dataclass(frozen=True)
class Request:
    """One service call for the UI's worker to make."""

    kind: str  # a SERVICES key

    @property
    def label(self) -> str:
        return SERVICES[self.kind][0]

    @property
    def service(self) -> str:
        return SERVICES[self.kind][1]

    @property
    def srv_type(self) -> str:
        return SERVICES[self.kind][2]

    @property
    def fields(self) -> dict:
        return dict(SERVICES[self.kind][3])


# key -> (action, what the key line says); the order is the key line's
KEYS: dict[str, tuple[str, str]] = {
    "s": ("start", "start"),
    "k": ("success", "keep: success"),
    "f": ("failure", "keep: failure"),
    "x": ("discard", "discard"),
    "h": ("home", "home"),
    "p": ("policy", "policy on/off"),
    " ": ("pause", "pause policy"),
    "t": ("takeover", "SpaceMouse takes over"),
    "a": ("ack", "acknowledge"),
    "c": ("cancel", "cancel countdown"),
    "q": ("quit", "quit"),
}
KEY_NAMES = {" ": "space"}
KEY_ROWS = (("episode", "skfx"), ("arm", "ha"), ("policy", "p t"), ("screen", "cq"))  # the key lines
# --- the countdown ----------------------------------------------------------------------------


@dataclass
class ResetCountdown:
    """The pause between episodes in which the operator resets the scene (on the UI's clock)."""

    seconds: float
    ends_at: float | None = None

    def start(self, now: float) -> None:
        self.ends_at = now + max(0.0, self.seconds)

    def cancel(self) -> None:
        self.ends_at = None

    @property
    def active(self) -> bool:
        return self.ends_at is not None

    def remaining(self, now: float) -> float:
        return 0.0 if self.ends_at is None else max(0.0, self.ends_at - now)

    def expired(self, now: float) -> bool:
        return self.ends_at is not None and now >= self.ends_at


# --- the loop ---------------------------------------------------------------------------------


@dataclass
class LoopConfig:
    reset_s: float = 10.0  # the reset countdown after each episode
    auto_start: bool = False  # when it runs out (and the arm holds), start the next episode
    home_after_episode: bool = True  # home the arm when an episode ends
    output_dir: Path | None = None  # the recorder's folder, for its episode count (else learned from its paths)


@dataclass
class Counts:
    success: int = 0
    failure: int = 0
    discarded: int = 0


@dataclass
class OperatorLoop:
    config: LoopConfig = field(default_factory=LoopConfig)
    view: NodeView = field(default_factory=NodeView)

    def __post_init__(self):
        self.countdown = ResetCountdown(self.config.reset_s)
        self.counts = Counts()  # this session's episodes
        self.messages: deque[str] = deque(maxlen=MESSAGES_SHOWN)
        self.confirming: tuple[str, str, float] | None = None  # (action, question, asked at)
        self.in_flight: list[str] = []  # labels of requests sent and not answered yet
        self.takeover = False  # the operator said the SpaceMouse drives (until the policy runs again)
        self.started: Path | None = None  # the episode the recorder said it started, until it ends
        self.waiting_for_arm = False  # the countdown ran out, auto start waits for the arm to hold
        self.quit = False
        self.output_dir: Path | None = Path(self.config.output_dir) if self.config.output_dir else None
        self.dataset_count: int | None = None
        self._counted_at = -float("inf")
        self.recording_since: float | None = None

    # -- input ---------------------------------------------------------------------------------
    def observe(self, name: str, value, now: float) -> None:
        """A NodeView field's new value (None: its node is gone)."""
        if name == "franka_diagnostics":
            self.view.franka_diagnostics_at = now
        was_recording, was = self.view.recording, getattr(self.view, name)
        setattr(self.view, name, value)
        if name == "recorder" and value != was:
            path = self.view.recording
            if path is not None and path != was_recording:
                self.recording_since = now
                self.output_dir = self.output_dir or path.parent
            elif path is None:
                self.recording_since = None
                self.started = None  # ended (here or from another terminal)
            self._recount(now, force=True)  # an episode began or was kept
        if name == "policy" and self.view.policy_running:
            self.takeover = False
        help_state = f"paused {HELP_REASON}"
        if name == "policy" and isinstance(value, str) and value.startswith(help_state) and value != was:
            why = value.removeprefix(help_state).lstrip(": ")
            self.say(f"the policy asks for help ({why}): t hands the arm to the SpaceMouse, p lets the policy go on")

    def press(self, key: str, now: float) -> list[Request]:
        """A key: the requests it makes (and what it says on the screen)."""
        if self.confirming is not None:
            action, _question, _at = self.confirming
            self.confirming = None
            if key.lower() == "y":
                return self._confirmed(action, now)
            self.say(f"{action}: cancelled, nothing changed")
            return []
        if key not in KEYS and key.lower() in KEYS:
            key = key.lower()  # caps lock must not make the keys dead
        if key not in KEYS:
            self.say(f"{KEY_NAMES.get(key, key)!r} is not a key here (the keys are on the last line)")
            return []
        return getattr(self, f"_key_{KEYS[key][0]}")(now)

    def done(self, request: Request, ok: bool, message: str, now: float) -> list[Request]:
        """A service's answer (``ok`` False: refused or unreachable, ``message`` says why); what follows."""
        if request.label in self.in_flight:
            self.in_flight.remove(request.label)
        self.say(f"{request.label}: {message}" if ok else f"FAILED to {request.label}: {message}")
        if not ok:
            return []
        follow: list[Request] = []
        if request.kind == "start":
            self.countdown.cancel()
            self.waiting_for_arm = False
            if message.strip():
                self.started = Path(message.strip())
                self.output_dir = self.output_dir or self.started.parent
        elif request.kind in ("success", "failure", "discard"):
            self.started = None
            self.takeover = False  # the next episode begins with the policy paused anyway
            if request.kind == "discard":
                self.counts.discarded += 1
            else:
                setattr(self.counts, request.kind, getattr(self.counts, request.kind) + 1)
            if self.config.home_after_episode:
                follow.append(Request("home"))
            self.countdown.start(now)
            self._recount(now, force=True)
        elif request.kind == "enable":
            self.takeover = False
        return self._sent(follow)

    def tick(self, now: float) -> list[Request]:
        """Time passes: a confirmation expires, the countdown runs out, the folder is recounted."""
        if self.confirming is not None and now - self.confirming[2] > CONFIRM_TIMEOUT_S:
            self.say(f"{self.confirming[0]}: no answer, nothing changed")
            self.confirming = None
        self._recount(now)
        if not self.countdown.expired(now):
            return []
        if not self.config.auto_start:
            self.countdown.cancel()
            self.say("reset done: s starts the next episode")
            return []
        robot, _ = self.view.robot(now)
        if robot is not None and robot.state in ROBOT_BLOCKS_START:
            if not self.waiting_for_arm:
                self.say(f"reset done; the next episode waits: {ROBOT_BLOCKS_START[robot.state]}")
            self.waiting_for_arm = True
            return []
        self.countdown.cancel()
        self.waiting_for_arm = False
        if self.view.recording is not None:
            return []  # someone started one meanwhile (another terminal)
        return self._sent([Request("start")])

    def say(self, text: str) -> None:
        self.messages.append(f"{time.strftime('%H:%M:%S')} {text}")

    # -- keys ----------------------------------------------------------------------------------
    def _key_start(self, now: float) -> list[Request]:
        if self.view.recording is not None:
            self.say(f"already recording {self.view.recording}: k, f or x ends it")
            return []
        robot, _ = self.view.robot(now)
        if robot is not None and robot.state in ROBOT_BLOCKS_START:
            self.say(f"not started: {ROBOT_BLOCKS_START[robot.state]}")
            return []
        self.countdown.cancel()
        self.waiting_for_arm = False
        return self._sent([Request("start")])

    def _end(self, kind: str) -> list[Request]:
        if self.view.recorder == "idle":
            self.say("not recording: s starts an episode")
            return []
        return self._sent([*self._pause_first(), Request(kind)])

    def _key_success(self, now: float) -> list[Request]:
        return self._end("success")

    def _key_failure(self, now: float) -> list[Request]:
        return self._end("failure")

    def _key_discard(self, now: float) -> list[Request]:
        if self.view.recorder == "idle":
            self.say("not recording: nothing to discard")
            return []
        return self._ask("discard", f"delete {self.view.recording or 'the episode being recorded'}?", now)

    def _key_home(self, now: float) -> list[Request]:
        return self._sent([*self._pause_first(), Request("home")])

    def _key_policy(self, now: float) -> list[Request]:
        if self.view.policy is None:
            self.say(f"no policy node ({topics.TOPIC_POLICY_STATE}): nothing to switch")
            return []
        if self.view.policy_running:
            return self._sent([Request("pause")])
        robot, _ = self.view.robot(now)
        if robot is not None and robot.state in ("awaiting_ack", "faulted"):
            self.say(f"policy not enabled: {ROBOT_BLOCKS_START[robot.state]}")
            return []
        return self._sent([Request("enable")])

    def _key_pause(self, now: float) -> list[Request]:
        return self._sent([Request("pause")])

    def _key_takeover(self, now: float) -> list[Request]:
        self.takeover = True
        if self.view.policy_running:
            self.say("the SpaceMouse drives: pausing the policy; p hands the arm back to it")
            return self._sent([Request("pause")])
        self.say("the SpaceMouse drives (the policy is not running)")
        return []

    def _key_ack(self, now: float) -> list[Request]:
        return self._sent([*self._pause_first(), Request("ack")])

    def _key_cancel(self, now: float) -> list[Request]:
        if not self.countdown.active:
            self.say("no countdown to cancel")
            return []
        self.countdown.cancel()
        self.waiting_for_arm = False
        self.say("countdown cancelled: s starts the next episode")
        return []

    def _key_quit(self, now: float) -> list[Request]:
        if self.view.recording is not None:
            return self._ask("quit", "quit this screen? the episode keeps recording", now)
        self.quit = True
        return []

    def _ask(self, action: str, question: str, now: float) -> list[Request]:
        self.confirming = (action, question, now)
        return []

    def _confirmed(self, action: str, now: float) -> list[Request]:
        if action == "quit":
            self.quit = True
            return []
        return self._sent([*self._pause_first(), Request(action)])

    def _pause_first(self) -> list[Request]:
        """A running policy is paused before the arm is homed, acknowledged or the episode ends."""
        return [Request("pause")] if self.view.policy_running else []

    def _sent(self, requests: list[Request]) -> list[Request]:
        self.in_flight.extend(r.label for r in requests)
        return requests

    def _recount(self, now: float, force: bool = False) -> None:
        """The recorder folder's kept episodes (bags), at most every DATASET_RECOUNT_S unless forced."""
        if self.output_dir is None or (not force and now - self._counted_at < DATASET_RECOUNT_S):
            return
        self._counted_at = now
        if not self.output_dir.is_dir():
            self.dataset_count = None  # the recorder runs on another machine: unknown here
            return
        unfinished = {self.view.recording, self.started}  # the recorder's answer may come before its status
        self.dataset_count = sum(1 for p in find_bags([self.output_dir]) if p not in unfinished)

    # -- output --------------------------------------------------------------------------------
    def render(self, now: float) -> list[tuple[str, str]]:
        """The screen as (style, text) fragments: styles ``ok``, ``warn``, ``bad``, ``dim``, ``title``, ``key``."""
        out: list[tuple[str, str]] = []

        def row(label: str, parts: list[tuple[str, str]]) -> None:
            out.append(("title", f"{label:<10}"))
            out.extend(parts)
            out.append(("", "\n"))

        out.append(("title", "equidiff lab: the operator loop"))
        out.append(("dim", "   (q quits this screen; the nodes keep running)\n\n"))

        robot, note = self.view.robot(now)
        if robot is None:
            row("ROBOT", [("warn", "unknown  "), ("dim", note)])
        else:
            style = {"holding": "ok", "moving": "ok", "homing": "warn"}.get(robot.state, "bad")
            parts = [(style, robot.state.replace("_", " ").upper())]
            if robot.reason:
                parts.append(("", f"  {robot.reason}"))
            if robot.state == "awaiting_ack":
                parts.append(("warn", "  (look at the arm, then a)"))
            parts.append(("dim", f"  [{note or robot.source}]"))
            row("ROBOT", parts)
            if robot.last_fault:
                when = f" at {_clock_text(robot.last_fault_ns)}" if robot.last_fault_ns else ""
                row("", [("dim", f"last fault{when}: "), ("", robot.last_fault)])

        recording = self.view.recording
        if self.view.recorder is None:
            row("RECORDER", [("warn", "(no recorder node)")])
        elif recording is not None:
            held = "" if self.recording_since is None else f"  {_duration_text(now - self.recording_since)}"
            row("RECORDER", [("bad", "RECORDING"), ("", f"  {recording}{held}")])
        else:
            row("RECORDER", [("ok", self.view.recorder.upper())])
        c = self.counts
        folder = ""
        if self.output_dir is not None:
            known = "?" if self.dataset_count is None else str(self.dataset_count)
            folder = f"  ·  in {self.output_dir}: {known}"
        row(
            "EPISODES",
            [("", f"this session: {c.success + c.failure} kept ({c.success} success, {c.failure} failure)"),
             ("dim", f", {c.discarded} discarded{folder}")],
        )  # fmt: skip

        if self.view.policy is None:
            row("POLICY", [("dim", "(no policy node)")])
        elif self.view.policy_running:
            row("POLICY", [("warn", "ON"), ("", "  running: its chunks move the arm")])
        elif self.view.policy.startswith(f"paused {HELP_REASON}"):  # its doubt gate holds the arm
            why = self.view.policy.removeprefix(f"paused {HELP_REASON}").lstrip(": ")
            row("POLICY", [("warn", "ASKS FOR HELP"), ("", f"  {why}"),
                           ("dim", "   t: SpaceMouse takes over  ·  p: let the policy go on")])  # fmt: skip
        else:
            row("POLICY", [("ok", "PAUSED"), ("", f"  {self.view.policy.removeprefix('paused').strip()}")])

        teleop: list[tuple[str, str]]
        if self.view.teleop_active is None:
            teleop = [("dim", "(no teleop node)")]
        elif self.view.teleop_active:
            teleop = [("warn", "SPACEMOUSE DRIVING")]
        else:
            teleop = [("", "idle")]
        if self.takeover:
            teleop.append(("warn", "  the SpaceMouse has the arm (t); p hands it back to the policy"))
        row("TELEOP", teleop)

        if self.countdown.active:
            left = self.countdown.remaining(now)
            if self.waiting_for_arm:
                text = "reset done: the next episode starts once the arm holds"
            elif self.config.auto_start:
                text = f"reset the scene: next episode in {left:.0f} s"
            else:
                text = f"reset the scene: {left:.0f} s"
            row("RESET", [("warn", text), ("dim", "   s: start now  ·  c: cancel")])
        else:
            row("RESET", [("dim", "-")])

        out.append(("", "\n"))
        if self.in_flight:
            out.append(("warn", f"... {', '.join(self.in_flight)}\n"))
        for line in self.messages:
            out.append(("", f"{line}\n"))
        if self.confirming is not None:
            out.append(("bad", f"\n{self.confirming[1]}  y: yes  ·  any other key: no\n"))
        out.append(("", "\n"))
        for group, keys in KEY_ROWS:
            out.append(("dim", f"{group:<10}"))
            for key in keys:
                out.append(("key", f" {KEY_NAMES.get(key, key)} "))
                out.append(("", f" {KEYS[key][1]}   "))
            out.append(("", "\n"))
        return out

    def screen_text(self, now: float) -> str:
        return "".join(text for _style, text in self.render(now))


def _duration_text(seconds: float) -> str:
    seconds = max(0, int(seconds))
    return f"{seconds // 60}:{seconds % 60:02d}"


def _clock_text(stamp_ns: int) -> str:
    """A wall-clock stamp as the local time of day; a simulated-time one (the twin: small) as seconds."""
    if stamp_ns > 10**18:  # after 2001: a wall-clock stamp
        return time.strftime("%H:%M:%S", time.localtime(stamp_ns / 1e9))
    return f"t={stamp_ns / 1e9:.1f} s"
