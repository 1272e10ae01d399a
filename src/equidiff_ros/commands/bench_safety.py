"""`equidiff bench safety`: a fault campaign against franky-sim through franka_node (issue 16 item 2).

    equidiff bench safety                          # all ten faults, ~3 min on 2 cores
    equidiff bench safety --faults nan,out_of_box,franka_node_killed

Starts franky-sim, franka_node (real franky client, real rclpy, separate processes) and
recorder_node, then drives franka_node over /franka/command_chunk the way the policy does and
injects one fault at a time, each checked for what "survived" means for it:

* ``nan``, ``jump``, ``stale_chunk``, ``out_of_cone``: a chunk with a NaN pose / a first step
  15 cm from the arm / stamped 2 s ago / tilted 60 deg from tool-down. Survived: counted as
  rejected in franka_node's /diagnostics, the node alive, the arm still (< ``--still-mm``).
* ``out_of_box``: 4 s of chunks heading down through the table and out past the safety box.
  Survived: the TCP never left the box (lab.yaml ``safety_box``) by more than ``--box-tol-mm``
  (default: the box's floor margin, 10 mm, which is there to absorb the arm's overshoot: the
  hand never touched the table).
* ``camera_stall``: a policy_node (``--policy``: ``shipped``, the twin's trained checkpoint,
  the default; or ``standin``, an untrained tiny one that starts in seconds) on synthetic 5 Hz
  voxel grids (a table and a block); the grids stop for 3.5 s, as voxel_node's do when a
  camera stalls. ``policy_chunks_accepted`` says how many of its chunks franka_node executed.
  Survived: no chunk during the stall, the arm held, chunks again once the grids come back.
* ``policy_node_killed``: that policy_node is SIGKILLed. Survived: the arm held (watchdog).
* ``recorder_sigkill``: recorder_node is SIGKILLed mid-episode. Survived: the episode is
  readable after ``equidiff bags repair`` and franka_node did not notice.
* ``gripper_stuck``: franky-sim's hand is jammed (``SimServer.jam_gripper``: the fingers stay
  and the gripper command never finishes) while a new width is sent and the arm moves 3 cm.
  Survived: the fingers did not move (the fault took), the arm reached its target (< 5 mm) and
  its state kept coming (no gap longer than half the 6 s jam: a control loop waiting on the
  gripper would stall until the jam clears; a loaded 2-core machine starves it for ~1.4 s at
  times), and after the jam clears a new width is reached.
* between faults the arm goes back home through franka_node's ``/franka/home`` (refused, and
  the campaign's next fault then fails, if a stop still awaited acknowledgement).
* ``franka_node_killed``: SIGKILL while the arm runs a chunk; the sender keeps publishing
  chunks that start where the arm is. franka_node is started again (same ``run_dir``): it
  must find the unclean exit, skip its home move and hold; chunks are refused until
  /franka/acknowledge, after which the arm follows them again. Survived: all of that.

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

import numpy as np

from equidiff_ros.control_client import MS, ControlClient, down_pose

FAULTS = (
    "nan",
    "jump",
    "stale_chunk",
    "out_of_box",
    "out_of_cone",
    "camera_stall",
    "policy_node_killed",
    "recorder_sigkill",
    "gripper_stuck",
    "franka_node_killed",
)
POLICY_FAULTS = ("camera_stall", "policy_node_killed")


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
        "--box-tol-mm",
        type=float,
        default=None,
        help="out_of_box survives within this distance outside the safety box "
        "(default: its floor margin, lab.yaml safety_box.floor_margin_m)",
    )
    parser.add_argument(
        "--policy",
        choices=["shipped", "standin"],
        default="shipped",
        help="policy_node's checkpoint for the policy faults (default: the shipped one if present)",
    )
    parser.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: a random private one)")
    parser.add_argument("--keep", type=Path, default=None, help="keep logs and episodes here (default: a temp dir)")


@dataclass
class Campaign:
    client: ControlClient
    sim: object  # SimServer
    box: object  # SafetyBox
    tmp: Path
    franka_params: dict
    still_m: float
    box_tol_m: float
    franka: object = None  # its Popen
    recorder: object = None
    episodes: list = field(default_factory=list)
    auto_resumes: int = 0
    excursion_m: float = 0.0
    t_start: float = field(default_factory=time.time)
    home_position: np.ndarray = field(default_factory=lambda: np.array([0.45, 0.0, 0.30]))  # control.yaml's

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

        with LabClient() as lab:
            lab.call("std_srvs/srv/Trigger", SERVICE_FRANKA_HOME)
        self.client.wait_for(
            lambda: np.linalg.norm(self.here() - self.home_position) < 0.002, 60.0, "the arm home", self.franka
        )
        time.sleep(0.3)

    def follow_me(self, seconds: float, direction=(0.0, 1.0, 0.0), speed: float = 0.03) -> float:
        """What a policy sends: chunks that start where the arm is and move slowly on; returns the send start."""
        from equidiff_core.chunk import PoseChunk

        d = np.asarray(direction, dtype=float)
        t0 = time.time()
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            now = time.time_ns()
            start = self.here()
            times = now + np.arange(8, dtype=np.int64) * 200 * MS
            poses = np.stack([down_pose(start + d * speed * 0.2 * i) for i in range(8)])
            self.client.publish_chunk(PoseChunk(now, times, poses, np.full(8, 0.08)))
            time.sleep(0.2)
        return t0


class StatusWatch:
    """franka_node's /franka/status (latched JSON) as it arrives, to wait on its state."""

    def __init__(self, client: ControlClient):
        from std_msgs.msg import String

        from equidiff_core.topics import TOPIC_FRANKA_STATUS
        from equidiff_ros.common import LATCHED_QOS

        self.client = client
        self.history: deque = deque(maxlen=2000)  # (receive wall s, status dict)
        client.node.create_subscription(
            String, TOPIC_FRANKA_STATUS, lambda m: self.history.append((time.time(), json.loads(m.data))), LATCHED_QOS
        )

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
    from equidiff_core.control import metrics

    start = c.here()
    t0 = time.time()
    direction = np.array([0.5, 0.3, -1.0]) / np.linalg.norm([0.5, 0.3, -1.0])

    def path(t):  # 0.12 m/s down through the table and out past the box's x and floor faces
        return start + direction * 0.12 * max(t - t0, 0.0)

    last, _ = c.client.stream(path, 4.0, obs_latency=0.0)
    time.sleep(1.0)
    outside = c.note_excursion(t0)
    requested = metrics.max_outside_box(path(last)[None], c.box.min_corner, c.box.max_corner)
    c.home()
    return {
        "survived": c.alive() and outside <= c.box_tol_m,
        "outside_mm": round(outside * 1000, 2),
        "requested_outside_mm": round(requested * 1000, 1),
    }


@dataclass
class PolicyFeed:
    """policy_node on synthetic voxel grids at the observation rate; ``stalled`` stops the grids."""

    client: ControlClient
    stalled: threading.Event = field(default_factory=threading.Event)
    stop: threading.Event = field(default_factory=threading.Event)
    proc: object = None
    thread: threading.Thread | None = None
    accepted_before: int = 0  # franka_node's accepted_chunks when the policy started

    def start(self, checkpoint: Path, log: Path) -> None:
        from equidiff_core.twin.processes import start_node

        self.proc = start_node(
            "policy_node",
            {
                "checkpoint": str(checkpoint),
                "precision": "fp32",
                "lab_config": self.client.lab_path,
                "start_paused": False,
            },
            log,
        )
        self.thread = threading.Thread(target=self._feed, daemon=True)
        self.thread.start()
        n0 = len(self.client.data.chunks)
        self.client.wait_for(lambda: len(self.client.data.chunks) > n0, 180.0, "policy_node's first chunk", self.proc)

    def _feed(self) -> None:
        from equidiff_core.pointcloud import grid_to_voxel_msg
        from equidiff_ros.commands.bench_control import synthetic_grid

        ws, lab = self.client.lab.workspace, self.client.lab
        grid = synthetic_grid(ws)
        while not self.stop.is_set():
            if not self.stalled.is_set():
                self.client.pub_voxels.publish(
                    grid_to_voxel_msg(
                        grid, ws.lower, ws.voxel_size, time.time_ns(), lab.base_frame, self.client.factory
                    )
                )
            self.stop.wait(1.0 / lab.observation_hz)

    def chunks_between(self, t0: float, t1: float) -> int:
        """Chunks received in [t0, t1] (wall clock, s)."""
        return sum(t0 <= r <= t1 for r, _ in list(self.client.data.chunks))

    def chunks_observed_after(self, t0: float) -> int:
        """Chunks answering an observation (their stamp) later than ``t0``."""
        return sum(stamp > t0 for _, stamp in list(self.client.data.chunks))


def fault_camera_stall(c: Campaign, feed: PolicyFeed) -> dict:
    time.sleep(3.0)  # the policy acting for a while first
    accepted = c.diag("accepted_chunks") - feed.accepted_before
    feed.stalled.set()
    t_stall = time.time() + 0.05  # a grid being published as the stall began is stamped before this
    time.sleep(3.5)
    t_end = time.time()
    # an inference already running may still answer a grid from before the stall: only chunks for
    # grids stamped during the stall count (there are none to answer)
    during = feed.chunks_observed_after(t_stall)
    held = c.moved_m(t_end - 1.0, t_end)  # the last chunk's plan has run out by then: the watchdog holds
    feed.stalled.clear()
    try:
        c.client.wait_for(lambda: feed.chunks_observed_after(t_end) > 0, 30.0, "policy chunks again", feed.proc)
        again = True
    except (TimeoutError, RuntimeError):
        again = False
    c.note_excursion(t_stall)
    return {
        "survived": during == 0 and held < c.still_m and again and c.alive(),
        "policy_chunks_accepted": accepted,
        "chunks_during_stall": during,
        "moved_while_stalled_mm": round(held * 1000, 2),
        "chunks_after_stall": again,
    }


def fault_policy_node_killed(c: Campaign, feed: PolicyFeed) -> dict:
    holds = c.diag("watchdog_holds")
    t_kill = time.time()
    feed.proc.send_signal(signal.SIGKILL)
    feed.proc.wait(timeout=10)
    time.sleep(3.5)
    t_end = time.time()
    after = feed.chunks_between(t_kill + 0.5, t_end)
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
        return 2 * float(c.client.data.last_joint_state.position[7])

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
    from equidiff_core.topics import SERVICE_FRANKA_ACKNOWLEDGE
    from equidiff_ros.commands.lab_client import LabClient, LabError

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
        c.client.wait_for(
            lambda: c.client.diag_value("franka_node", "awaiting_ack") is not None, 10.0, "franka_node's diagnostics"
        )
        at_restart = c.here()
        awaiting = str(c.client.diag_value("franka_node", "awaiting_ack", ""))
        accepted, t_held = c.diag("accepted_chunks"), time.time()
        time.sleep(2.0)  # the policy's chunks keep coming, starting where the arm is
        held = c.moved_m(t_held, time.time())
        c.wait_diag("ack_rejected", 0, timeout=3.0)
        refused = c.diag("ack_rejected") > 0
        if held >= c.still_m or c.diag("accepted_chunks") > accepted:
            c.auto_resumes += 1
        try:
            with LabClient() as lab:
                lab.call("std_srvs/srv/Trigger", SERVICE_FRANKA_ACKNOWLEDGE)
            acked = True
        except LabError:
            acked = False
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
    from equidiff_ros.commands.lab_client import LabClient

    with LabClient() as lab:
        path = Path(lab.call("std_srvs/srv/Trigger", SERVICE_RECORDER_START))
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


def run_campaign(
    faults: list[str],
    tmp: Path,
    still_mm: float = 3.0,
    box_tol_mm: float | None = None,
    log: Callable[[str], None] = lambda _m: None,
    policy: str = "shipped",
) -> dict:
    """Run ``faults`` (in FAULTS' order) and return the result dict (the JSON line's content)."""
    from equidiff_core.config import default_config_dir, load_lab_config
    from equidiff_core.control import load_control_config
    from equidiff_core.machine import cpu_description
    from equidiff_core.robots.franky.sim import SimServer
    from equidiff_core.twin.processes import start_node, stop_process

    unknown = sorted(set(faults) - set(FAULTS))
    if unknown:
        raise ValueError(f"unknown fault(s) {unknown}; choose from {list(FAULTS)}")
    faults = [f for f in FAULTS if f in faults]
    lab_path = default_config_dir() / "lab.yaml"
    lab = load_lab_config(lab_path)
    if box_tol_mm is None:
        box_tol_mm = lab.safety_box.floor_margin_m * 1000
    wall0 = time.monotonic()
    result: dict = {"machine": cpu_description(), "ros_domain_id": int(os.environ["ROS_DOMAIN_ID"])}
    per_fault: dict = {}
    run_dir = tmp / "run"
    run_dir.mkdir(exist_ok=True)
    with SimServer() as sim:
        client = feed = None
        c = Campaign(
            None,
            sim,
            lab.safety_box,
            tmp,
            {"robot_ip": sim.host, "realtime": False, "lab_config": str(lab_path), "run_dir": str(run_dir)},
            still_mm / 1000,
            box_tol_mm / 1000,
        )
        c.home_position = np.asarray(load_control_config(default_config_dir() / "control.yaml").home_position)
        try:
            start_franka(c)
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
            client.wait_for(lambda: len(client.data.poses) > 10, 90.0, "/franka/ee_pose", c.franka)
            time.sleep(1.0)
            t0 = time.time()
            time.sleep(1.0)
            result["baseline_hold_drift_mm"] = round(c.moved_m(t0, time.time()) * 1000, 3)
            start_episode(c)
            for name in faults:
                if name in POLICY_FAULTS and feed is None:
                    feed = PolicyFeed(client, accepted_before=c.diag("accepted_chunks"))
                    checkpoint, result["policy"] = policy_checkpoint(policy, tmp, lab.workspace)
                    log(f"starting policy_node ({result['policy']})")
                    feed.start(checkpoint, tmp / "policy_node.log")
                if name == "recorder_sigkill" and c.episodes and c.recorder is not None:
                    stop_episode(c)  # keep the first episode; the kill takes the next one
                log(f"fault: {name}")
                t_fault = time.time()
                fn = globals()[f"fault_{name}"]
                try:
                    per_fault[name] = fn(c, feed) if name in POLICY_FAULTS else fn(c)
                except Exception as err:  # noqa: BLE001 - a fault that breaks the campaign is not survived
                    per_fault[name] = {"survived": False, "error": f"{type(err).__name__}: {err}"}
                c.note_excursion(t_fault)
                if not c.alive():
                    log("franka_node died: restarting it for the remaining faults")
                    start_franka(c)
                elif name in POLICY_FAULTS:
                    c.home()  # the policy moved (and yawed) the arm
                log(f"  {json.dumps(per_fault[name])}")
            if c.recorder is not None and c.episodes:
                stop_episode(c)
        finally:
            if feed is not None:
                feed.stop.set()
                if feed.thread is not None:
                    feed.thread.join(timeout=5)
                stop_process(feed.proc)
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
            "box_tol_mm": box_tol_mm,
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
                args.box_tol_mm,
                log=lambda m: print(m, file=sys.stderr, flush=True),
                policy=args.policy,
            )
        except ValueError as err:
            print(f"equidiff bench safety: {err}", file=sys.stderr)
            return 2
    print(json.dumps(result))
    return 0
