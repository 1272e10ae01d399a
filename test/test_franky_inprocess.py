"""The franky backend in-process (Controller + FrankyRobot) on franky-sim: recovery, gripper,
posture, limits.

Each test starts its own franky-sim. They live apart from test_franka_sim.py so that module's
franky-sim and franka_node (a module fixture, alive until its last test) do not run beside
them: two sims and a node on a busy 2-core CI machine starved this one's sim past libfranka's
1 s receive timeout ("UDP receive: Timeout" while homing).
"""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

pytest.importorskip("franky")
pytest.importorskip("franky_sim")

from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.control import load_control_config
from equidiff_core.robots.franky.sim import SimServer
from equidiff_core.wire.chunk import PoseChunk

pytestmark = [pytest.mark.sim, pytest.mark.slow]

LAB_PATH = default_config_dir() / "lab.yaml"
CONTROL = load_control_config(default_config_dir() / "control.yaml")


def test_controller_holds_once_when_the_franky_motion_stops_and_recovers_when_acknowledged():
    """In-process Controller + FrankyRobot on their own franky-sim: the streaming motion is
    stopped under it (preempted by another client). The next tick notices, holds once (nothing retried),
    and only the acknowledgement restarts streaming, holding where the arm is."""
    from equidiff_core.control import Controller
    from equidiff_core.robots import RobotError, make_robot

    with SimServer() as sim:
        robot = make_robot("franky", ip=sim.host, config=CONTROL.franky, realtime=False, gripper=False)
        with robot:
            ctl = Controller(robot, load_lab_config(LAB_PATH).safety_box, CONTROL)
            with pytest.raises(RobotError, match="outside the safety box"):
                ctl.start(home=False)  # franky-sim's initial pose is above the box: no surprise motion
            ctl.start(home=True)
            try:
                time.sleep(0.5)
                before = ctl.state.ee_pose[:3, 3].copy()
                robot._robot.stop()
                time.sleep(1.0)
                status = ctl.status()
                assert status.state == "awaiting_ack" and "Move command preempted" in status.reason, status
                assert ctl.stats.robot_stops == 1 and ctl.stats.recoveries == 0 and not robot._robot.is_in_control
                assert np.linalg.norm(ctl.state.ee_pose[:3, 3] - before) < 0.002
                here = ctl.state.ee_pose.copy()
                now = ctl.clock.now_ns()
                nudge = here.copy()
                nudge[0, 3] += 0.01
                chunk = PoseChunk(now, np.array([now + 300_000_000]), nudge[None], np.array([0.08]))
                assert not ctl.submit(chunk) and ctl.stats.ack_rejected == 1
                assert "Move command preempted" in ctl.acknowledge()
                assert robot._robot.is_in_control and ctl.status().state == "holding"  # streaming again
                time.sleep(0.5)
                assert np.linalg.norm(ctl.state.ee_pose[:3, 3] - here[:3, 3]) < 0.002  # held where it was
                now = ctl.clock.now_ns()
                assert ctl.submit(PoseChunk(now, np.array([now + 300_000_000]), nudge[None], np.array([0.08])))
            finally:
                ctl.stop()


def test_a_fault_automatic_recovery_cannot_clear_faults_until_it_is_cleared_at_the_robot():
    """franky-sim's ``error`` fault (a joint past its limit: "manual error recovery required"),
    through the real franky client: held, the acknowledgement's recovery is refused by the
    robot (faulted), and once cleared at the robot another acknowledgement goes on."""
    from equidiff_core.control import AcknowledgeRefused, Controller
    from equidiff_core.robots import make_robot

    with SimServer() as sim:
        robot = make_robot("franky", ip=sim.host, config=CONTROL.franky, realtime=False, gripper=False)
        with robot:
            ctl = Controller(robot, load_lab_config(LAB_PATH).safety_box, CONTROL)
            ctl.start(home=True)
            try:
                time.sleep(0.3)
                sim.inject("error")
                time.sleep(0.5)
                status = ctl.status()
                assert status.state == "awaiting_ack" and "joint_position_limits_violation" in status.reason, status
                with pytest.raises(AcknowledgeRefused, match="manual error recovery required"):
                    ctl.acknowledge()
                assert ctl.status().state == "faulted" and ctl.faulted and not robot._robot.is_in_control
                sim.inject("clear")  # the operator's manual recovery at the arm
                assert "joint_position_limits_violation" in ctl.acknowledge()
                assert ctl.status().state == "holding" and not ctl.faulted and robot._robot.is_in_control
            finally:
                ctl.stop()


def test_franky_gripper_follows_widths_changed_while_it_moves():
    """A width sent while the last gripper command still ran made franky-sim drop that command's
    reply and franky block the new call forever: the fingers never moved again and the twin's
    homing failed ("gripper 50 mm for 80 mm"). Changing the width mid-motion must still end at
    the newest width."""
    from equidiff_core.robots import make_robot

    policy = os.sched_getscheduler(0)
    with SimServer() as sim:
        robot = make_robot("franky", ip=sim.host, config=CONTROL.franky, realtime=False, gripper=True)
        with robot:
            # libfranka made this (the test runner's) thread SCHED_FIFO 99 in Robot(); every node
            # a later test started inherited it, and CI's main-job smoke test hung
            assert os.sched_getscheduler(0) == policy
            for width in (0.03, 0.07, 0.01):  # each one well before the last has finished
                robot.move_gripper(width)
                time.sleep(0.15)
            robot.move_gripper(0.08)
            deadline = time.monotonic() + 15.0
            while time.monotonic() < deadline and abs(robot.read_state().gripper_width - 0.08) > 0.003:
                time.sleep(0.1)
            assert robot.read_state().gripper_width == pytest.approx(0.08, abs=0.003)


def test_arm_keeps_its_posture_while_the_tcp_wanders_and_yaws():
    """Cartesian impedance leaves the FR3's redundant elbow free: 40 s of wandering, yawing
    targets drifted the joints 1.7 rad on franky-sim (in the twin's main job, until joints hit
    their limits and the arm flailed out of the workspace). The tracker's null-space posture
    task must bring the arm back to its home configuration when the TCP returns home."""
    from equidiff_core.control import Controller
    from equidiff_core.geometry import rotation_angle
    from equidiff_core.robots import make_robot
    from equidiff_core.twin.expert import tcp_pose

    rng = np.random.default_rng(0)
    lab = load_lab_config(LAB_PATH)
    with SimServer() as sim:
        robot = make_robot("franky", ip=sim.host, config=CONTROL.franky, realtime=False, gripper=False)
        with robot:
            ctl = Controller(robot, lab.safety_box, CONTROL)
            ctl.start(home=True)
            try:
                q_home, home = ctl.state.joint_positions.copy(), ctl.state.ee_pose[:3, 3].copy()

                assert np.isfinite(ctl.state.robot_time_s)  # libfranka's time: the glide is timed by it
                state = {"pose": ctl.state.ee_pose.copy()}

                def send(pose):  # a teleop-like one-point target, 50 ms ahead
                    now = time.time_ns()
                    ctl.submit(PoseChunk(now, np.array([now + 50_000_000]), pose[None], np.array([0.08])))
                    state["pose"] = pose

                def behind() -> bool:  # the TCP trails its last target by more than 3 cm or 14 deg
                    tcp, target = ctl.state.ee_pose, state["pose"]
                    return (
                        np.linalg.norm(tcp[:3, 3] - target[:3, 3]) > 0.03
                        or rotation_angle(tcp[:3, :3], target[:3, :3]) > 0.25
                    )

                def glide(p0, y0, p1, y1, seconds):
                    """Targets at 20 Hz moving from (p0, y0) to (p1, y1) in ``seconds`` of the robot's own
                    time; like teleop's lead limit, the glide waits while the TCP trails its target, so a
                    starved machine (CI's busy 2 cores: the sim, libfranka and this loop all late) slows it
                    down instead of running a target past the first-step jump check."""
                    progress, last = 0.0, ctl.state.robot_time_s
                    deadline = time.monotonic() + 10 * seconds + 10
                    while progress < seconds:
                        assert time.monotonic() < deadline, f"the TCP stopped following its targets: {ctl.stats}"
                        now = ctl.state.robot_time_s
                        if not behind():  # at most 0.1 s of glide per target: a late loop takes no big step
                            progress = min(progress + min(now - last, 0.1), seconds)
                        last = now
                        a = progress / seconds
                        send(tcp_pose((1 - a) * p0 + a * p1, (1 - a) * y0 + a * y1))
                        time.sleep(0.05)

                pos, yaw = home, 0.0
                for _ in range(8):
                    goal, goal_yaw = rng.uniform([0.32, -0.12, 0.05], [0.58, 0.12, 0.3]), rng.uniform(-1.2, 1.2)
                    glide(pos, yaw, goal, goal_yaw, 3.0)
                    pos, yaw = goal, goal_yaw
                glide(pos, yaw, home, 0.0, 2.0)
                settle_until, deadline = ctl.state.robot_time_s + 1.0, time.monotonic() + 20.0
                while ctl.state.robot_time_s < settle_until and time.monotonic() < deadline:
                    send(state["pose"])  # hold home for 1 s of the robot's time
                    time.sleep(0.05)
                assert ctl.stats.rejected_chunks == 0, ctl.stats
                assert np.linalg.norm(ctl.state.ee_pose[:3, 3] - home) < 0.005, ctl.stats
                assert np.abs(ctl.state.joint_positions - q_home).max() < 0.2, ctl.state.joint_positions - q_home
            finally:
                ctl.stop()


def test_limits_are_set_explicitly_on_connect_and_a_joint_driven_into_its_limit_stops():
    """On franky-sim: the collision thresholds and the blocking moves' joint
    velocity limit are set from control.yaml on connect (franky-sim acknowledges the thresholds
    but simulates no reflex, so only their delivery shows here), and yawing the hand until joint 7
    reaches a (tightened) position limit stops the motion and holds until acknowledged."""
    import dataclasses

    from equidiff_core.control import Controller
    from equidiff_core.robots import make_robot
    from equidiff_core.twin.expert import tcp_pose, tcp_yaw

    lab = load_lab_config(LAB_PATH)
    with SimServer() as sim:
        robot = make_robot(
            "franky", ip=sim.host, config=CONTROL.franky, realtime=False, gripper=False, safety=CONTROL.safety
        )
        with robot:
            applied = robot.applied_limits
            assert applied["collision_torque_thresholds_nm"] == list(CONTROL.franky.collision_torque_thresholds_nm)
            assert applied["collision_force_thresholds_n"] == list(CONTROL.franky.collision_force_thresholds_n)
            franky_limit = robot._robot.joint_velocity_limit
            np.testing.assert_allclose(
                franky_limit.get(), np.minimum(CONTROL.safety.max_joint_speeds_rad_s, franky_limit.max)
            )
            ctl = Controller(robot, lab.safety_box, CONTROL)
            ctl.start(home=True)
            ctl.stop()
            q7 = float(ctl.state.joint_positions[6])
            # joint 7 may turn 0.3 rad either way from home: the tracker pushes back from 0.2 rad on,
            # the controller stops at 0.25 rad if it still turns towards the limit
            lo, hi = list(CONTROL.safety.joint_position_min_rad), list(CONTROL.safety.joint_position_max_rad)
            lo[6], hi[6] = q7 - 0.3, q7 + 0.3
            tight = dataclasses.replace(
                CONTROL,
                safety=dataclasses.replace(
                    CONTROL.safety, joint_position_min_rad=tuple(lo), joint_position_max_rad=tuple(hi)
                ),
            )
            robot.safety = tight.safety
            ctl = Controller(robot, lab.safety_box, tight)
            ctl.start(home=False)
            try:
                home = ctl.state.ee_pose.copy()
                yaw0, yaw = tcp_yaw(home), 0.0
                deadline = time.monotonic() + 60.0
                while not ctl.awaiting_ack and yaw < 1.2 and time.monotonic() < deadline:
                    yaw += 0.01  # ~0.2 rad/s: one-point targets 50 ms ahead at 20 Hz, as teleop sends
                    now = time.time_ns()
                    ctl.submit(
                        PoseChunk(
                            now, np.array([now + 50_000_000]), tcp_pose(home[:3, 3], yaw0 + yaw)[None], np.array([0.08])
                        )
                    )
                    time.sleep(0.05)
                assert "joint 7" in ctl.awaiting_ack, ctl.stats
                assert abs(ctl.state.joint_positions[6] - q7) < 0.3 + 0.05  # stopped near its limit
                stopped_at = ctl.state.ee_pose.copy()
                now = time.time_ns()
                assert not ctl.submit(PoseChunk(now, np.array([now + 50_000_000]), home[None], np.array([0.08])))
                time.sleep(0.5)
                assert np.linalg.norm(ctl.state.ee_pose[:3, 3] - stopped_at[:3, 3]) < 0.003  # held
                assert "joint 7" in ctl.acknowledge()
            finally:
                ctl.stop()
