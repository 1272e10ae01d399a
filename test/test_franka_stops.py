"""Stops that a lab survives: franka_node (real franky) against franky-sim, whose
server injects the faults at the libfranka protocol level (``robots.franky.faults``), so the
real franky client raises the real exceptions. One sim and one franka_node at a time serve the
module; the node is restarted by the last test.

What must hold: a user stop, a reflex or a lost connection puts franka_node into one held state
(no restart: the same process), /franka/status says so, an acknowledgement while the user stop
is pressed is refused, release + acknowledgement recovers (reconnecting after a lost connection)
and chunks are accepted again; a fault after that holds again; a (re)started franka_node holds
until acknowledged, clean start or not, unless ``require_ack_on_start:=false``.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

pytest.importorskip("franky")
pytest.importorskip("franky_sim")
pytest.importorskip("rclpy")

from helpers_ros import private_test_domain

from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.control import load_control_config
from equidiff_core.robots.franky.sim import SimServer
from equidiff_core.twin.processes import start_node, stop_process
from equidiff_core.wire.chunk import PoseChunk
from equidiff_ros.benches.safety_probe import StatusWatch, acknowledge
from equidiff_ros.control_client import MS, ControlClient, down_pose

pytestmark = [pytest.mark.sim, pytest.mark.ros, pytest.mark.slow]

LAB_PATH = default_config_dir() / "lab.yaml"
CONTROL = load_control_config(default_config_dir() / "control.yaml")
HOME = np.asarray(CONTROL.home_position)


class Stack:
    def __init__(self, sim, log_dir):
        self.sim, self.log_dir, self.proc, self.starts = sim, log_dir, None, 0
        self.client = ControlClient(load_lab_config(LAB_PATH), str(LAB_PATH))
        self.status = StatusWatch(self.client)

    def start_franka(self, **params):
        self.starts += 1
        self.status.history.clear()
        self.client.data.diagnostics.pop("franka_node", None)  # the previous node's counters
        self.proc = start_node(
            "franka_node",
            {"robot_ip": self.sim.host, "realtime": False, "lab_config": str(LAB_PATH), **params},
            self.log_dir / f"franka_node{self.starts}.log",
            priority=True,
        )
        return self.status.wait(bool, 90.0, "franka_node's first /franka/status", self.proc)

    def log(self) -> str:
        path = self.log_dir / f"franka_node{self.starts}.log"
        return path.read_text(errors="replace")[-3000:] if path.exists() else ""

    def diag(self, key: str) -> int:
        return int(float(self.client.diag_value("franka_node", key, 0) or 0))

    def nudge(self, seconds: float, dy: float = 0.02) -> float:
        """What a policy sends: chunks starting where the arm is, heading ``dy`` further; returns the start."""
        t0, end = time.time(), time.monotonic() + seconds
        while time.monotonic() < end:
            now, here = time.time_ns(), self.client.latest_position()
            times = now + np.arange(4, dtype=np.int64) * 200 * MS
            poses = np.stack([down_pose(here + [0.0, dy * i / 3, 0.0]) for i in range(4)])
            self.client.publish_chunk(PoseChunk(now, times, poses, np.full(4, 0.08)))
            time.sleep(0.2)
        return t0

    def moved_mm(self, t0: float) -> float:
        _, p = self.client.samples("poses", t0, time.time())
        return float(np.max(np.linalg.norm(p - p[0], axis=1)) * 1000) if len(p) else 0.0


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    import os

    log_dir = tmp_path_factory.mktemp("franka_stops")
    mp = pytest.MonkeyPatch()
    mp.setenv("ROS_DOMAIN_ID", str(private_test_domain(os.getpid() + 7)))
    mp.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    with SimServer() as sim:
        s = Stack(sim, log_dir)
        try:
            yield s
        finally:
            s.client.close()
            code = stop_process(s.proc)
            mp.undo()
            assert code == 0, f"franka_node did not shut down cleanly (exit {code}):\n{s.log()}"


def test_a_started_node_holds_until_acknowledged_then_moves_home_from_outside_the_box(stack):
    status = stack.start_franka()  # the lab's defaults: require_ack_on_start
    assert status["state"] == "awaiting_ack" and "franka_node started" in status["reason"], status
    assert "moves it home first" in status["reason"]  # franky-sim starts above the box
    stack.client.wait_for(lambda: len(stack.client.data.poses) > 5, 30.0, "/franka/ee_pose", stack.proc)
    t0 = stack.nudge(1.0)
    assert stack.moved_mm(t0) < 1.0  # nothing moved, nothing streamed
    stack.client.wait_for(lambda: stack.diag("ack_rejected") > 0, 10.0, "chunks refused")
    granted, message = acknowledge()
    assert granted and "moving home first" in message, message
    stack.status.wait(lambda s: s["state"] == "holding", 60.0, "holding at home", stack.proc)
    # franky's planned move ends when its plan does; franky-sim's arm lags it by up to ~1 cm
    assert np.linalg.norm(stack.client.latest_position() - HOME) < 0.02
    accepted, t0 = stack.diag("accepted_chunks"), stack.nudge(1.0)
    stack.client.wait_for(lambda: stack.diag("accepted_chunks") > accepted, 10.0, "chunks accepted")
    assert stack.moved_mm(t0) > 5.0


def test_a_user_stop_holds_until_released_and_acknowledged_and_a_reflex_holds_again(stack):
    pid, sim = stack.proc.pid, stack.sim
    stack.nudge(0.6)
    sim.inject("user_stop")
    status = stack.status.wait(lambda s: s["state"] == "awaiting_ack", 10.0, "the held state", stack.proc)
    assert status["reason"].startswith("user stop: libfranka: Move command aborted: User Stop pressed"), status
    assert status["last_fault"].startswith("user stop") and status["last_fault_ns"] > 0
    stack.status.wait(lambda s: "still pressed" in s["reason"], 5.0, "'still pressed'")
    rejected, t0 = stack.diag("ack_rejected"), stack.nudge(1.0)
    assert stack.moved_mm(t0) < 2.0
    stack.client.wait_for(lambda: stack.diag("ack_rejected") > rejected, 10.0, "chunks refused while stopped")
    granted, message = acknowledge()
    assert not granted and "still pressed" in message, message
    assert stack.status.latest["state"] == "awaiting_ack"
    sim.inject("release")
    stack.status.wait(lambda s: "released" in s["reason"], 5.0, "'released' (polled)")
    granted, message = acknowledge()
    assert granted and message.startswith("acknowledged: user stop"), message
    stack.status.wait(lambda s: s["state"] == "holding", 5.0, "holding after the acknowledgement")
    accepted, t0 = stack.diag("accepted_chunks"), stack.nudge(1.0, dy=-0.02)
    stack.client.wait_for(lambda: stack.diag("accepted_chunks") > accepted, 10.0, "chunks accepted again")
    assert stack.moved_mm(t0) > 5.0

    sim.inject("reflex")  # a fault after the acknowledgement: held again, never resumed
    status = stack.status.wait(lambda s: s["state"] == "awaiting_ack", 10.0, "held again", stack.proc)
    assert status["reason"].startswith(
        'reflex: libfranka: Move command aborted: motion aborted by reflex! ["cartesian_reflex"]'
    )
    t0 = stack.nudge(1.0)
    assert stack.moved_mm(t0) < 2.0 and stack.status.latest["state"] == "awaiting_ack"
    granted, message = acknowledge()
    assert granted and "reflex" in message, message
    stack.status.wait(lambda s: s["state"] == "holding", 5.0, "holding")
    assert stack.proc.pid == pid and stack.proc.poll() is None  # no restart
    assert stack.diag("robot_stops") == 2 and stack.diag("recoveries") >= 2


def test_a_lost_connection_holds_and_the_acknowledgement_connects_again(stack):
    stack.nudge(0.6)
    t_drop = time.time()
    stack.sim.inject("drop", 1.5)  # past libfranka's 1 s UDP receive timeout: its Robot is dead
    status = stack.status.wait(lambda s: s["state"] == "awaiting_ack", 10.0, "the held state", stack.proc)
    assert status["reason"].startswith("connection to the robot lost"), status
    assert "connects again" in status["reason"]
    time.sleep(max(0.0, t_drop + 2.0 - time.time()))  # the sim answers again (to a new client)
    granted, message = acknowledge()
    assert granted and "reconnected" in message, message
    stack.status.wait(lambda s: s["state"] == "holding", 10.0, "holding after reconnecting")
    t0 = time.time()
    stack.client.wait_for(lambda: stack.client.data.poses[-1][0] > t0 + 0.5, 10.0, "/franka/ee_pose again")
    accepted, t0 = stack.diag("accepted_chunks"), stack.nudge(1.0)
    stack.client.wait_for(lambda: stack.diag("accepted_chunks") > accepted, 10.0, "chunks accepted again")
    assert stack.moved_mm(t0) > 5.0


def test_a_restarted_node_holds_until_acknowledged_after_a_clean_exit(stack):
    assert stop_process(stack.proc) == 0, stack.log()  # a clean exit
    status = stack.start_franka()
    assert status["state"] == "awaiting_ack" and status["reason"].startswith("franka_node started"), status
    stack.client.wait_for(lambda: stack.client.data.poses[-1][0] > time.time() - 0.2, 30.0, "/franka/ee_pose")
    t0 = stack.nudge(1.0)
    assert stack.moved_mm(t0) < 1.0  # (franky-sim's own PD held the arm while no client was connected)
    granted, message = acknowledge()  # inside the box: it holds where it is
    assert (
        granted
        and message == "acknowledged: franka_node started: acknowledge (`equidiff lab ack`) before it accepts chunks"
    )
    stack.status.wait(lambda s: s["state"] == "holding", 5.0, "holding")
    accepted = stack.diag("accepted_chunks")
    stack.nudge(0.6)
    stack.client.wait_for(lambda: stack.diag("accepted_chunks") > accepted, 10.0, "chunks accepted")


def test_the_waiver_starts_a_node_that_homes_and_takes_chunks_at_once(stack):
    assert stop_process(stack.proc) == 0, stack.log()
    stack.start_franka(require_ack_on_start=False)  # the twin's waiver: homes, then takes chunks
    stack.status.wait(lambda s: s["state"] == "holding", 60.0, "holding without an acknowledgement", stack.proc)
    stack.client.wait_for(lambda: np.linalg.norm(stack.client.latest_position() - HOME) < 0.02, 30.0, "home")
    accepted, t0 = stack.diag("accepted_chunks"), stack.nudge(1.0)
    stack.client.wait_for(lambda: stack.diag("accepted_chunks") > accepted, 10.0, "chunks accepted at once")
    assert stack.moved_mm(t0) > 5.0
