"""The campaign's state and its moves (``equidiff bench safety``): the running nodes, what the arm did
(from the ROS side's recordings) and the commands a policy or an operator gives, shared by every fault.

The ROS side is passed in as a ``Probe`` (``equidiff_ros.benches.safety_probe.SafetyProbe``): the core
stays ROS-free and drives the graph only through it and through the client it opens.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, Self

import numpy as np

from equidiff_core import geometry
from equidiff_core.control import metrics
from equidiff_core.geometry import down_pose
from equidiff_core.twin.processes import start_node
from equidiff_core.wire.chunk import PoseChunk
from equidiff_core.wire.rosmsg import NS_PER_S
from equidiff_core.wire.topics import SERVICE_FRANKA_HOME, SERVICE_RECORDER_START, SERVICE_RECORDER_STOP

STEP_NS = NS_PER_S // 5  # the step (0.2 s) of the chunks the campaign sends


class Probe(Protocol):
    """What the campaign needs of the ROS side (rclpy cannot live in the core)."""

    ServiceError: type[Exception]  # what ``trigger`` raises for a missing or refusing service

    def open_client(self, lab, lab_path: str) -> Any:
        """A client of the live graph (``equidiff_ros.control_client.ControlClient``)."""

    def watch_status(self, client) -> Any:
        """A watch on /franka/status and the measured pose (``latest``, ``wait``, ``ee_pose``)."""

    def acknowledge(self) -> tuple[bool, str]:
        """franka_node's /franka/acknowledge as the operator calls it: (granted, its message)."""

    def trigger(self, service: str) -> str:
        """A std_srvs/Trigger service's message, or ``ServiceError``."""

    def approach(self, client, target: np.ndarray, speed: float = 0.05, settle: float = 0.5) -> None:
        """A straight line from the TCP to ``target``, streamed as chunks."""

    def shipped_policy(self) -> tuple[Path, str] | None:
        """(checkpoint, label) of the twin's trained policy, if there is one."""


@dataclass
class Campaign:
    """The running campaign: the sim, the nodes it started, the probe's client and status watch, and what
    it counts across the faults (auto-resumes, the largest excursion outside the safety box)."""

    client: Any  # the probe's client (ControlClient)
    sim: object  # SimServer
    box: object  # SafetyBox
    tmp: Path
    franka_params: dict
    still_m: float
    box_margin_m: float
    shm: str = ""  # the twin sim's shared state, for its cameras
    probe: Probe | None = None
    status: Any = None  # the probe's status watch
    franka: object = None  # its Popen
    recorder: object = None
    episodes: list = field(default_factory=list)
    auto_resumes: int = 0
    excursion_m: float = 0.0
    t_start: float = field(default_factory=time.time)
    home_position: np.ndarray = field(default_factory=lambda: np.array([0.45, 0.0, 0.30]))  # control.yaml's
    joint_limits: tuple = ((), ())  # control.yaml's joint_position_min_rad / _max_rad

    # --- observations --------------------------------------------------------------------
    def diag(self, key: str) -> int:
        return int(float(self.client.diag_value("franka_node", key, 0) or 0))

    def wait_diag(self, key: str, above: int, timeout: float = 6.0) -> bool:
        try:  # diagnostics come once a second
            self.client.wait_for(lambda: self.diag(key) > above, timeout, f"franka_node's {key}")
            return True
        except TimeoutError:
            return False

    def here(self) -> np.ndarray:
        return self.client.latest_position().copy()

    def moved_m(self, t0: float, t1: float) -> float:
        """Largest distance of the TCP from where it was at ``t0``, over [t0, t1] (wall clock, s)."""
        self.wait_past(t1)
        _, p = self.client.samples("poses", t0, t1)
        return float(np.max(np.linalg.norm(p - p[0], axis=1))) if len(p) else float("nan")

    def wait_past(self, t: float, timeout: float = 10.0) -> None:
        deadline = time.monotonic() + max(0.0, t - time.time()) + timeout
        while time.monotonic() < deadline and not (self.client.data.poses and self.client.data.poses[-1][0] > t):
            time.sleep(0.05)

    def note_excursion(self, t0: float, t1: float | None = None) -> float:
        _, p = self.client.samples("poses", t0, time.time() if t1 is None else t1)
        out = metrics.max_outside_box(p, self.box.min_corner, self.box.max_corner) if len(p) else 0.0
        self.excursion_m = max(self.excursion_m, out)
        return out

    def alive(self) -> bool:
        return self.franka is not None and self.franka.poll() is None

    # --- commands --------------------------------------------------------------------------
    def hold_chunk(self, position=None, width: float = 0.08, steps: int = 4):
        now = time.time_ns()
        p = self.here() if position is None else position
        return PoseChunk(
            now,
            now + np.arange(steps, dtype=np.int64) * STEP_NS,
            np.stack([down_pose(p)] * steps),
            np.full(steps, width),
        )

    def home(self) -> None:
        """Back to the home pose (and its orientation: the policy may have yawed the hand) through
        franka_node's own /franka/home, then wait until the arm is there."""
        for attempt in range(3):
            message = self.probe.trigger(SERVICE_FRANKA_HOME)
            seconds = float(message.rsplit(" in ", 1)[-1].split()[0])  # "homing to [...] in N s"
            try:  # a sim far below real time runs the glide late; the watchdog then holds it short of home: again
                self.client.wait_for(
                    lambda: np.linalg.norm(self.here() - self.home_position) < 0.002,
                    seconds + 10.0,
                    "the arm home",
                    self.franka,
                )
                break
            except TimeoutError:
                if attempt == 2:
                    raise
        time.sleep(0.3)

    def follow_me(self, seconds: float, direction=(0.0, 1.0, 0.0), speed: float = 0.03) -> float:
        """What a policy sends: chunks that start where the arm is and move slowly on; returns the send start."""
        d = np.asarray(direction, dtype=float)
        t0 = time.time()
        end = time.monotonic() + seconds
        while True:
            now = time.time_ns()
            here = self.status.ee_pose if self.status is not None and self.status.ee_pose is not None else None
            start = self.here() if here is None else here[:3, 3]
            R = down_pose(start)[:3, :3] if here is None else here[:3, :3]  # keeps the measured orientation
            times = now + np.arange(8, dtype=np.int64) * STEP_NS
            poses = np.stack([geometry.make_pose(R, start + d * speed * 0.2 * i) for i in range(8)])
            self.client.publish_chunk(PoseChunk(now, times, poses, np.full(8, 0.08)))
            if time.monotonic() >= end:  # one chunk at least (``seconds`` 0: exactly one)
                return t0
            time.sleep(0.2)


class Sender:
    """A policy that goes on publishing whatever happens to franka_node (``publish`` once per 0.2 s)."""

    def __init__(self, publish: Callable[[], None]):
        self.publish, self.stop = publish, threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self.stop.is_set():
            self.publish()
            self.stop.wait(0.2)

    def __enter__(self) -> Self:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join(timeout=5)


# --- set-up ----------------------------------------------------------------------------------


def franka_log(c: Campaign) -> str:
    logs = sorted(c.tmp.glob("franka_node*.log"), key=lambda p: p.stat().st_mtime)
    return logs[-1].read_text(errors="replace") if logs else ""


def start_franka(c: Campaign) -> bool:
    n = sum(1 for _ in c.tmp.glob("franka_node*.log"))
    c.franka = start_node("franka_node", c.franka_params, c.tmp / f"franka_node{n or ''}.log", priority=True)
    return c.franka.poll() is None


def start_episode(c: Campaign) -> Path:
    for attempt in range(6):  # a recorder_node starting on a loaded machine takes a while to offer it
        try:
            path = Path(c.probe.trigger(SERVICE_RECORDER_START))
            break
        except c.probe.ServiceError:
            if attempt == 5 or (c.recorder is not None and c.recorder.poll() is not None):
                raise
    c.episodes.append(path)
    return path


def stop_episode(c: Campaign) -> None:
    c.probe.trigger(SERVICE_RECORDER_STOP)
