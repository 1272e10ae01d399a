"""The franka node on franky-sim: real franky client, real rclpy, separate processes.

One franky-sim (twin_node's, on simulated time: it publishes /clock) and one franka_node with
``use_sim_time`` serve the whole module (starting them costs ~10 s); the scenarios are the ones
``equidiff bench control`` measures. Everything here runs on the sim's clock: chunks are stamped
and paced in it, and the figures are read in it, so a sim slowed by a busy machine slows the whole
test with it instead of changing what it measures (``bench control`` keeps the wall clock and
reports how the load changes its figures).
"""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

pytest.importorskip("franky")
pytest.importorskip("franky_sim")
pytest.importorskip("rclpy")

from helpers_ros import private_test_domain

from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.control import load_control_config, metrics
from equidiff_core.robots.franky.sim import free_loopback_host
from equidiff_core.twin.node_specs import twin_node_params
from equidiff_core.twin.processes import start_node, stop_process
from equidiff_core.wire.chunk import PoseChunk
from equidiff_ros.benches import control as bench
from equidiff_ros.benches.safety_probe import acknowledge
from equidiff_ros.control_client import ControlClient, down_pose

pytestmark = [pytest.mark.sim, pytest.mark.ros, pytest.mark.slow]

LAB_PATH = default_config_dir() / "lab.yaml"
TWIN_PATH = default_config_dir() / "twin.yaml"
CONTROL = load_control_config(default_config_dir() / "control.yaml")


@pytest.fixture(scope="module")
def franka(tmp_path_factory):
    """(client, node process, lab): twin_node's franky-sim + franka_node on a private ROS domain,
    both on simulated time."""
    log_dir = tmp_path_factory.mktemp("franka_sim")
    mp = pytest.MonkeyPatch()
    mp.setenv("ROS_DOMAIN_ID", str(private_test_domain(os.getpid())))
    mp.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    lab = load_lab_config(LAB_PATH)
    host = free_loopback_host()
    twin = proc = client = None
    try:
        params = twin_node_params(LAB_PATH, TWIN_PATH, host, 0, True, 0.1, 30.0, 1.0)
        twin = start_node(
            "twin_node",
            {**params, "shm_name": f"eqd_franka_sim_{os.getpid()}"},
            log_dir / "twin_node.log",
            priority=True,
        )
        client = ControlClient(lab, str(LAB_PATH), use_sim_time=True)
        client.wait_for(lambda: client.now_ns() > 0, 90.0, "/clock from twin_node", twin)
        proc = start_node(
            "franka_node",
            {"robot_ip": host, "realtime": False, "lab_config": str(LAB_PATH), "use_sim_time": True},
            log_dir / "franka_node.log",
            priority=True,
        )
        client.record_pose_stamps()  # every state's stamp, none dropped while the test runner is starved
        client.wait_for(lambda: len(client.data.poses) > 10, 90.0, "/franka/ee_pose", proc)
        # it holds until acknowledged, as in the lab; franky-sim's arm starts above the box, so
        # the acknowledgement moves it home (test_franka_stops.py tests that start in detail)
        granted, message = acknowledge()
        assert granted and "moving home first" in message, message
        home = np.asarray(CONTROL.home_position)
        client.wait_for(lambda: np.linalg.norm(client.latest_position() - home) < 0.02, 60.0, "home", proc)
        yield client, proc, lab
    finally:
        if client is not None:
            client.close()
        code = stop_process(proc) if proc is not None else 0
        stop_process(twin)
        mp.undo()
        log = (log_dir / "franka_node.log").read_text() if (log_dir / "franka_node.log").exists() else ""
        assert code == 0, f"franka_node did not shut down cleanly (exit {code}):\n{log[-3000:]}"


def state_stamps(client, t_from: float, t_to: float) -> tuple[np.ndarray, np.ndarray]:
    """(stamps, gaps): the sorted stamps of the /franka/ee_pose messages in [t_from, t_to] (simulated
    time, franka_node's clock here) and the gaps between them, the window's edges included.
    A state republished unchanged (the control loop stalled) keeps its stamp: a stalled control
    loop shows as a gap just like stalled publishing."""
    deadline = time.monotonic() + 10.0  # the deep queue may still hold a backlog: wait until it is past t_to
    while time.monotonic() < deadline and not (client.pose_stamps and client.pose_stamps[-1] > t_to):
        time.sleep(0.05)
    stamps = np.sort([t for t in list(client.pose_stamps) if t_from <= t <= t_to])
    return stamps, np.diff(np.concatenate([[t_from], stamps, [t_to]]))


def test_the_path_error_ignores_lateness_and_the_arc_counts_progress():
    """What the tracking test asserts without time: a TCP 0.3 s late on the circle is on its path
    (but 18 mm RMS late on the clock); one 3 mm outside it is 3 mm off; a quarter turn is counted."""
    circle = bench.Circle(radius=0.05, speed=0.06)
    times = np.linspace(0.5, 2.0, 100)
    late = np.stack([circle.position(t - 0.3) for t in times])
    assert circle.distance(late).max() < 1e-9
    assert metrics.tracking_rms(times, late, circle.position) > 0.015
    outside = late + 0.003 * (late - np.asarray(circle.center)) / circle.radius
    np.testing.assert_allclose(circle.distance(outside), 0.003, atol=1e-9)
    quarter = np.stack([circle.position(t) for t in np.linspace(0.0, np.pi / 2 * circle.radius / circle.speed, 20)])
    assert circle.arc_length(quarter) == pytest.approx(np.pi / 2 * circle.radius)
    assert circle.arc_length(quarter[::-1]) == pytest.approx(-np.pi / 2 * circle.radius)


def test_state_is_published_at_100_hz_from_the_home_pose(franka):
    client, _proc, _lab = franka
    j0, t0 = client.data.joint_states, client.now()
    client.sleep(2.0)
    stamps, gaps = state_stamps(client, t0, client.now())
    # 100 Hz is the node's period, not a count per second: a busy 2-core box starves the whole
    # stack at times (72 Hz on average once in CI, 45-65 Hz with two busy loops beside it, on the
    # wall clock), which lengthens some intervals but not those where the node had the CPU. So: a quarter
    # of the intervals between successive new states are one 10 ms period (a 60 Hz node's are
    # >= 15 ms: stamps fall on the 200 Hz control ticks), and no state was long overdue.
    fresh = np.diff(np.unique(stamps))
    percentiles_ms = np.round(np.percentile(fresh, [10, 25, 50, 75, 90]) * 1000, 1)
    assert np.percentile(fresh, 25) <= 0.0125, f"interval percentiles 10/25/50/75/90: {percentiles_ms} ms"
    assert gaps.max() < 0.5, f"no new state for {gaps.max():.2f} s"
    assert client.data.joint_states - j0 >= 0.5 * len(stamps)  # a joint state goes out with every pose
    msg = client.data.last_joint_state
    assert list(msg.name)[-2:] == ["fr3_finger_joint1", "fr3_finger_joint2"] and len(msg.name) == 9
    assert msg.position[7] == pytest.approx(msg.position[8]) and 0.0 < msg.position[7] <= 0.041
    home = np.asarray(CONTROL.home_position)
    assert np.linalg.norm(client.latest_position() - home) < 0.02  # it moved home once acknowledged


def test_curve_is_tracked_smoothly_and_held_when_commands_stop(franka):
    client, proc, _lab = franka
    wall0, t_start = time.monotonic(), client.now()
    r = bench.run_track_and_hold(
        client,
        speed=0.06,
        radius=0.05,
        duration=4.0,
        settle=1.0,
        obs_latency=0.1,
        watchdog_s=CONTROL.safety.watchdog_timeout_s,
    )
    r["sim_realtime_factor"] = round((client.now() - t_start) / (time.monotonic() - wall0), 3)  # < 1: a busy machine
    _, gaps = state_stamps(client, t_start, client.now())
    r["largest_state_gap_s"] = round(float(gaps.max()), 3)
    # The metrics need the TCP observed throughout the ~3 s tracking window, not a count per
    # second (236 of the nominal 300 once on CI's busy box, where this runner is starved too and
    # drops states): the state kept coming (as in test_state_is_published...) and the metrics
    # had at least 50 samples, one per ~4 mm of the circle.
    assert r["largest_state_gap_s"] < 0.5, r
    assert r["tracking_samples"] >= 50, r
    # On the path, and along it. How late the TCP is (tracking_rms_mm) is `equidiff bench control`'s
    # figure: on the wall clock it depends on how much CPU franky-sim gets (0.7 mm quiet, 11.9 mm RMS
    # beside a running twin); on the sim's clock, as here, it stayed 1.1-1.9 mm beside one (docs/control.md).
    assert r["path_rms_mm"] <= 5.0, r
    assert r["arc_travelled_mm"] >= 30.0, r  # of the ~180 mm commanded in the window: it moved on
    assert r["velocity_reversals"] == 0, r
    assert r["command_velocity_reversals"] == 0, r
    assert r["track_chunk_switches"] > 0 and r["track_standstill_total_s"] == 0.0, r  # no stop at a switch
    # Held: one target from the hold on, and the arm at rest at it. How far the arm ran on after the
    # hold engaged (hold_drift_mm) is `equidiff bench control`'s figure: on the wall clock the
    # watchdog counts wall time while a starved sim lags the command (docs/control.md).
    assert r["hold_target_span_mm"] <= 0.1, r
    assert r["hold_at_rest_after_s"] is not None, r  # still for 0.5 s, within 10 s
    assert r["hold_rest_distance_to_target_mm"] <= 3.0, r
    assert proc.poll() is None


def test_commands_outside_the_workspace_never_take_the_tcp_outside(franka):
    client, proc, lab = franka
    bench.approach(client, np.asarray(CONTROL.home_position))
    r = bench.run_workspace(client, lab.workspace, duration=3.0)
    assert r["workspace_requested_outside_mm"] > 50  # the sender really asked for it
    assert r["max_outside_workspace_mm"] == 0.0, r
    assert proc.poll() is None


def test_nan_chunk_is_rejected_and_the_node_keeps_running(franka):
    client, proc, _lab = franka
    r = bench.run_nan(client)
    assert r["nan_rejected"] == 1 and r["alive_after_nan"], r
    assert proc.poll() is None


def test_gripper_moves_without_blocking_the_arm(franka):
    """A gripper command must not hold up franka_node's control loop or its state publishing
    (on franky-sim it once froze both): a blocking move stops them for the whole move, about a
    second for these 4-6 cm at 0.05 m/s, so no new state may be missing for 0.5 s meanwhile."""
    client, proc, _lab = franka
    here = client.latest_position()

    def width():
        return 2 * client.data.last_joint_state.position[7]

    def move_fingers(target):  # as the policy does: chunks holding the arm, the width in them
        deadline = time.monotonic() + 15.0  # however slowly a busy sim moves the fingers
        while time.monotonic() < deadline and abs(width() - target) > 0.003:
            now = client.now_ns()
            times = now + np.arange(4, dtype=np.int64) * 200_000_000
            client.publish_chunk(PoseChunk(now, times, np.stack([down_pose(here)] * 4), np.full(4, target)))
            client.sleep(0.2)  # keeps the watchdog quiet while the fingers travel
        assert width() == pytest.approx(target, abs=0.006)

    t0 = client.now()
    move_fingers(0.08)  # from wherever the fingers are (40 mm at start-up)
    move_fingers(0.02)
    _, gaps = state_stamps(client, t0, client.now())
    assert gaps.max() < 0.5, f"no new state for {gaps.max():.2f} s while the gripper moved"
    assert np.linalg.norm(client.latest_position() - here) < 0.005  # the arm held still meanwhile
    assert proc.poll() is None
