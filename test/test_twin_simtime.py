"""The twin on simulated time: lockstep gates, libfranka kept alive across pauses, stalls, /clock."""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from helpers_ros import FrozenMainThread

from equidiff_core.twin.lockstep import NS_PER_TICK, Lockstep, LockstepConfig

MS = NS_PER_TICK


def test_a_frame_owes_its_chunk_by_its_instant_plus_the_latency_budget():
    ls = Lockstep(LockstepConfig(frame_period_ticks=200, latency_ticks=100))
    ls.frame_taken(200)  # not awaiting yet: nothing is owed
    assert ls.chunk_blocker(10_000) == ""
    assert ls.await_from(400 * MS)  # an episode starting at t=0.4 s, announced in time
    assert ls.awaiting
    ls.frame_taken(400)
    assert ls.chunk_blocker(499) == ""  # before t + L the sim runs on
    assert "voxel_node" in ls.chunk_blocker(500)  # at t + L: no grid for the frame either
    ls.on_voxels(400 * MS)
    assert ls.chunk_blocker(500).startswith("policy_node: no chunk for the observation at t=0.400 s")
    ls.on_chunk(399 * MS)  # a chunk for an older observation does not pay this frame's debt
    assert ls.chunk_blocker(500)
    ls.on_chunk(400 * MS)
    assert ls.chunk_blocker(500) == ""
    ls.frame_taken(600)
    ls.on_voxels(600 * MS)
    assert ls.chunk_blocker(700)
    ls.on_skipped(600 * MS)  # the policy will not answer it (no robot state): nothing is owed
    assert ls.chunk_blocker(700) == ""
    ls.frame_taken(800)
    ls.await_from(-1)  # the episode ended: its debts are void
    assert ls.chunk_blocker(10_000) == "" and not ls.awaiting
    # the next episode starts at t=1.2 s: the frame before it owes nothing, its own frame does
    assert ls.await_from(1200 * MS)
    ls.frame_taken(1000)
    assert ls.chunk_blocker(10_000) == ""
    ls.frame_taken(1200)
    assert ls.chunk_blocker(1300)
    ls.await_from(-1)
    # a start announced after its first frame was taken is late: that frame is not owed
    ls.frame_taken(1400)
    assert not ls.await_from(1400 * MS)
    assert ls.chunk_blocker(10_000) == ""
    ls.await_from(-1)
    # with L longer than a frame period several chunks are owed; a newer chunk pays older debts too
    slow = Lockstep(LockstepConfig(frame_period_ticks=200, latency_ticks=400))
    slow.await_from(0)
    slow.frame_taken(600)
    slow.frame_taken(800)
    assert slow.chunk_blocker(999) == "" and slow.chunk_blocker(1000)
    slow.on_chunk(800 * MS)
    assert slow.chunk_blocker(10_000) == ""


def test_a_stall_gives_up_the_oldest_debt_and_is_recorded():
    ls = Lockstep(LockstepConfig(frame_period_ticks=200, latency_ticks=100))
    ls.await_from(0)
    ls.frame_taken(200)
    ls.frame_taken(400)
    ls.give_up_oldest("policy stalled")
    assert ls.stalls == ["policy stalled"]
    assert ls.chunk_blocker(450) == "" and ls.chunk_blocker(500)  # the next frame's debt still stands
    with pytest.raises(ValueError):
        LockstepConfig(frame_period_ticks=0, latency_ticks=100)


@pytest.mark.sim
@pytest.mark.slow
def test_sim_waits_for_cameras_and_the_policy_and_keeps_franky_alive_through_a_long_pause():
    """On simulated time the sim must not pass a frame instant before every registered camera
    took the frame, nor an observation's time + L before its chunk arrived. It may wait far
    longer than libfranka's 1 s UDP timeout: the client must still be connected and able to
    move afterwards (keep_alive re-sends the last state under its id)."""
    franky = pytest.importorskip("franky")
    from equidiff_core.robots.franky.sim import free_loopback_host
    from equidiff_core.runtime.machine import keep_thread_scheduler
    from equidiff_core.twin import TwinConfig
    from equidiff_core.twin.shared_state import StateReader
    from equidiff_core.twin.sim import TwinSim

    clock: list[int] = []
    cfg = LockstepConfig(frame_period_ticks=200, latency_ticks=100, stall_timeout_s=60.0, max_speed=0.0)
    sim = TwinSim(
        TwinConfig(),
        host=free_loopback_host(),
        shm_name=f"eqd_simtime_{os.getpid()}",
        lockstep=cfg,
        on_clock=clock.append,
        camera_names=("cam_a",),
    )
    sim.start(seed=1)
    try:
        with keep_thread_scheduler("libfranka"):
            robot = franky.Robot(sim.host, realtime_config=franky.RealtimeConfig.Ignore)
        robot.recover_from_errors()
        camera = StateReader(sim.shm_name)
        camera.register(0)

        def ticks_after(seconds: float) -> int:
            time.sleep(seconds)
            return sim.tick

        # a registered camera that takes no frame holds the sim at the next frame instant
        stuck = ticks_after(1.0)
        assert stuck % 200 == 0 and ticks_after(0.5) == stuck
        frame, _, sim_time, stamp = camera.take_frame(0, timeout_s=1.0)
        assert stamp == stuck * MS and sim_time == pytest.approx(stuck / 1000)
        # while an episode awaits the policy: the next frame's chunk is owed by its instant + L
        sim.lockstep.await_from(0)
        frame, *_ = camera.take_frame(frame, timeout_s=5.0)
        owed = sim.tick - sim.tick % 200
        deadline = time.monotonic() + 5.0
        while sim.tick < owed + 100 and time.monotonic() < deadline:
            time.sleep(0.01)
        held = ticks_after(2.5)  # 2.5 s of wall time without a new robot state: past libfranka's 1 s
        assert held == owed + 100, "the sim passed t + L without the chunk"
        assert sim.status()["wait_s"]["policy"] > 2.0
        assert clock[-1] == held * MS  # /clock shows the instant the sim waits at
        sim.lockstep.on_chunk(owed * MS)
        camera.unregister()
        assert ticks_after(1.0) > held
        # the episode ends: nothing holds the sim now (awaiting, the next frame's chunk would hold
        # the motion below until the 60 s stall timeout let the sim go on)
        sim.lockstep.await_from(-1)
        # libfranka survived the pause: state reads and a motion work
        with keep_thread_scheduler("libfranka"):
            robot.move(franky.JointMotion(list(robot.state.q)))
        assert np.all(np.isfinite(robot.state.q))
        assert all(b >= a for a, b in itertools.pairwise(clock))  # /clock never goes back (it repeats while waiting)
    finally:
        sim.stop()


@pytest.mark.sim
def test_a_camera_that_never_takes_its_frame_is_reported_as_a_stall_and_dropped():
    from equidiff_core.robots.franky.sim import free_loopback_host
    from equidiff_core.twin import TwinConfig
    from equidiff_core.twin.shared_state import StateReader
    from equidiff_core.twin.sim import TwinSim

    cfg = LockstepConfig(frame_period_ticks=50, latency_ticks=10, stall_timeout_s=1.0, max_speed=0.0)
    sim = TwinSim(
        TwinConfig(),
        host=free_loopback_host(),
        shm_name=f"eqd_stall_{os.getpid()}",
        lockstep=cfg,
        camera_names=("cam_a", "cam_b"),
    )
    sim.start(seed=1)
    try:
        dead = StateReader(sim.shm_name)
        dead.register(1)  # registers, then never takes a frame (a hung camera process)
        deadline = time.monotonic() + 20
        while not sim.lockstep.stalls and time.monotonic() < deadline:
            time.sleep(0.05)
        assert (
            sim.lockstep.stalls
            and "cam_b" in sim.lockstep.stalls[0]
            and "did not take the frame" in sim.lockstep.stalls[0]
        )
        before = sim.tick
        time.sleep(0.5)
        assert sim.tick > before + 50  # dropped: the sim goes on without it
        assert sim.status()["stalls"] == 1 and "cam_b" in sim.status()["last_stall"]
        dead.close()
    finally:
        sim.stop()


@pytest.mark.ros
def test_a_node_on_simulated_time_without_clock_waits_and_says_why(ros_domain, tmp_path):
    log = tmp_path / "voxel.log"
    with open(log, "w") as fh:
        proc = subprocess.Popen(
            [sys.executable, "-m", "equidiff_ros.voxel_node", "--ros-args", "-p", "use_sim_time:=true"],
            stdout=fh,
            stderr=subprocess.STDOUT,
        )
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and "no /clock has arrived" not in log.read_text():
            assert proc.poll() is None, log.read_text()
            time.sleep(0.2)
        text = log.read_text()
        assert "use_sim_time is true but no /clock has arrived" in text and "twin_node" in text
        assert "fusing" not in text  # it did not start working on a clock that reads 0
    finally:
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=30)
    assert code == 0, log.read_text()


def test_polled_clock_sleeps_until_its_time_and_stops_on_request():
    from equidiff_core.runtime.clock import PolledClock

    now = [0]
    clock = PolledClock(lambda: now[0])
    stop = threading.Event()
    threading.Timer(0.05, lambda: now.__setitem__(0, 10)).start()
    assert clock.sleep_until(10, stop) is True and clock.now_ns() == 10
    threading.Timer(0.05, stop.set).start()
    assert clock.sleep_until(20, stop) is False  # a clock that stopped never traps the caller
    watched = PolledClock(lambda: now[0], stall_s=0.2)  # a client's clock: a dead sim is an error
    with pytest.raises(TimeoutError, match="stood still at 0.000 s for 0.2 s"):
        watched.sleep_until(20, threading.Event())


@pytest.mark.slow
@pytest.mark.ros
@pytest.mark.sim
def test_a_hung_policy_ends_its_episode_as_stalled_naming_it_and_the_job_goes_on(ros_domain, tmp_path):
    """A policy_node that stops answering (its main thread frozen: alive, silent) must not hang the sim: after
    the stall timeout the episode ends as stalled, naming policy_node, its bag is kept, and the
    next episode runs once the policy answers again."""
    from equidiff_core.config import default_config_dir, load_lab_config
    from equidiff_core.data.bags import read_episode
    from equidiff_core.twin.config import TwinConfig
    from equidiff_core.twin.standin import make_standin_policy
    from equidiff_ros.twin import TwinStack, run_policy_episode

    cfg_dir = default_config_dir()
    lab = load_lab_config(cfg_dir / "lab.yaml")
    policy = make_standin_policy(tmp_path / "standin.pt", lab.workspace, preset="tiny", cfg=TwinConfig())
    with TwinStack(
        tmp_path / "run",
        cfg_dir / "lab.yaml",
        cfg_dir / "twin.yaml",
        policy=str(policy),
        domain_id=221 + (ros_domain + 5) % 12,
        stall_timeout_s=5.0,
        log=lambda s: None,
    ) as stack:
        pid = next(n.popen.pid for n in stack.group.nodes if n.name == "policy_node")
        with FrozenMainThread(pid):  # its executor and Python hang; its DDS threads answer on
            stalled = run_policy_episode(stack, 1, 10.0)
        assert stalled.stalled.startswith("t=") and "policy_node: no chunk for the observation" in stalled.stalled
        assert not stalled.success
        episode = read_episode(Path(stalled.bag))
        assert episode.meta.success is False and "stalled" in (episode.meta.notes or "")
        # "once the policy answers again": thawed, it first works off what queued up while it
        # was stopped; the next episode starts once it answers (its chunks arrive, gate closed)
        seen = stack.sup.policy_chunks_seen
        stack.sup.wait_for(
            lambda: stack.sup.policy_chunks_seen > seen + 2, 120.0, "policy_node answering again", stack.check
        )
        after = run_policy_episode(stack, 2, 4.0)
        assert not after.stalled and after.chunks >= 2 and after.dropped_cycles == 0


@pytest.mark.ros
def test_the_stamp_of_a_serialised_message_is_read_without_decoding_it():
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import PointCloud2
    from trajectory_msgs.msg import MultiDOFJointTrajectory

    from equidiff_core.wire.rosmsg import header_stamp_ns_from_cdr

    for cls in (PointCloud2, MultiDOFJointTrajectory):
        msg = cls()
        msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id = 12, 345_000_001, "fr3_link0"
        assert header_stamp_ns_from_cdr(serialize_message(msg)) == 12_345_000_001


@pytest.mark.ros
def test_the_control_clients_sleep_follows_the_sim_clock_and_a_stopped_one_is_a_clear_error(ros_domain):
    """The client's sleeps are sim seconds, however long they take on the wall clock; a /clock that stops
    (twin_node gone) ends a sleep with TimeoutError after ``clock_stall_s`` wall seconds, not a hang."""
    from rosgraph_msgs.msg import Clock

    from equidiff_core.config import default_config_dir, load_lab_config
    from equidiff_ros.control_client import ControlClient

    lab_path = default_config_dir() / "lab.yaml"
    client = ControlClient(load_lab_config(lab_path), str(lab_path), use_sim_time=True, clock_stall_s=1.0)
    clock_pub = client.node.create_publisher(Clock, "/clock", 10)
    sim_ns = [1_000_000_000]
    ticking = threading.Event()
    ticking.set()

    def tick():  # the sim at a tenth of real time: 1 ms of sim time every 10 ms
        while ticking.is_set() and client.context.ok():
            clock_pub.publish(Clock(clock=client.factory.time(sim_ns[0])))
            sim_ns[0] += 1_000_000
            time.sleep(0.01)

    ticker = threading.Thread(target=tick, daemon=True)
    try:
        ticker.start()
        client.wait_for(lambda: client.now_ns() > 0, 30.0, "the first /clock")
        start = client.now()
        wall = time.monotonic()
        client.sleep(0.05)  # 50 ms of sim time: ~0.5 s of wall time
        assert client.now() >= start + 0.05 and time.monotonic() - wall > 0.2
        ticking.clear()
        ticker.join()
        wall = time.monotonic()
        with pytest.raises(TimeoutError, match="simulated clock stood still .* is the twin still running"):
            client.sleep(1.0)
        assert 1.0 <= time.monotonic() - wall < 20.0
    finally:
        ticking.clear()
        client.close()
