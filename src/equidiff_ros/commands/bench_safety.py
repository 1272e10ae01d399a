"""`equidiff bench safety`: a fault campaign against franky-sim through franka_node (issues 16 and 27).

    equidiff bench safety                          # all fourteen faults, ~6 min on 2 cores
    equidiff bench safety --faults nan,out_of_box,user_stop,franka_node_killed
    equidiff bench safety --faults out_of_box --box-margin-mm 0   # the raw overshoot the margin is set from

Starts the twin's franky-sim (its scene, scene seed chosen so no object lies near the arm's
approaches; the robot faults are injected at the libfranka protocol level, so the real franky
client raises the real exceptions: ``robots.franky.faults``), franka_node (real franky client,
real rclpy, separate processes, the lab's defaults: it holds at start until acknowledged, which
the bench does as the operator) and recorder_node, then drives franka_node over
/franka/command_chunk the way the policy does and injects one fault at a time, each checked
for what "survived" means for it:

* ``nan``, ``jump``, ``stale_chunk``, ``out_of_cone``: a chunk with a NaN pose / a first step
  15 cm from the arm / stamped 2 s ago / tilted 60 deg from tool-down. Survived: counted as
  rejected in franka_node's /diagnostics, the node alive, the arm still (< ``--still-mm``).
* ``out_of_box``: at the speed limit (chunks asking for 0.3 m/s, the filter allows 0.25) into
  the floor, the -y and +x walls and the corner of the -y wall and the floor, each from a start
  9-21 cm away. Reports each
  approach's ``overshoot_mm`` (the measured TCP past the plane commands stop at: the box shrunk
  by control.yaml's ``safety.box_margin_m``), its ``outside_mm`` (past the safety box itself,
  lab.yaml), ``travel_mm`` and ``speed_limited`` (franka_node's speed limit cut the command). Survived: 0 mm outside. With ``--box-margin-mm 0`` the
  overshoot is the raw one the margin is set from (docs/control.md).
* ``user_stop``: pressed while the arm follows a policy's chunks (the sender goes on throughout),
  held 2 s, an acknowledgement tried while pressed, released, then acknowledged. ``reflex``:
  a collision reflex mid-motion, then acknowledged. ``connection_lost``: the robot stops
  answering for 1.5 s (libfranka's 1 s receive timeout kills its connection), then
  acknowledged (franka_node connects again). ``divergence``: the sender yaws the hand on and on
  until joint 7 runs into its position limit (franka_node's divergence stop), then acknowledged.
  Survived, each: franka_node (the same process) held (/franka/status ``awaiting_ack`` with the
  fault's reason), the arm still and every chunk refused until the acknowledgement (an
  acknowledgement while the user stop is pressed is refused), and after it the arm follows the
  chunks again.
* ``camera_stall``: the twin's cameras (three camera_nodes, backend twin, rendering the sim's
  own state) -> voxel_node -> policy_node (``--policy``: ``shipped``, the twin's trained
  checkpoint, the default; or ``standin``, an untrained tiny one that starts in seconds) drive
  the arm; one camera_node is frozen (SIGSTOP) for 5 s, so voxel_node's sets stop.
  ``policy_chunks_accepted`` says how many of the policy's chunks franka_node executed.
  Survived: no chunk answers an observation taken during the stall, the arm held, chunks again
  once the camera is back.
* ``policy_node_killed``: that policy_node is SIGKILLed. Survived: the arm held (watchdog).
* ``recorder_sigkill``: recorder_node is SIGKILLed mid-episode. Survived: the episode is
  readable after ``equidiff bags repair`` and franka_node did not notice.
* ``gripper_stuck``: franky-sim's hand is jammed (the fingers stay and the gripper command
  never finishes) while a new width is sent and the arm moves 3 cm. Survived: the fingers did
  not move (the fault took), the arm reached its target (< 5 mm) and its state kept coming (no
  gap longer than half the 6 s jam: a control loop waiting on the gripper would stall until the
  jam clears; a loaded 2-core machine starves it for ~1.4 s at times), and after the jam clears
  a new width is reached.
* between faults the arm goes back home through franka_node's ``/franka/home`` (refused, and
  the campaign's next fault then fails, if a stop still awaited acknowledgement).
* ``franka_node_killed``: SIGKILL while the arm runs a chunk; the sender keeps publishing
  chunks that start where the arm is. franka_node is started again (same ``run_dir``): it
  must find the unclean exit, not move and hold; chunks are refused until /franka/acknowledge,
  after which the arm follows them again. Survived: all of that.

Across the campaign: ``max_excursion_mm`` (largest distance of the measured TCP outside the
safety box), ``auto_resumes`` (times the arm moved or a chunk was accepted while franka_node
awaited an acknowledgement: must be 0) and ``episodes_lost`` (recorded episodes that cannot be
read, after repair: must be 0). Baseline in the same run: the arm's drift while holding still
before any fault (``baseline_hold_drift_mm``), against which ``--still-mm`` is set.

Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Self

import numpy as np

from equidiff_core.rosmsg import arm_joint_positions, gripper_width_from_joint_state, pose_from_msg
from equidiff_ros.control_client import MS, ControlClient, down_pose

FAULTS = (
    "nan",
    "jump",
    "stale_chunk",
    "out_of_box",
    "out_of_cone",
    "user_stop",
    "reflex",
    "connection_lost",
    "divergence",
    "camera_stall",
    "policy_node_killed",
    "recorder_sigkill",
    "gripper_stuck",
    "franka_node_killed",
)
POLICY_FAULTS = ("camera_stall", "policy_node_killed")
STALL_S = 5.0  # how long camera_stall freezes a camera_node
# The arm's approaches in out_of_box start here and head for the floor, the -y and +x walls and
# the corner of the -y wall and the floor. The box's corners at the floor nearest to and farthest
# from the base are out of the FR3's comfortable reach pointing down: towards x 0.26 the elbow ran
# into its joint limit, towards x 0.64 the arm oscillated until franka_node's joint-speed stop
# caught it (joint 4 at 2.5 rad/s; docs/control.md). SCENE_SEED puts the twin's block and bowl at
# y > 0.09 m, clear of every approach.
APPROACH_START = np.array([0.50, -0.10, 0.22])
SCENE_SEED = 82
APPROACHES = {
    "floor": (0.0, 0.0, -1.0),
    "wall_y": (0.0, -1.0, 0.0),
    "wall_x": (1.0, 0.0, 0.0),
    "corner": (0.0, -1.0, -1.0),
}
APPROACH_SPEED_M_S = 0.30  # asked for; the filter's speed limit (0.25) governs


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument(
        "--faults", default=",".join(FAULTS), help=f"comma-separated subset of {', '.join(FAULTS)} (default: all)"
    )
    parser.add_argument(
        "--still-mm", type=float, default=3.0, help="the arm 'held still' when it moved less than this (default 3 mm)"
    )
    parser.add_argument(
        "--control-config",
        type=Path,
        default=None,
        help="franka_node's control.yaml for this run (default: config/control.yaml)",
    )
    parser.add_argument(
        "--box-margin-mm",
        type=float,
        default=None,
        help="franka_node's safety.box_margin_m for this run, in mm (default: control.yaml's); "
        "0 measures the raw overshoot past the box",
    )
    parser.add_argument(
        "--policy",
        choices=["shipped", "standin"],
        default="shipped",
        help="policy_node's checkpoint for the policy faults (default: the shipped one if present)",
    )
    parser.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: a random private one)")
    parser.add_argument("--keep", type=Path, default=None, help="keep logs and episodes here (default: a temp dir)")


class StatusWatch:
    """franka_node's /franka/status (latched JSON) as it arrives, to wait on its state; and the
    newest measured TCP pose, orientation included (``ee_pose``, 4x4)."""

    def __init__(self, client: ControlClient):
        from geometry_msgs.msg import PoseStamped
        from std_msgs.msg import String

        from equidiff_core.topics import TOPIC_EE_POSE, TOPIC_FRANKA_STATUS
        from equidiff_ros.common import LATCHED_QOS, RELIABLE_QOS

        self.client = client
        self.history: deque = deque(maxlen=2000)  # (receive wall s, status dict)
        self.ee_pose: np.ndarray | None = None
        client.node.create_subscription(
            String, TOPIC_FRANKA_STATUS, lambda m: self.history.append((time.time(), json.loads(m.data))), LATCHED_QOS
        )
        client.node.create_subscription(PoseStamped, TOPIC_EE_POSE, self._on_pose, RELIABLE_QOS)

    def _on_pose(self, msg) -> None:
        self.ee_pose = pose_from_msg(msg)

    @property
    def latest(self) -> dict:
        return self.history[-1][1] if self.history else {}

    def wait(self, predicate: Callable[[dict], bool], timeout: float, what: str, proc=None) -> dict:
        """The first status (from now on, or the latest) for which ``predicate`` holds."""
        self.client.wait_for(lambda: bool(self.history) and predicate(self.latest), timeout, what, proc)
        return self.latest

    def states_since(self, t: float) -> list[str]:
        return [status["state"] for when, status in list(self.history) if when >= t]


def acknowledge() -> tuple[bool, str]:
    """Call franka_node's /franka/acknowledge as `equidiff lab ack` does: (granted, its message)."""
    from equidiff_core.topics import SERVICE_FRANKA_ACKNOWLEDGE
    from equidiff_ros.commands.lab_client import LabClient, LabError

    with LabClient() as lab:
        try:
            return True, lab.call("std_srvs/srv/Trigger", SERVICE_FRANKA_ACKNOWLEDGE)
        except LabError as err:
            return False, str(err)


@dataclass
class Campaign:
    client: ControlClient
    sim: object  # SimServer
    box: object  # SafetyBox
    tmp: Path
    franka_params: dict
    still_m: float
    box_margin_m: float
    shm: str = ""  # the twin sim's shared state, for its cameras
    status: StatusWatch | None = None
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
        from equidiff_core.control import metrics

        _, p = self.client.samples("poses", t0, time.time() if t1 is None else t1)
        out = metrics.max_outside_box(p, self.box.min_corner, self.box.max_corner) if len(p) else 0.0
        self.excursion_m = max(self.excursion_m, out)
        return out

    def alive(self) -> bool:
        return self.franka is not None and self.franka.poll() is None

    # --- commands --------------------------------------------------------------------------
    def hold_chunk(self, position=None, width: float = 0.08, steps: int = 4):
        from equidiff_core.chunk import PoseChunk

        now = time.time_ns()
        p = self.here() if position is None else position
        return PoseChunk(
            now,
            now + np.arange(steps, dtype=np.int64) * 200 * MS,
            np.stack([down_pose(p)] * steps),
            np.full(steps, width),
        )

    def home(self) -> None:
        """Back to the home pose (and its orientation: the policy may have yawed the hand) through
        franka_node's own /franka/home, then wait until the arm is there."""
        from equidiff_core.topics import SERVICE_FRANKA_HOME
        from equidiff_ros.commands.lab_client import LabClient

        for attempt in range(3):
            with LabClient() as lab:
                message = lab.call("std_srvs/srv/Trigger", SERVICE_FRANKA_HOME)
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
        from equidiff_core import geometry
        from equidiff_core.chunk import PoseChunk

        d = np.asarray(direction, dtype=float)
        t0 = time.time()
        end = time.monotonic() + seconds
        while True:
            now = time.time_ns()
            here = self.status.ee_pose if self.status is not None and self.status.ee_pose is not None else None
            start = self.here() if here is None else here[:3, 3]
            R = down_pose(start)[:3, :3] if here is None else here[:3, :3]  # keeps the measured orientation
            times = now + np.arange(8, dtype=np.int64) * 200 * MS
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


# --- the faults ------------------------------------------------------------------------------


def rejected_and_still(c: Campaign, counter: str, publish: Callable[[], None]) -> dict:
    before, t0 = c.diag(counter), time.time()
    publish()
    counted = c.wait_diag(counter, before)
    moved = c.moved_m(t0, time.time())
    return {
        "survived": counted and c.alive() and moved < c.still_m,
        "rejected": counted,
        "moved_mm": round(moved * 1000, 2),
    }


def fault_nan(c: Campaign) -> dict:
    from equidiff_core.chunk import chunk_to_msg

    def publish():
        msg = chunk_to_msg(c.hold_chunk(), c.client.factory, c.client.lab.base_frame)
        msg.points[2].transforms[0].translation.x = float("nan")
        c.client.pub_chunk.publish(msg)

    return rejected_and_still(c, "nan_rejected", publish)


def fault_jump(c: Campaign) -> dict:
    return rejected_and_still(
        c, "jump_rejected", lambda: c.client.publish_chunk(c.hold_chunk(c.here() + [0.0, 0.15, 0.0]))
    )


def fault_stale_chunk(c: Campaign) -> dict:
    from equidiff_core.chunk import PoseChunk

    def publish():
        old = time.time_ns() - 2_000_000_000
        here = c.here() + [0.0, 0.03, 0.0]  # a valid target, only too old
        c.client.publish_chunk(
            PoseChunk(
                old, old + np.arange(4, dtype=np.int64) * 200 * MS, np.stack([down_pose(here)] * 4), np.full(4, 0.08)
            )
        )

    return rejected_and_still(c, "stale_rejected", publish)


def fault_out_of_cone(c: Campaign) -> dict:
    from scipy.spatial.transform import Rotation

    from equidiff_core import geometry
    from equidiff_core.chunk import PoseChunk

    def publish():
        now = time.time_ns()
        here = c.here()
        poses = [down_pose(here)]
        for tilt in np.radians([20.0, 40.0, 60.0]):  # the policy tipping the hand over
            R = Rotation.from_rotvec([0.0, tilt, 0.0]).as_matrix() @ down_pose(here)[:3, :3]
            poses.append(geometry.make_pose(R, here))
        c.client.publish_chunk(
            PoseChunk(now, now + np.arange(4, dtype=np.int64) * 200 * MS, np.stack(poses), np.full(4, 0.08))
        )

    return rejected_and_still(c, "cone_rejected", publish)


def fault_out_of_box(c: Campaign) -> dict:
    """At the speed limit into the floor, two walls and their corner (see the module docstring)."""
    from equidiff_core.chunk import PoseChunk
    from equidiff_core.control import metrics
    from equidiff_ros.commands.bench_control import approach

    clip_lo, clip_hi = c.box.min_corner + c.box_margin_m, c.box.max_corner - c.box_margin_m
    per = {}
    for name, direction in APPROACHES.items():
        approach(c.client, APPROACH_START, speed=0.1, settle=0.5)
        d = np.asarray(direction) / np.linalg.norm(direction)
        limited, t0 = c.diag("speed_limited_ticks"), time.time()
        end = time.monotonic() + 3.0
        while time.monotonic() < end:
            # ahead of where franka_node's command is (its executed target), at 0.3 m/s: the speed
            # limit governs whatever the sim's pace (the command itself never runs ahead of the arm's time)
            now, start = time.time_ns(), c.client.data.targets[-1][1]
            times = now + np.arange(1, 9, dtype=np.int64) * 100 * MS
            poses = np.stack([down_pose(start + d * APPROACH_SPEED_M_S * 0.1 * i) for i in range(1, 9)])
            c.client.publish_chunk(PoseChunk(now, times, poses, np.full(8, 0.08)))
            time.sleep(0.1)
        time.sleep(1.0)
        _, p = c.client.samples("poses", t0, time.time())
        per[name] = {
            "overshoot_mm": round(metrics.max_outside_box(p, clip_lo, clip_hi) * 1000, 2),
            "outside_mm": round(metrics.max_outside_box(p, c.box.min_corner, c.box.max_corner) * 1000, 2),
            "travel_mm": round(float(np.linalg.norm(p[-1] - p[0])) * 1000, 1) if len(p) else 0.0,
            "speed_limited": c.wait_diag("speed_limited_ticks", limited, timeout=3.0),
        }
        c.note_excursion(t0)
    c.home()
    outside = max(a["outside_mm"] for a in per.values())
    return {
        "survived": c.alive() and outside == 0.0,
        "outside_mm": outside,
        "max_overshoot_mm": max(a["overshoot_mm"] for a in per.values()),
        "box_margin_mm": round(c.box_margin_m * 1000, 2),
        "approaches": per,
    }


def held_until_acknowledged(
    c: Campaign,
    sender: Callable[[], None],
    inject: Callable[[], None],
    reason_starts: str,
    pressed: bool = False,
    after_fault_s: float = 0.0,
    resume: Callable[[], None] | None = None,
) -> dict:
    """The common course of a robot stop: ``inject`` it while ``sender`` publishes chunks (it goes
    on throughout), check that franka_node holds (the same process, /franka/status
    ``awaiting_ack`` with a reason starting ``reason_starts``, the arm still, every chunk
    refused); with ``pressed`` (the user stop) an acknowledgement is tried first and must be
    refused, then the stop is released; then acknowledge and check the arm follows again (the
    chunks of ``resume``, if given, from then on)."""
    pid, out = c.franka.pid, {}
    with Sender(sender) as policy:
        time.sleep(0.8)  # the arm follows the sender
        t_fault = time.time()
        inject()
        try:
            status = c.status.wait(lambda s: s.get("state") == "awaiting_ack", 15.0, "the held state", c.franka)
        except (TimeoutError, RuntimeError) as err:
            return {"survived": False, "error": str(err), "status": c.status.latest}
        out["reason"] = status["reason"][:120]
        out["held_after_s"] = round(time.time() - t_fault, 2)
        time.sleep(max(0.0, t_fault + after_fault_s - time.time()))  # e.g. until a dropped link answers again
        time.sleep(0.5)  # the arm brakes
        c.client.wait_for(  # the 1 Hz diagnostics have caught up with the stop: a baseline for the count
            lambda: c.client.diag_value("franka_node", "state") == "awaiting_ack", 5.0, "diagnostics of the stop"
        )
        accepted, rejected, t_held = c.diag("accepted_chunks"), c.diag("ack_rejected"), time.time()
        time.sleep(2.0)
        refused = c.wait_diag("ack_rejected", rejected, timeout=3.0)
        if pressed:
            granted, message = acknowledge()
            out["ack_while_pressed_refused"] = not granted and "still pressed" in message
            c.sim.inject("release")
            time.sleep(1.0)
        policy.publish = resume or sender  # refused until the acknowledgement anyway
        time.sleep(0.3)
        accepted_while_held = c.diag("accepted_chunks") > accepted
        t_ack = time.time()
        granted, message = acknowledge()
        out["acknowledged"] = message[:120]
        # the arm from the stop until the acknowledgement, and the state read as it recovered (the
        # first after it: a lost connection has no state in between, so this shows its drift)
        c.wait_past(t_ack + 0.5)
        t, p = c.client.samples("poses", t_held, time.time())
        p = np.concatenate([p[t <= t_ack], p[t > t_ack][:1]]) if len(t) else p
        held = float(np.max(np.linalg.norm(p - p[0], axis=1))) if len(p) else float("nan")
        resumed_alone = not held < c.still_m or accepted_while_held
        c.auto_resumes += int(resumed_alone)
        accepted = c.diag("accepted_chunks")
        time.sleep(2.5)
        follows = c.wait_diag("accepted_chunks", accepted, timeout=3.0) and (
            c.moved_m(t_ack, time.time()) > 0.01 or resume is not None  # a turn of the hand moves the TCP little
        )
    c.note_excursion(t_fault)
    out.update(
        held_moved_mm=round(held * 1000, 2),
        refused_until_ack=refused,
        follows_after_ack=follows,
        same_process=c.franka.pid == pid and c.alive(),
    )
    out["survived"] = bool(
        out["reason"].startswith(reason_starts)
        and held < c.still_m
        and refused
        and not resumed_alone
        and granted
        and follows
        and out["same_process"]
        and out.get("ack_while_pressed_refused", True)
    )
    c.home()
    return out


def fault_user_stop(c: Campaign) -> dict:
    return held_until_acknowledged(
        c, lambda: c.follow_me(0.0), lambda: c.sim.inject("user_stop"), "user stop: ", pressed=True
    )


def fault_reflex(c: Campaign) -> dict:
    return held_until_acknowledged(c, lambda: c.follow_me(0.0), lambda: c.sim.inject("reflex"), "reflex: ")


def fault_connection_lost(c: Campaign) -> dict:
    return held_until_acknowledged(
        c,
        lambda: c.follow_me(0.0),
        lambda: c.sim.inject("drop", 1.5),
        "connection to the robot lost",
        after_fault_s=2.0,  # the robot answers again (to a new connection) before the operator acknowledges
    )


def fault_divergence(c: Campaign) -> dict:
    """The sender yaws the hand on and on (0.5 rad/s, the speed limit is 0.6) until joint 7 runs
    into its position limit: franka_node's divergence stop. Joint 7 turns against the yaw about
    the base's z while the hand points down; the sender heads for the nearer of its limits."""
    from equidiff_core import geometry
    from equidiff_core.chunk import PoseChunk

    q7 = float(arm_joint_positions(c.client.data.last_joint_state)[6])
    lo, hi = c.joint_limits[0][6], c.joint_limits[1][6]
    yaw_sign = -1.0 if hi - q7 < q7 - lo else 1.0
    rate = 0.5

    def yawing():  # from the measured pose on, as a policy answering observations would
        now, here = time.time_ns(), c.status.ee_pose
        times = now + np.arange(8, dtype=np.int64) * 200 * MS
        poses = [
            geometry.make_pose(geometry.rotz(yaw_sign * rate * 0.2 * (i + 1)) @ here[:3, :3], here[:3, 3])
            for i in range(8)
        ]
        c.client.publish_chunk(PoseChunk(now, times, np.stack(poses), np.full(8, 0.08)))

    stopped = {}

    def inject():  # the yawing itself is the fault: wait for it to run into the limit
        c.status.wait(lambda s: s.get("state") == "awaiting_ack", 20.0, "the divergence stop", c.franka)
        stopped["q7"] = float(arm_joint_positions(c.client.data.last_joint_state)[6])

    def unyawing():  # after the acknowledgement: back, away from the limit (towards it would stop again)
        now, here = time.time_ns(), c.status.ee_pose
        times = now + np.arange(8, dtype=np.int64) * 200 * MS
        poses = [
            geometry.make_pose(geometry.rotz(-yaw_sign * 0.3 * 0.2 * (i + 1)) @ here[:3, :3], here[:3, 3])
            for i in range(8)
        ]
        c.client.publish_chunk(PoseChunk(now, times, np.stack(poses), np.full(8, 0.08)))

    result = held_until_acknowledged(c, yawing, inject, "divergence stop: joint 7", resume=unyawing)
    result["q7_start_rad"], result["q7_at_stop_rad"] = round(q7, 3), round(stopped.get("q7", float("nan")), 3)
    return result


@dataclass
class CameraPipeline:
    """The twin's cameras (one camera_node each, backend twin, rendering the sim's state) ->
    voxel_node -> policy_node -> franka_node: what the policy faults act on."""

    c: Campaign
    cameras: dict = field(default_factory=dict)  # name -> Popen
    voxel: object = None
    policy: object = None
    accepted_before: int = 0  # franka_node's accepted_chunks when the policy started

    def start(self, checkpoint: Path) -> None:
        from equidiff_core.twin.processes import start_node

        c, lab_path = self.c, self.c.client.lab_path
        for cam in c.client.lab.cameras:
            self.cameras[cam.name] = start_node(
                "camera_node",
                {
                    "lab_config": lab_path,
                    "backend": "twin",
                    "camera": cam.name,
                    "backend_options": json.dumps({"shm_name": c.shm}),
                },
                c.tmp / f"camera_{cam.name}.log",
            )
        # the twin supervisor's lenient matching on real time (its cameras share 2 loaded cores)
        # lenient on a loaded machine (clouds came 2-5 s apart at load 20); a frozen camera still
        # stops the sets: its newest cloud is then never within slop_s of the others'
        self.voxel = start_node(
            "voxel_node", {"lab_config": lab_path, "slop_s": 0.15, "stale_after_s": 10.0}, c.tmp / "voxel_node.log"
        )
        self.accepted_before = c.diag("accepted_chunks")
        self.policy = start_node(
            "policy_node",
            {
                "checkpoint": str(checkpoint),
                "precision": "fp32",
                "lab_config": lab_path,
                "start_paused": False,
                "max_observation_age_s": 8.0,
                # the execution horizon's latency budget: a chunk carries up to all 16 steps, so one
                # answering a seconds-old observation on a loaded CPU still has live steps
                "latency_s": 2.0,
                "max_state_offset_s": 0.5,
            },
            c.tmp / "policy_node.log",
        )
        n0 = len(c.client.data.chunks)
        c.client.wait_for(lambda: len(c.client.data.chunks) > n0, 600.0, "policy_node's first chunk", self.policy)

    def chunks_observed_after(self, t0: float) -> int:
        """Chunks answering an observation (their stamp) later than ``t0``."""
        return sum(stamp > t0 for _, stamp in list(self.c.client.data.chunks))

    def chunks_between(self, t0: float, t1: float) -> int:
        """Chunks received in [t0, t1] (wall clock, s)."""
        return sum(t0 <= r <= t1 for r, _ in list(self.c.client.data.chunks))

    def stop(self) -> None:
        from equidiff_core.twin.processes import stop_process

        for proc in [self.policy, self.voxel, *self.cameras.values()]:
            if proc is not None and proc.poll() is None:
                os.kill(proc.pid, signal.SIGCONT)  # a frozen one must be able to exit
            stop_process(proc)


def fault_camera_stall(c: Campaign, pipe: CameraPipeline) -> dict:
    time.sleep(5.0)  # the policy acting for a while first
    accepted = c.diag("accepted_chunks") - pipe.accepted_before
    name, camera = next(iter(pipe.cameras.items()))
    os.kill(camera.pid, signal.SIGSTOP)  # the camera freezes: no more clouds from it
    t_stall = time.time() + 0.3  # a cloud already sent may still complete one set
    try:
        time.sleep(STALL_S)
    finally:
        t_end = time.time()
        os.kill(camera.pid, signal.SIGCONT)
    held = c.moved_m(t_end - 1.0, t_end)  # the last chunk's plan has run out by then: the watchdog holds
    try:
        c.client.wait_for(lambda: pipe.chunks_observed_after(t_end) > 0, 60.0, "policy chunks again", pipe.policy)
        again = True
    except (TimeoutError, RuntimeError):
        again = False
    # an inference already running may still answer a grid from before the stall: only chunks for
    # grids stamped during the stall count (there are none to answer), counted once chunks came again
    during = pipe.chunks_observed_after(t_stall) - pipe.chunks_observed_after(t_end)
    c.note_excursion(t_stall)
    return {
        "survived": during == 0 and held < c.still_m and again and c.alive(),
        "stalled_camera": name,
        "policy_chunks_accepted": accepted,
        "chunks_during_stall": during,
        "moved_while_stalled_mm": round(held * 1000, 2),
        "chunks_after_stall": again,
    }


def fault_policy_node_killed(c: Campaign, pipe: CameraPipeline) -> dict:
    holds = c.diag("watchdog_holds")
    t_kill = time.time()
    pipe.policy.send_signal(signal.SIGKILL)
    pipe.policy.wait(timeout=10)
    time.sleep(3.5)
    t_end = time.time()
    after = pipe.chunks_between(t_kill + 0.5, t_end)
    held = c.moved_m(t_end - 1.0, t_end)
    watchdog = c.wait_diag("watchdog_holds", holds, timeout=3.0)
    c.note_excursion(t_kill)
    return {
        "survived": after == 0 and held < c.still_m and c.alive(),
        "chunks_after_kill": after,
        "watchdog_fired_after_kill": watchdog,
        "moved_after_kill_mm": round(held * 1000, 2),
    }


def fault_recorder_sigkill(c: Campaign) -> dict:
    from equidiff_core.bags import BagError, read_episode, repair_bag

    if c.recorder is None or c.recorder.poll() is not None:
        return {"survived": False, "error": "recorder_node is not running"}
    episode = start_episode(c)
    t0 = time.time()
    c.follow_me(2.0, direction=(0.0, 1.0, 0.0))  # the arm moves while recording
    c.recorder.send_signal(signal.SIGKILL)
    c.recorder.wait(timeout=10)
    c.recorder = None
    moved = c.moved_m(t0, time.time())
    try:
        report = repair_bag(episode)
        poses = read_episode(episode, ["/franka/ee_pose"]).message_counts.get("/franka/ee_pose", 0)
        readable = poses > 0
        detail = {"repaired": report is not None, "ee_pose_messages": poses}
    except (BagError, Exception) as err:  # noqa: BLE001 - any failure to read it back is a lost episode
        readable, detail = False, {"error": f"{type(err).__name__}: {err}"}
    c.home()
    return {"survived": readable and c.alive() and moved > 0.02, **detail}


JAM_S = 6.0  # how long the gripper stays jammed


def fault_gripper_stuck(c: Campaign) -> dict:
    from equidiff_ros.commands.bench_control import approach

    def width() -> float:
        return gripper_width_from_joint_state(c.client.data.last_joint_state)

    def send_width(target: float, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            c.client.publish_chunk(c.hold_chunk(width=target))
            time.sleep(0.2)

    c.client.wait_for(lambda: (send_width(0.08, 0.2), abs(width() - 0.08) < 0.004)[1], 30.0, "the fingers to open")
    stamps = c.client.pose_stamps if hasattr(c.client, "pose_stamps") else c.client.record_pose_stamps()
    c.sim.jam_gripper(True)
    t0, w0, start = time.time(), width(), c.here()
    send_width(0.02, 2.0)  # close on nothing: 60 mm in 1.2 s, were the fingers free
    change = abs(width() - w0)
    target = start + [0.0, 0.03, 0.0]
    approach(c.client, target, speed=0.03, settle=0.5)  # the arm goes on meanwhile
    try:  # a sim below real time gets there later (held on the target by the last chunk, then the watchdog)
        c.client.wait_for(lambda: np.linalg.norm(c.here() - target) < 0.005, 3.0, "the arm at its target")
    except TimeoutError:
        pass
    reached = float(np.linalg.norm(c.here() - target))
    # past FrankyConfig.gripper_command_timeout_s (5 s): franka_node warns that the command has not finished
    time.sleep(max(0.0, t0 + JAM_S - time.time()))
    t1 = time.time()
    s = np.sort([t for t in list(stamps) if t0 <= t <= t1])
    gap = float(np.max(np.diff(np.concatenate([[t0], s, [t1]]))))
    c.sim.jam_gripper(False)
    send_width(0.05, 0.2)  # a new width after the jam cleared
    try:
        c.client.wait_for(
            lambda: (send_width(0.05, 0.2), abs(width() - 0.05) < 0.004)[1], 30.0, "the fingers to follow again"
        )
        followed = True
    except TimeoutError:
        followed = False
    send_width(0.08, 0.2)
    faulted = c.client.diag_value("franka_node", "faulted") == "True"
    return {
        "survived": change < 0.004 and reached < 0.005 and gap < JAM_S / 2 and followed and c.alive() and not faulted,
        "jammed_width_change_mm": round(change * 1000, 1),
        "arm_error_mm": round(reached * 1000, 2),
        "largest_state_gap_s": round(gap, 3),
        "fingers_followed_after": followed,
        "pending_command_warned": "has not finished" in franka_log(c),
    }


def fault_franka_node_killed(c: Campaign) -> dict:
    stop = threading.Event()

    def policy():  # the policy goes on publishing whatever happens to franka_node
        while not stop.is_set():
            c.follow_me(0.2, direction=(0.0, -1.0, 0.0))

    sender = threading.Thread(target=policy, daemon=True)
    sender.start()
    try:
        time.sleep(1.0)  # mid-chunk: the arm is moving
        at_kill = c.here()
        c.franka.send_signal(signal.SIGKILL)
        c.franka.wait(timeout=10)
        t_killed = time.time()
        c.client.data.diagnostics.pop("franka_node", None)  # the dead node's
        restarted = start_franka(c)
        c.client.wait_for(
            lambda: c.client.data.poses and c.client.data.poses[-1][0] > t_killed + 0.5,
            90.0,
            "/franka/ee_pose again",
            c.franka,
        )
        status = c.status.wait(lambda s: s.get("state") == "awaiting_ack", 10.0, "the restarted node's hold", c.franka)
        at_restart = c.here()
        awaiting = str(status.get("reason", ""))
        accepted, t_held = c.diag("accepted_chunks"), time.time()
        time.sleep(2.0)  # the policy's chunks keep coming, starting where the arm is
        held = c.moved_m(t_held, time.time())
        c.wait_diag("ack_rejected", 0, timeout=3.0)
        refused = c.diag("ack_rejected") > 0
        if held >= c.still_m or c.diag("accepted_chunks") > accepted:
            c.auto_resumes += 1
        acked, _ = acknowledge()
        t_ack = time.time()
        time.sleep(2.0)
        resumed = c.moved_m(t_ack, time.time()) > 0.01
    finally:
        stop.set()
        sender.join(timeout=5)
    c.note_excursion(c.t_start)
    drift = float(np.linalg.norm(at_restart - at_kill))
    c.home()
    return {
        "survived": restarted and "uncleanly" in awaiting and refused and held < c.still_m and acked and resumed,
        "drift_while_down_mm": round(drift * 1000, 1),
        "held_after_restart_mm": round(held * 1000, 2),
        "awaiting_ack": awaiting[:80],
        "refused_until_ack": refused,
        "resumed_after_ack": resumed,
    }


# --- set-up ----------------------------------------------------------------------------------


def franka_log(c: Campaign) -> str:
    logs = sorted(c.tmp.glob("franka_node*.log"), key=lambda p: p.stat().st_mtime)
    return logs[-1].read_text(errors="replace") if logs else ""


def start_franka(c: Campaign) -> bool:
    from equidiff_core.twin.processes import start_node

    n = sum(1 for _ in c.tmp.glob("franka_node*.log"))
    c.franka = start_node("franka_node", c.franka_params, c.tmp / f"franka_node{n or ''}.log", priority=True)
    return c.franka.poll() is None


def start_episode(c: Campaign) -> Path:
    from equidiff_core.topics import SERVICE_RECORDER_START
    from equidiff_ros.commands.lab_client import LabClient, LabError

    for attempt in range(6):  # a recorder_node starting on a loaded machine takes a while to offer it
        try:
            with LabClient() as lab:
                path = Path(lab.call("std_srvs/srv/Trigger", SERVICE_RECORDER_START))
            break
        except LabError:
            if attempt == 5 or (c.recorder is not None and c.recorder.poll() is not None):
                raise
    c.episodes.append(path)
    return path


def stop_episode(c: Campaign) -> None:
    from equidiff_core.topics import SERVICE_RECORDER_STOP
    from equidiff_ros.commands.lab_client import LabClient

    with LabClient() as lab:
        lab.call("std_srvs/srv/Trigger", SERVICE_RECORDER_STOP)


def episodes_lost(paths: list[Path]) -> int:
    from equidiff_core.bags import read_episode

    lost = 0
    for path in paths:
        try:
            lost += "/franka/ee_pose" not in read_episode(path, ["/franka/ee_pose"])
        except Exception:  # noqa: BLE001 - unreadable is lost, whatever the reason
            lost += 1
    return lost


def control_config_with_margin(tmp: Path, margin_mm: float | None, path: Path | None = None) -> tuple[Path, object]:
    """``path`` (default control.yaml), or a copy of it with ``safety.box_margin_m`` set (``--box-margin-mm``)."""
    import yaml

    from equidiff_core.config import default_config_dir
    from equidiff_core.control import load_control_config

    path = Path(path) if path is not None else default_config_dir() / "control.yaml"
    if margin_mm is not None:
        data = yaml.safe_load(path.read_text()) or {}
        data.setdefault("safety", {})["box_margin_m"] = float(margin_mm) / 1000
        path = tmp / "control.yaml"
        path.write_text(yaml.safe_dump(data))
    return path, load_control_config(path)


def run_campaign(
    faults: list[str],
    tmp: Path,
    still_mm: float = 3.0,
    box_margin_mm: float | None = None,
    log: Callable[[str], None] = lambda _m: None,
    policy: str = "shipped",
    control_config: Path | None = None,
) -> dict:
    """Run ``faults`` (in FAULTS' order) and return the result dict (the JSON line's content)."""
    from equidiff_core.config import default_config_dir, load_lab_config
    from equidiff_core.machine import cpu_description
    from equidiff_core.robots.franky.sim import SimServer
    from equidiff_core.twin.processes import start_node, stop_process
    from equidiff_ros.commands.lab_client import LabError

    unknown = sorted(set(faults) - set(FAULTS))
    if unknown:
        raise ValueError(f"unknown fault(s) {unknown}; choose from {list(FAULTS)}")
    faults = [f for f in FAULTS if f in faults]
    lab_path = default_config_dir() / "lab.yaml"
    lab = load_lab_config(lab_path)
    control_path, control = control_config_with_margin(tmp, box_margin_mm, control_config)
    wall0 = time.monotonic()
    result: dict = {"machine": cpu_description(), "ros_domain_id": int(os.environ["ROS_DOMAIN_ID"])}
    per_fault: dict = {}
    run_dir = tmp / "run"
    run_dir.mkdir(exist_ok=True)
    shm = f"equidiff_bench_safety_{os.getpid()}"
    # the sim waits up to 0.5 s for franky's command each tick, as the twin on simulated time does: an
    # FR3 never runs on a starved client's stale torque (it stops with a reflex), and the figures
    # here are franka_node's, not the machine's load (which made the overshoot 2-15 mm at 20 ms)
    twin_args = ("--config", str(default_config_dir() / "twin.yaml"), "--shm", shm, "--seed", str(SCENE_SEED))
    twin_args += ("--command-wait-s", "0.5")
    with SimServer(module="equidiff_core.twin.sim", args=twin_args) as sim:
        client = pipe = None
        c = Campaign(
            None,
            sim,
            lab.safety_box,
            tmp,
            {
                "robot_ip": sim.host,
                "realtime": False,
                "lab_config": str(lab_path),
                "control_config": str(control_path),
                "run_dir": str(run_dir),
            },
            still_mm / 1000,
            control.safety.box_margin_m,
            shm=sim.ready[0] if sim.ready else shm,
        )
        c.home_position = np.asarray(control.home_position)
        c.joint_limits = (control.safety.joint_position_min_rad, control.safety.joint_position_max_rad)
        try:
            c.recorder = start_node(
                "recorder_node",
                {
                    "output_dir": str(tmp / "episodes"),
                    "task": "safety",
                    "min_free_gib": 0.0,
                    "lab_config": str(lab_path),
                },
                tmp / "recorder_node.log",
            )
            client = c.client = ControlClient(lab, str(lab_path))
            c.status = StatusWatch(client)
            start_franka(c)  # the lab's defaults: it holds until the operator acknowledges
            c.status.wait(lambda s: s.get("state") == "awaiting_ack", 90.0, "franka_node's start-up hold", c.franka)
            result["start_hold"] = c.status.latest["reason"][:120]
            granted, message = acknowledge()  # as the operator; above the box, it moves home first
            if not granted:
                raise RuntimeError(f"the start-up acknowledgement was refused: {message}")
            c.status.wait(lambda s: s.get("state") == "holding", 60.0, "franka_node holding", c.franka)
            c.home()
            c.t_start = time.time()  # the campaign's excursions count from here: franky-sim starts above the box
            time.sleep(1.0)
            t0 = time.time()
            time.sleep(1.0)
            result["baseline_hold_drift_mm"] = round(c.moved_m(t0, time.time()) * 1000, 3)
            start_episode(c)
            for name in faults:
                if name in POLICY_FAULTS and pipe is None:
                    pipe = CameraPipeline(c)
                    checkpoint, result["policy"] = policy_checkpoint(policy, tmp, lab.workspace)
                    log(f"starting the twin's cameras, voxel_node and policy_node ({result['policy']})")
                    pipe.start(checkpoint)
                if name == "recorder_sigkill" and c.episodes and c.recorder is not None:
                    stop_episode(c)  # keep the first episode; the kill takes the next one
                log(f"fault: {name}")
                t_fault = time.time()
                fn = globals()[f"fault_{name}"]
                try:
                    per_fault[name] = fn(c, pipe) if name in POLICY_FAULTS else fn(c)
                except Exception as err:  # noqa: BLE001 - a fault that breaks the campaign is not survived
                    per_fault[name] = {"survived": False, "error": f"{type(err).__name__}: {err}"}
                c.note_excursion(t_fault)
                if not c.alive():
                    log("franka_node died: restarting it for the remaining faults")
                    start_franka(c)
                elif name in POLICY_FAULTS:
                    if name == POLICY_FAULTS[-1] or not set(POLICY_FAULTS[POLICY_FAULTS.index(name) + 1 :]) & set(
                        faults
                    ):
                        pipe.stop()  # the cameras' rendering costs a core: not beside the remaining faults
                    c.home()  # the policy moved (and yawed) the arm
                log(f"  {json.dumps(per_fault[name])}")
            if c.recorder is not None and c.episodes:
                try:
                    stop_episode(c)
                except LabError as err:  # a starved recorder: its SIGINT below still closes the bag
                    log(f"stopping the last episode: {err}")
        finally:
            if pipe is not None:
                pipe.stop()
            if client is not None:
                client.close()
            stop_process(c.recorder)
            result["franka_node_exit_code"] = stop_process(c.franka)
            result["sim_realtime_factor"] = sim.realtime_factor()
    survived = sum(bool(v.get("survived")) for v in per_fault.values())
    result.update(
        {
            "faults_tried": len(per_fault),
            "faults_survived": survived,
            "max_excursion_mm": round(c.excursion_m * 1000, 2),
            "auto_resumes": c.auto_resumes,
            "episodes_recorded": len(c.episodes),
            "episodes_lost": episodes_lost(c.episodes),
            "still_mm": still_mm,
            "box_margin_mm": round(c.box_margin_m * 1000, 2),
            "wall_deceleration_m_s2": control.safety.wall_deceleration_m_s2,
            "wall_s": round(time.monotonic() - wall0, 1),
            "faults": per_fault,
        }
    )
    return result


def policy_checkpoint(which: str, tmp: Path, workspace) -> tuple[Path, str]:
    """(checkpoint, label): the shipped twin policy if asked for and present, else an untrained tiny stand-in."""
    from equidiff_core.twin.standin import STANDIN_LABEL, make_standin_policy
    from equidiff_ros.commands.twin_run import SHIPPED_CHECKPOINT, SHIPPED_NAME

    if which == "shipped" and SHIPPED_CHECKPOINT.is_file():
        return SHIPPED_CHECKPOINT, f"shipped {SHIPPED_NAME}"
    path = tmp / "standin.pt"
    if not path.exists():
        make_standin_policy(path, workspace, preset="tiny", policy="baseline")
    return path, STANDIN_LABEL


def run(args: argparse.Namespace) -> int:
    from equidiff_core.twin.processes import join_private_domain

    join_private_domain(args.domain_id)
    faults = [f.strip() for f in args.faults.split(",") if f.strip()]
    with tempfile.TemporaryDirectory(prefix="bench_safety_") as tmp:
        out = args.keep or Path(tmp)
        out.mkdir(parents=True, exist_ok=True)
        try:
            result = run_campaign(
                faults,
                out,
                args.still_mm,
                args.box_margin_mm,
                log=lambda m: print(m, file=sys.stderr, flush=True),
                policy=args.policy,
                control_config=args.control_config,
            )
        except ValueError as err:
            print(f"equidiff bench safety: {err}", file=sys.stderr)
            return 2
    print(json.dumps(result))
    return 0
