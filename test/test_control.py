"""Safety filter, chunk scheduler and control loop (pure: dry-run robot, simulated clock)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, rule

from equidiff_core import geometry
from equidiff_core.config import (
    ConfigError,
    SafetyBox,
    Workspace,
    default_config_dir,
    from_dict,
)
from equidiff_core.control import (
    AcknowledgeRefused,
    ChunkScheduler,
    ControlConfig,
    Controller,
    ControllerStatus,
    SafetyConfig,
    SafetyFilter,
    SafetyRejection,
    SchedulerConfig,
    Setpoint,
    check_chunk,
    load_control_config,
)
from equidiff_core.control.state_machine import (
    AWAITING_OPERATOR,
    MOVING,
    NOT_STREAMING,
    STATES,
    STATUS,
    TRANSITIONS,
    Event,
    SafetyState,
    mermaid_diagram,
)
from equidiff_core.robots import RobotError, RobotStopped, UserStopPressed, make_robot
from equidiff_core.robots.dryrun import DryRunConfig, DryRunRobot
from equidiff_core.wire.chunk import ChunkError, ChunkReason, PoseChunk, chunk_from_msg, chunk_to_msg
from equidiff_core.wire.rosmsg import rosbags_factory

WS = Workspace()
BOX = SafetyBox()
CENTER = np.asarray(WS.center)
MS = 1_000_000
HOME = geometry.pose_from_pos_quat((0.45, 0.0, 0.30), (1.0, 0.0, 0.0, 0.0))


def pose_at(p, base=HOME):
    T = base.copy()
    T[:3, 3] = p
    return T


def circle(t, center=(0.45, 0.0, 0.25), radius=0.05, speed=0.079):
    """A point on a horizontal circle, starting at angle 0, moving at ``speed`` m/s."""
    w = speed / radius
    return np.asarray(center) + radius * np.array([np.cos(w * t), np.sin(w * t), 0.0])


def circle_chunk(stamp_ns, t0_ns, steps=8, dt_ns=200 * MS, width=0.08):
    times = stamp_ns + np.arange(steps, dtype=np.int64) * dt_ns
    poses = np.stack([pose_at(circle((t - t0_ns) / 1e9)) for t in times])
    return PoseChunk(int(stamp_ns), times, poses, np.full(steps, width))


class FakeClock:
    def __init__(self, t_ns=1_000_000 * 1_000_000_000):
        self.t = t_ns

    def now_ns(self):
        return self.t

    def sleep_until(self, t_ns, stop):
        self.t = max(self.t, t_ns)
        return not stop.is_set()


def make_controller(config=ControlConfig(), start=None, clock=None, robot=None):
    start = circle(0.0) if start is None else start
    clock = clock or FakeClock()
    robot = robot or DryRunRobot(DryRunConfig(initial_position=tuple(start)))
    robot.connect()
    ctl = Controller(robot, BOX, config, clock=clock)
    ctl.start(home=False, thread=False)
    return ctl, robot, clock


# --- config ------------------------------------------------------------------------------


def test_control_yaml_loads_and_matches_the_documented_defaults():
    assert load_control_config(default_config_dir() / "control.yaml") == ControlConfig()


def test_control_config_errors_name_the_key():
    with pytest.raises(ConfigError, match=r"ControlConfig\.safety: unknown key"):
        from_dict(ControlConfig, {"safety": {"max_speed": 1.0}})
    with pytest.raises(ConfigError, match=r"safety.watchdog_timeout_s: 0.0 s is out of range; allowed: 0 < x <= 5 s"):
        from_dict(ControlConfig, {"safety": {"watchdog_timeout_s": 0}})
    with pytest.raises(ConfigError, match="interpolation"):
        from_dict(ControlConfig, {"scheduler": {"interpolation": "spline"}})


# --- safety ------------------------------------------------------------------------------


def test_filter_clips_targets_to_the_safety_box_and_its_floor_margin():
    box = SafetyBox(lower=(0.3, -0.1, 0.0), upper=(0.6, 0.1, 0.3), floor_margin_m=0.02)
    # no box_margin_m (its own test: test_commands_brake_towards_a_wall_and_stop_the_margin_inside)
    safety = SafetyFilter(box, SafetyConfig(max_linear_speed_m_s=100.0, box_margin_m=0.0))
    out = safety.filter(pose_at(CENTER), pose_at(np.array(box.upper) + 0.3), dt=1.0)
    assert out.clipped
    np.testing.assert_allclose(out.pose[:3, 3], box.upper)
    out = safety.filter(pose_at(CENTER), pose_at((0.45, 0.0, -0.1)), dt=1.0)  # into the table
    assert out.clipped
    np.testing.assert_allclose(out.pose[:3, 3], (0.45, 0.0, 0.02))  # held the floor margin above it
    with pytest.raises(ConfigError, match="safety box is empty"):
        from_dict(SafetyBox, {"lower": [0.3, -0.1, 0.0], "upper": [0.6, 0.1, 0.01], "floor_margin_m": 0.02})


def test_commands_brake_towards_a_wall_and_stop_the_margin_inside():
    """A command stopped dead at a wall at the speed limit let the impedance-tracked arm
    overshoot it (2.6 mm outside the box on franky-sim). Commands now stop ``box_margin_m`` inside
    and brake on the way (v <= sqrt(2 a d)), arriving at rest; far from a wall the speed limit
    alone governs."""
    limits = SafetyConfig(box_margin_m=0.004, wall_deceleration_m_s2=2.0)
    safety = SafetyFilter(BOX, limits)
    floor = BOX.min_corner[2] + limits.box_margin_m
    dt, p = 0.005, pose_at((0.45, 0.0, 0.20))
    zs = [p[2, 3]]
    for _ in range(400):  # straight down through the table, asked for at 0.3 m/s
        p = safety.filter(p, pose_at((0.45, 0.0, p[2, 3] - 0.3 * dt)), dt).pose
        zs.append(p[2, 3])
    zs, speeds = np.array(zs), -np.diff(zs) / dt
    assert zs.min() == pytest.approx(floor, abs=1e-4) and zs.min() >= floor - 1e-12  # the margin above the floor
    assert speeds.max() == pytest.approx(limits.max_linear_speed_m_s)  # the speed limit far from it
    gap = zs[:-1] - floor
    assert np.all(speeds <= np.sqrt(2 * limits.wall_deceleration_m_s2 * gap) + 1e-9)  # braked near it
    assert speeds[-50:].max() < 0.01  # at rest when it gets there
    away = safety.filter(p, pose_at((0.45, 0.0, 0.3)), dt)  # leaving a wall is not braked
    assert away.pose[2, 3] - p[2, 3] == pytest.approx(limits.max_linear_speed_m_s * dt)
    assert safety.inside(pose_at((0.45, 0.0, BOX.min_corner[2] + 0.001))[:3, 3])  # the box itself, not the margin
    with pytest.raises(ConfigError, match=r"safety.box_margin_m: -0.001 m is out of range"):
        from_dict(ControlConfig, {"safety": {"box_margin_m": -0.001}})
    with pytest.raises(ValueError, match="leaves nothing of the safety box"):
        SafetyFilter(BOX, SafetyConfig(box_margin_m=0.5))


def test_filter_limits_linear_and_angular_speed():
    limits = SafetyConfig(max_linear_speed_m_s=0.25, max_angular_speed_rad_s=0.6)
    safety = SafetyFilter(BOX, limits)
    start = pose_at(CENTER)
    far = pose_at(CENTER + [0.1, 0.0, 0.0], base=geometry.rotz_pose(1.0) @ HOME)
    out = safety.filter(start, far, dt=0.005)
    assert out.speed_limited
    moved = np.linalg.norm(out.pose[:3, 3] - start[:3, 3])
    assert moved == pytest.approx(0.25 * 0.005)
    from equidiff_core.geometry import rotation_angle

    assert rotation_angle(start[:3, :3], out.pose[:3, :3]) == pytest.approx(0.6 * 0.005, rel=1e-6)
    assert np.linalg.norm(out.linear_velocity) <= 0.25 + 1e-9
    # A reachable target is passed through with its own feed-forward.
    near = pose_at(CENTER + [0.001, 0, 0])
    out = safety.filter(start, near, dt=0.005, linear_velocity=np.array([0.2, 0, 0]))
    assert not out.speed_limited and not out.clipped
    np.testing.assert_allclose(out.pose, near, atol=1e-12)
    np.testing.assert_allclose(out.linear_velocity, [0.2, 0, 0])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(*[st.floats(-2.0, 2.0)] * 3), min_size=1, max_size=30))
def test_filtered_commands_never_leave_the_box(targets):
    safety = SafetyFilter(BOX, SafetyConfig())
    pose = pose_at(CENTER)
    for t in targets:
        pose = safety.filter(pose, pose_at(np.asarray(t)), dt=0.05).pose
        assert safety.inside(pose[:3, 3])


def test_check_chunk_rejects_jumps_and_bad_rotations():
    limits = SafetyConfig(max_first_step_jump_m=0.05, max_first_step_rotation_rad=0.5)
    here = pose_at((0.45, 0.0, 0.25))
    ok = PoseChunk(0, np.array([1, 2]), np.stack([pose_at((0.47, 0, 0.25)), pose_at((0.5, 0, 0.25))]), np.zeros(2))
    check_chunk(ok, here, limits)
    far = PoseChunk(0, np.array([1]), pose_at((0.55, 0, 0.25))[None], np.zeros(1))
    with pytest.raises(SafetyRejection, match="mm from the current pose"):
        check_chunk(far, here, limits)
    turned = PoseChunk(0, np.array([1]), (geometry.rotz_pose(0.8, (0.45, 0, 0.25)) @ here)[None], np.zeros(1))
    with pytest.raises(SafetyRejection, match="rotated"):
        check_chunk(turned, here, limits)
    sheared = ok.poses.copy()
    sheared[:, 0, 1] += 2e-4  # passes PoseChunk's 1e-3 but not a stricter limit
    with pytest.raises(ChunkError, match="orthonormal"):
        check_chunk(dataclasses.replace(ok, poses=sheared), here, SafetyConfig(orthonormal_tol=1e-5))


# --- scheduler ------------------------------------------------------------------------------


def rest_at(pose):
    return Setpoint(pose, np.zeros(3), np.zeros(3), float("nan"), False)


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_scheduler_drops_past_steps_and_passes_through_the_rest(interpolation):
    sched = ChunkScheduler(SchedulerConfig(interpolation=interpolation))
    t0 = 10_000 * MS
    chunk = circle_chunk(stamp_ns=t0, t0_ns=t0)
    now = t0 + 300 * MS  # steps 0 and 1 are past
    live = sched.live_steps(chunk, now)
    assert len(live) == 6 and live.times_ns[0] == t0 + 400 * MS
    sched.schedule(live, now, rest_at(pose_at(circle(0.3))))
    for t, pose in zip(live.times_ns, live.poses):
        np.testing.assert_allclose(sched.sample(int(t)).pose, pose, atol=1e-9)
    end = sched.sample(int(live.times_ns[-1]) + 500 * MS)
    assert not end.active and np.allclose(end.linear_velocity, 0)
    np.testing.assert_allclose(end.pose, live.poses[-1], atol=1e-9)


def test_scheduler_rejects_stale_chunks_and_keeps_a_recent_teleop_target():
    sched = ChunkScheduler(SchedulerConfig(max_step_age_s=0.25, lead_s=0.05))
    now = 50_000 * MS
    teleop = PoseChunk(now - 20 * MS, np.array([now - 20 * MS]), pose_at((0.5, 0, 0.2))[None], np.array([0.04]))
    live = sched.live_steps(teleop, now)
    assert live.times_ns.tolist() == [now + 50 * MS]
    stale = dataclasses.replace(teleop, stamp_ns=now - 400 * MS, times_ns=np.array([now - 400 * MS]))
    with pytest.raises(ChunkError, match="stale"):
        sched.live_steps(stale, now)


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_streamed_chunks_track_a_curve_without_velocity_reversals(interpolation):
    """5 Hz chunks of 8 steps along a circle, each 100 ms late (inference): the setpoint moves
    along the circle with continuous position, never backwards, within 1 mm of it."""
    cfg = dataclasses.replace(ControlConfig(), scheduler=SchedulerConfig(interpolation=interpolation))
    ctl, _robot, clock = make_controller(cfg)
    t0 = clock.t
    period = int(1e9 / cfg.control_hz)
    positions, times = [], []
    for tick in range(int(4.0 * cfg.control_hz)):
        if tick % int(0.2 * cfg.control_hz) == 0:
            obs = max(t0, clock.t - 100 * MS)
            assert ctl.submit(circle_chunk(obs, t0))
        cmd = ctl.tick()
        positions.append(cmd.target.pose[:3, 3])
        times.append((clock.t - t0) / 1e9)
        clock.t += period
    positions, times = np.array(positions), np.array(times)
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    assert steps.max() < 0.25 / cfg.control_hz + 1e-9  # speed limit, no jumps at chunk switches
    # Progress along the circle (its angle) never decreases.
    angle = np.unwrap(np.arctan2(positions[:, 1] - 0.0, positions[:, 0] - 0.45))
    assert np.diff(angle).min() > -1e-9, "the setpoint moved backwards"
    ref = np.array([circle(t) for t in times])
    err = np.linalg.norm(positions - ref, axis=1)[times > 0.5]
    assert err.max() < 1e-3


# --- controller -------------------------------------------------------------------------


def test_watchdog_holds_the_pose_when_commands_stop():
    """A chunk is a plan for its whole span: its steps run to the last one (policy_node answers
    every 1.6 s with 1.4 s of steps), and the watchdog holds the measured pose only once no new
    chunk came for watchdog_timeout_s after that last step."""
    ctl, _robot, clock = make_controller()
    t0 = clock.t
    chunk = circle_chunk(t0, t0)  # 8 steps, 1.4 s
    ctl.submit(chunk)
    period = int(1e9 / ctl.config.control_hz)
    last_step_s = (int(chunk.times_ns[-1]) - t0) / 1e9
    timeout_s = ctl.config.safety.watchdog_timeout_s
    for _ in range(int((last_step_s + timeout_s - 0.05) * ctl.config.control_hz)):
        ctl.tick()
        clock.t += period
    assert not ctl.holding and ctl.stats.watchdog_holds == 0  # the whole chunk ran, then 0.45 s of its last pose
    reached = ctl.tick().target.pose[:3, 3]
    np.testing.assert_allclose(reached, chunk.poses[-1][:3, 3], atol=1e-3)  # it got to the chunk's end
    for _ in range(int(0.1 * ctl.config.control_hz)):  # past the timeout after the last step
        clock.t += period
        ctl.tick()
    assert ctl.holding and ctl.stats.watchdog_holds == 1
    held = ctl.tick().target.pose.copy()
    assert np.linalg.norm(held[:3, 3] - reached) < 0.25 * 0.25 + 1e-6
    for _ in range(int(2.0 * ctl.config.control_hz)):
        clock.t += period
        np.testing.assert_allclose(ctl.tick().target.pose, held, atol=1e-12)
    assert ctl.stats.watchdog_holds == 1
    resume = PoseChunk(clock.t, np.array([clock.t + 200 * MS]), pose_at(held[:3, 3] + 0.01)[None], np.ones(1))
    assert ctl.submit(resume) and not ctl.holding  # a fresh chunk resumes


@pytest.mark.parametrize("robot_clock_rate", [None, 0.5])
def test_speed_limits_hold_in_the_robots_own_time(robot_clock_rate):
    """A twin on a loaded machine runs at ~0.5x real time; commanded at wall-clock speed, its arm
    lagged 8 cm behind and was then whipped at 3 rad/s. With a robot clock (libfranka's state
    time) the command moves at most v_max per second of *robot* time; without one, of ours."""
    clock = FakeClock()
    start_ns = clock.t

    class ClockedRobot(DryRunRobot):
        def read_state(self):
            state = super().read_state()
            if robot_clock_rate is None:
                return state
            return dataclasses.replace(state, robot_time_s=(clock.t - start_ns) / 1e9 * robot_clock_rate)

    ctl, _robot, _ = make_controller(clock=clock, robot=ClockedRobot(DryRunConfig(initial_position=(0.45, 0.0, 0.25))))
    period = int(1e9 / ctl.config.control_hz)
    goal = pose_at(np.array([0.45, 0.07, 0.25]))  # 7 cm away, due in 50 ms: speed-limited all the way
    ctl.submit(PoseChunk(clock.t, np.array([clock.t + 50 * MS]), goal[None], np.ones(1)))
    first = ctl.tick().target.pose[:3, 3].copy()
    for _ in range(int(0.2 * ctl.config.control_hz)):  # 0.2 s of wall time
        clock.t += period
        last = ctl.tick().target.pose[:3, 3]
    moved = float(np.linalg.norm(last - first))
    v_max = ctl.config.safety.max_linear_speed_m_s
    assert moved == pytest.approx(v_max * 0.2 * (robot_clock_rate or 1.0), rel=0.05)


def test_arm_running_away_from_its_command_is_stopped_and_held_where_it_is():
    """The FR3 stops itself with a reflex; franky-sim never does (the twin's arm once flailed out of
    the workspace at 25 rad/s). The controller stops the motion, restarts it where the arm is
    and holds; running away again while it holds stops streaming altogether (nothing is
    counted, nothing resumes) until an operator acknowledges."""

    class RunawayRobot(DryRunRobot):
        offset, joint_speed, restarts = np.zeros(3), np.zeros(7), 0

        def read_state(self):
            state = super().read_state()
            state.ee_pose[:3, 3] += self.offset
            state.joint_velocities[:] = self.joint_speed
            return state

        def start_streaming(self):
            self.restarts += 1
            super().start_streaming()

    robot = RunawayRobot(DryRunConfig(initial_position=tuple(circle(0.0))))
    ctl, _, clock = make_controller(robot=robot)
    period = int(1e9 / ctl.config.control_hz)
    t0 = clock.t
    ctl.submit(circle_chunk(t0, t0))
    for _ in range(20):
        assert ctl.tick() is not None
        clock.t += period
    restarts = robot.restarts
    robot.offset = np.array([0.12, 0.0, 0.0])  # the arm runs 12 cm away from its command
    runaway = robot.read_state().ee_pose[:3, 3]
    assert ctl.tick() is None
    assert ctl.stats.divergence_stops == 1 and "mm from the command" in ctl.stats.last_divergence
    assert robot.restarts == restarts + 1 and ctl.holding
    clock.t += period
    held = ctl.tick().target.pose[:3, 3]
    np.testing.assert_allclose(held, runaway, atol=1e-9)  # holds where the arm is, not where it was sent
    robot.offset = np.zeros(3)
    for _ in range(int(0.5 * ctl.config.control_hz)):  # braking grace: no second stop
        clock.t += period
        ctl.tick()
    assert ctl.stats.divergence_stops == 1 and not ctl.faulted
    # It never resumes on its own: chunks are refused, the arm holds, until an operator acknowledges.
    assert "divergence stop" in ctl.awaiting_ack
    assert not ctl.submit(circle_chunk(clock.t, t0)) and ctl.stats.ack_rejected == 1 and ctl.holding
    assert "awaiting an operator's acknowledgement" in ctl.stats.last_rejection
    robot.joint_speed = np.array([2.4, 0, 0, 0, 0, 3.9, 4.9])  # fast but within each joint's limit
    for _ in range(int(2 * ctl.config.control_hz)):
        clock.t += period
        np.testing.assert_allclose(ctl.tick().target.pose[:3, 3], runaway, atol=1e-9)  # still held
    assert ctl.stats.divergence_stops == 1 and ctl.holding
    assert "divergence stop" in ctl.acknowledge() and not ctl.awaiting_ack and ctl.acknowledge() == ""
    go_on = PoseChunk(clock.t, np.array([clock.t + 200 * MS]), pose_at(runaway + 0.01)[None], np.ones(1))
    assert ctl.submit(go_on) and not ctl.holding  # after the operator's go-ahead
    robot.joint_speed = np.full(7, 3.0)  # keeps whipping: stopped and held, then streaming stopped
    restarts = robot.restarts
    for _ in range(int(5 * ctl.config.control_hz)):
        clock.t += period
        ctl.tick()
    assert "joint 1 at 3.0 rad/s (limit 2.5 rad/s)" in ctl.stats.last_divergence
    assert ctl.stats.divergence_stops == 3 and robot.restarts == restarts + 1  # restarted once, then left stopped
    assert not ctl.faulted and ctl.status().state == "awaiting_ack" and "streaming stopped" in ctl.status().reason
    assert not ctl.submit(go_on)
    robot.joint_speed = np.zeros(7)
    assert "again while holding" in ctl.acknowledge() and robot.restarts == restarts + 2
    clock.t += period
    assert ctl.tick() is not None and ctl.status().state == "holding"


def test_chunk_outside_the_workspace_never_moves_the_command_outside():
    ctl, robot, clock = make_controller(start=(0.45, 0.0, 0.30))
    period = int(1e9 / ctl.config.control_hz)
    upper = BOX.max_corner - ctl.config.safety.box_margin_m  # commands stop this far inside the box
    zs = []
    for tick in range(int(2.0 * ctl.config.control_hz)):
        if tick % 40 == 0:  # a sender that keeps asking for 2 cm per step upwards, through the lid
            z = ctl.state.ee_pose[2, 3]
            poses = np.stack([pose_at((0.45, 0.0, z + 0.02 * i)) for i in range(8)])
            assert ctl.submit(PoseChunk(clock.t, clock.t + np.arange(8) * 200 * MS, poses, np.full(8, 0.08)))
        clock.t += period
        zs.append(ctl.tick().target.pose[2, 3])
    assert max(zs) <= upper[2] + 1e-9
    assert max(zs) == pytest.approx(upper[2])  # it went as far as allowed, no farther
    assert ctl.stats.clipped_ticks > 0
    assert all(cmd[2][2, 3] <= upper[2] + 1e-9 for cmd in robot.sent if cmd[0] == "target")


def test_rejected_chunks_are_counted_and_the_node_keeps_its_trajectory():
    ctl, _robot, clock = make_controller()
    t0 = clock.t
    assert ctl.submit(circle_chunk(t0, t0))
    far = PoseChunk(t0, np.array([t0 + 200 * MS]), pose_at((0.60, 0.1, 0.1))[None], np.zeros(1))
    assert not ctl.submit(far)
    assert ctl.stats.jump_rejected == 1
    # A NaN chunk never becomes a PoseChunk: decoding fails, the node records it.
    msg = chunk_to_msg(circle_chunk(t0, t0), rosbags_factory(), "fr3_link0")
    msg.points[3].transforms[0].translation.y = float("nan")
    with pytest.raises(ChunkError) as err:
        chunk_from_msg(msg)
    ctl.record_rejection(err.value)
    assert ctl.stats.nan_rejected == 1 and ctl.stats.rejected_chunks == 2
    # The accepted trajectory is still executed.
    for _ in range(int(0.4 * ctl.config.control_hz)):
        clock.t += int(1e9 / ctl.config.control_hz)
        ctl.tick()
    np.testing.assert_allclose(ctl.tick().target.pose[:3, 3], circle(0.4), atol=1e-3)


def test_gripper_is_commanded_only_when_its_target_changes():
    ctl, robot, clock = make_controller()
    t0 = clock.t
    widths = np.array([0.08, 0.08, 0.078, 0.02, 0.02, 0.021, 0.08, 0.08])
    times = t0 + np.arange(8) * 200 * MS
    poses = np.stack([pose_at(circle(0.0))] * 8)
    chunk = PoseChunk(t0, times, poses, widths)
    for tick in range(int(1.6 * ctl.config.control_hz)):
        if tick % 40 == 0:  # re-sent every 0.2 s, as a live sender would, so the watchdog stays quiet
            ctl.submit(chunk)
        ctl.tick()
        clock.t += int(1e9 / ctl.config.control_hz)
    sent = [float(v) for kind, _, v in robot.sent if kind == "gripper"]
    assert sent == pytest.approx([0.08, 0.02, 0.08])


def test_teleop_one_point_chunks_are_followed_smoothly():
    """teleop_node's format: one point, stamp = now, reached 50 ms later, at 20 Hz."""
    ctl, _robot, clock = make_controller(start=(0.45, 0.0, 0.25))
    period = int(1e9 / ctl.config.control_hz)
    target = np.array([0.45, 0.0, 0.25])
    xs = []
    for tick in range(int(1.5 * ctl.config.control_hz)):
        if tick % 10 == 0:  # 20 Hz, the operator pushes +x at 4 cm/s
            target = target + [0.002, 0.0, 0.0]
            assert ctl.submit(
                PoseChunk(clock.t, np.array([clock.t + 50 * MS]), pose_at(target)[None], np.ones(1) * 0.08)
            )
        xs.append(ctl.tick().target.pose[0, 3])
        clock.t += period
    assert not ctl.holding and ctl.stats.rejected_chunks == 0
    assert np.diff(xs).min() >= -1e-12  # never backwards
    assert xs[-1] == pytest.approx(target[0], abs=0.003)  # within one teleop step of the operator


class StoppingRobot(DryRunRobot):
    """The dry-run arm with an FR3's own stops, behind our Robot interface: a user stop (pressed
    until released), a reflex, a lost connection (unreadable until reconnected), and a fault
    automatic recovery cannot clear. Counts reads and recoveries."""

    def __init__(self, position=None):
        super().__init__(DryRunConfig(initial_position=tuple(circle(0.0) if position is None else position)))
        self.stopped = ""  # a RobotStopped kind: the motion ended
        self.pressed = self.lost = self.manual = False
        self.reads = self.recoveries = 0

    def press(self):
        self.pressed, self.stopped = True, "user_stop"

    def read_state(self):
        if self.lost:
            raise RobotStopped("connection_lost", "libfranka: UDP receive: Timeout")
        self.reads += 1
        mode = "user_stopped" if self.pressed else ("reflex" if self.stopped == "reflex" else "idle")
        return dataclasses.replace(super().read_state(), mode=mode)

    def stream_target(self, pose, v, w):
        if self.stopped:
            raise RobotStopped(self.stopped, f"libfranka: Move command aborted ({self.stopped})")
        super().stream_target(pose, v, w)

    def recover(self):
        self.recoveries += 1
        if self.pressed:
            raise UserStopPressed("the user stop is still pressed")
        if self.manual:
            raise RobotError("recover_from_errors failed: manual error recovery required")
        done = "reconnected, errors cleared" if self.lost else "errors cleared"
        self.lost, self.stopped = False, ""
        return done


def run_ticks(ctl, clock, seconds):
    period = int(1e9 / ctl.config.control_hz)
    commands = []
    for _ in range(int(seconds * ctl.config.control_hz)):
        clock.t += period
        commands.append(ctl.tick())
    return commands


def test_a_user_stop_holds_once_until_released_and_acknowledged():
    """A user stop makes every streamed target fail. One held state, entered once (no
    failing tick counted, no recovery hammered, the stopped robot polled at a low rate); an
    acknowledgement while it is pressed is refused; after release + acknowledgement the arm
    holds and accepts chunks; a fault after that holds again."""
    robot = StoppingRobot()
    ctl, _, clock = make_controller(robot=robot)
    t0 = clock.t
    assert ctl.submit(circle_chunk(t0, t0)) and ctl.status().state == "moving"
    run_ticks(ctl, clock, 0.2)
    robot.press()
    reads = robot.reads
    commands = run_ticks(ctl, clock, 3.0)
    assert all(c is None for c in commands)  # nothing streamed to a stopped robot
    status = ctl.status()
    assert status.state == "awaiting_ack" and status.reason.startswith("user stop: libfranka")
    assert "still pressed" in status.reason and status.last_fault.startswith("user stop")
    assert status.last_fault_ns > t0 and ctl.stats.robot_stops == 1 and robot.recoveries == 0
    assert robot.reads - reads <= 3.0 * 10 + 2  # polled at 10 Hz, not at the 200 Hz control rate
    assert not ctl.submit(circle_chunk(clock.t, clock.t)) and ctl.stats.ack_rejected == 1
    with pytest.raises(ChunkError, match="awaiting"):
        ctl.go_home()
    with pytest.raises(AcknowledgeRefused, match="still pressed"):
        ctl.acknowledge()
    assert ctl.status().state == "awaiting_ack" and robot.recoveries == 0 and ctl.stats.ack_refused == 1
    robot.pressed = False  # released: the mode reads idle, the motion is still ended
    run_ticks(ctl, clock, 0.3)
    assert "released: acknowledge to go on" in ctl.status().reason
    assert ctl.acknowledge().startswith("user stop") and robot.recoveries == 1
    assert ctl.status().state == "holding" and ctl.status().last_fault.startswith("user stop")
    assert all(c is not None and c.holding for c in run_ticks(ctl, clock, 0.5))
    assert ctl.submit(circle_chunk(clock.t, clock.t)) and ctl.status().state == "moving"
    run_ticks(ctl, clock, 0.2)

    robot.stopped = "reflex"  # a repeated fault after the acknowledgement: held again, never resumed
    run_ticks(ctl, clock, 1.0)
    assert ctl.status().state == "awaiting_ack" and ctl.status().reason.startswith("reflex")
    assert ctl.stats.robot_stops == 2 and robot.recoveries == 1
    assert not ctl.submit(circle_chunk(clock.t, clock.t))
    assert ctl.acknowledge().startswith("reflex") and ctl.submit(circle_chunk(clock.t, clock.t))


def test_a_lost_connection_holds_and_the_acknowledgement_connects_again():
    robot = StoppingRobot()
    ctl, _, clock = make_controller(robot=robot)
    assert ctl.submit(circle_chunk(clock.t, clock.t))
    run_ticks(ctl, clock, 0.2)
    robot.lost = True
    assert all(c is None for c in run_ticks(ctl, clock, 2.0))
    status = ctl.status()
    assert status.state == "awaiting_ack" and status.reason.startswith("connection to the robot lost")
    assert "connects again" in status.reason and ctl.stats.robot_stops == 1 and robot.recoveries == 0
    assert not ctl.submit(circle_chunk(clock.t, clock.t))
    assert "reconnected" in ctl.acknowledge() and ctl.status().state == "holding"
    assert ctl.submit(circle_chunk(clock.t, clock.t)) and run_ticks(ctl, clock, 0.1)[-1] is not None


def test_a_recovery_the_robot_refuses_faults_until_an_acknowledgement_succeeds():
    robot = StoppingRobot()
    ctl, _, clock = make_controller(robot=robot)
    robot.stopped, robot.manual = "reflex", True  # e.g. a joint past its limit: guided out in Desk
    run_ticks(ctl, clock, 0.5)
    with pytest.raises(AcknowledgeRefused, match="manual error recovery required"):
        ctl.acknowledge()
    status = ctl.status()
    assert status.state == "faulted" and "manual error recovery" in status.reason and ctl.faulted
    assert "manual error recovery" in status.last_fault
    assert all(c is None for c in run_ticks(ctl, clock, 1.0)) and not ctl.submit(circle_chunk(clock.t, clock.t))
    with pytest.raises(ChunkError):
        ctl.go_home()
    robot.manual = False  # fixed at the robot: acknowledged again
    assert ctl.acknowledge().startswith("reflex") and not ctl.faulted
    assert ctl.status().state == "holding" and ctl.submit(circle_chunk(clock.t, clock.t))


def test_a_held_start_moves_nothing_until_acknowledged():
    """franka_node after any restart: no home move, chunks refused; with the TCP outside the box
    the acknowledgement moves it home (the robot's planned move) before streaming starts."""
    robot = DryRunRobot(DryRunConfig(initial_position=tuple(circle(0.0))))
    robot.connect()
    clock = FakeClock()
    ctl = Controller(robot, BOX, ControlConfig(), clock=clock)
    ctl.start(home=True, thread=False, hold="franka_node started")
    assert ctl.status() == ControllerStatus("awaiting_ack", "franka_node started", "", 0)
    assert [k for k, _, _ in robot.sent] == []  # no home move
    assert not ctl.submit(circle_chunk(clock.t, clock.t))
    assert all(c.holding for c in run_ticks(ctl, clock, 0.2))
    assert ctl.acknowledge() == "franka_node started" and ctl.submit(circle_chunk(clock.t, clock.t))

    outside = (0.55, 0.0, 0.52)  # franky-sim's start pose, above the box
    robot = DryRunRobot(DryRunConfig(initial_position=outside))
    robot.connect()
    ctl = Controller(robot, BOX, ControlConfig(), clock=clock)
    with pytest.raises(RobotError, match="outside the safety box"):
        ctl.start(home=False, thread=False, hold="franka_node started")
    ctl.start(home=True, thread=False, hold="franka_node started")
    assert "moves it home first" in ctl.status().reason and list(robot.sent) == []
    assert all(c is None for c in run_ticks(ctl, clock, 0.5)) and list(robot.sent) == []
    assert "moving home first" in ctl.acknowledge() and ctl.status().state == "homing"
    assert not ctl.submit(circle_chunk(clock.t, clock.t))
    run_ticks(ctl, clock, 0.1)
    assert robot.sent[0][0] == "move_to" and ctl.status().state == "holding"
    np.testing.assert_allclose(ctl.state.ee_pose[:3, 3], ctl.config.home_position)


def test_streaming_does_not_start_with_the_tcp_outside_the_box():
    robot = DryRunRobot(DryRunConfig(initial_position=(0.55, 0.0, 0.52)))  # franky-sim's start pose
    robot.connect()
    ctl = Controller(robot, BOX, ControlConfig(), clock=FakeClock())
    with pytest.raises(RobotError, match="outside the safety box"):
        ctl.start(home=False, thread=False)
    assert [k for k, _, _ in robot.sent] == []  # nothing was sent
    ctl.start(home=True, thread=False)  # the home pose is inside: fine
    assert robot.sent[0][0] == "move_to"


def test_dryrun_logs_what_would_be_sent(caplog):
    robot = make_robot("dryrun")
    robot.connect()
    ctl = Controller(robot, BOX, ControlConfig(), clock=FakeClock())
    with caplog.at_level("INFO", logger="equidiff.robot.dryrun"):
        ctl.start(home=True, thread=False)
        ctl.tick()
    assert any("would send move_to" in r.message for r in caplog.records)
    assert [k for k, _, _ in robot.sent][:2] == ["move_to", "target"]
    with pytest.raises(ValueError, match="unknown robot backend"):
        make_robot("ur5")


# --- explicit limits: cone, joint limits, gripper range, robot limits -----------


def tilted(position, tilt, yaw=0.0, axis=(0.0, 1.0, 0.0)):
    """A TCP pose at ``position``, yawed by ``yaw`` and then tilted ``tilt`` rad about base ``axis``."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(np.asarray(axis) * tilt).as_matrix() @ geometry.rotz(yaw) @ HOME[:3, :3]
    return geometry.make_pose(R, np.asarray(position, dtype=float))


def test_tilt_is_measured_from_straight_down_whatever_the_yaw():
    for yaw in (0.0, 1.0, -2.5):
        assert geometry.tilt_angle(tilted(CENTER, 0.0, yaw)[:3, :3]) == pytest.approx(0.0, abs=1e-12)
        assert geometry.tilt_angle(tilted(CENTER, 0.3, yaw)[:3, :3]) == pytest.approx(0.3)
        R = tilted(CENTER, 1.2, yaw, axis=(0.6, 0.8, 0.0))[:3, :3]
        limited = geometry.limit_tilt(R, 0.5)
        assert geometry.tilt_angle(limited) == pytest.approx(0.5)
        geometry.validate_rotation(limited)
        # swung back about the tilt's own axis: the shortest way, 0.7 rad
        assert geometry.rotation_angle(R, limited) == pytest.approx(0.7)
    inside = tilted(CENTER, 0.4)[:3, :3]
    assert geometry.limit_tilt(inside, 0.5) is inside


def test_chunk_with_a_step_outside_the_cone_is_rejected_and_the_arm_holds():
    ctl, _robot, clock = make_controller(start=(0.45, 0.0, 0.25))
    limit = ctl.config.safety.max_tilt_rad
    here = ctl.state.ee_pose
    times = clock.t + np.arange(4) * 200 * MS
    ok = np.stack([tilted((0.45, 0.0, 0.25), a * (limit - 0.05), 0.3 * a) for a in np.linspace(0, 1, 4)])
    assert ctl.submit(PoseChunk(clock.t, times, ok, np.full(4, 0.08)))  # up to the cone's edge, yawing: fine
    over = ok.copy()
    over[3] = tilted((0.45, 0.0, 0.25), limit + 0.05)
    ctl2, _robot2, clock2 = make_controller(start=(0.45, 0.0, 0.25))
    assert not ctl2.submit(PoseChunk(clock2.t, times, over, np.full(4, 0.08)))
    assert ctl2.stats.cone_rejected == 1 and ctl2.stats.rejected_chunks == 1 and ctl2.holding
    assert "tilts the tool" in ctl2.stats.last_rejection
    for _ in range(40):
        clock2.t += int(1e9 / ctl2.config.control_hz)
        np.testing.assert_allclose(ctl2.tick().target.pose, here, atol=1e-12)  # nothing of it ran
    with pytest.raises(SafetyRejection) as err:
        check_chunk(PoseChunk(0, np.array([1]), over[3:], np.zeros(1)), None, ctl.config.safety)
    assert err.value.kind == "cone"


def test_every_command_stays_inside_the_cone():
    """Interpolating between two steps inside the cone that also yaw can swing the tool axis out by
    a little; the per-tick filter swings it back."""
    safety = SafetyFilter(BOX, SafetyConfig(max_tilt_rad=0.5, max_angular_speed_rad_s=100.0))
    start = tilted(CENTER, 0.5, 0.0, axis=(1.0, 0.0, 0.0))
    target = tilted(CENTER, 0.9, 3.0, axis=(0.0, 1.0, 0.0))
    out = safety.filter(start, target, dt=0.005)
    assert out.clipped and geometry.tilt_angle(out.pose[:3, :3]) <= 0.5 + 1e-9


def test_gripper_widths_are_clipped_to_the_hands_range():
    """The shipped policy predicted widths from -0.059 to 0.154 m on the sample bag: the hand gets
    its own range (min/max_gripper_width_m), never more, never less."""
    ctl, robot, clock = make_controller()
    limits = ctl.config.safety
    pose = pose_at(circle(0.0))
    for width in (-0.059, 0.154, 0.04):
        ctl.submit(PoseChunk(clock.t, clock.t + np.arange(2) * 200 * MS, np.stack([pose] * 2), np.full(2, width)))
        for _ in range(10):
            clock.t += int(1e9 / ctl.config.control_hz)
            ctl.tick()
    sent = [float(v) for kind, _, v in robot.sent if kind == "gripper"]
    assert sent == pytest.approx([limits.min_gripper_width_m, limits.max_gripper_width_m, 0.04])
    narrow = SafetyFilter(BOX, SafetyConfig(min_gripper_width_m=0.01, max_gripper_width_m=0.05))
    assert [narrow.clip_width(w) for w in (-0.059, 0.03, 0.154)] == pytest.approx([0.01, 0.03, 0.05])


def test_joint_moving_into_its_position_limit_stops_the_motion_until_acknowledged():
    """Joint position limits (SafetyConfig.joint_position_*): a joint within the margin of its limit
    that still moves towards it stops the motion like a divergence; moving away is allowed."""

    class JointRobot(DryRunRobot):
        q, dq = np.array(DryRunConfig().joint_positions), np.zeros(7)

        def read_state(self):
            return dataclasses.replace(
                super().read_state(), joint_positions=self.q.copy(), joint_velocities=self.dq.copy()
            )

    robot = JointRobot(DryRunConfig(initial_position=tuple(circle(0.0))))
    ctl, _, clock = make_controller(robot=robot)
    limits = ctl.config.safety
    period = int(1e9 / ctl.config.control_hz)
    robot.q[6] = limits.joint_position_max_rad[6] - 0.02  # within the margin ...
    robot.dq[6] = -0.5  # ... moving away: fine
    for _ in range(5):
        clock.t += period
        assert ctl.tick() is not None
    robot.q[3], robot.dq[3] = limits.joint_position_min_rad[3] + 0.2, -1.0  # far from its limit: fine
    clock.t += period
    assert ctl.tick() is not None and ctl.stats.divergence_stops == 0
    robot.dq[6] = 0.3  # towards the limit
    clock.t += period
    assert ctl.tick() is None
    assert ctl.stats.divergence_stops == 1 and "joint 7" in ctl.stats.last_divergence
    assert "moving towards its limit" in ctl.awaiting_ack and ctl.holding
    assert not ctl.submit(circle_chunk(clock.t, clock.t))
    assert "joint 7" in ctl.acknowledge()


def test_limits_are_explicit_config_keys_with_checked_values():
    cfg = load_control_config(default_config_dir() / "control.yaml")
    assert len(cfg.franky.collision_torque_thresholds_nm) == 7 and len(cfg.franky.collision_force_thresholds_n) == 6
    assert cfg.safety.joint_position_min_rad[3] < cfg.safety.joint_position_max_rad[3] < 0  # the FR3's elbow
    with pytest.raises(ConfigError, match="collision_torque_thresholds_nm must be 7 positive"):
        from_dict(ControlConfig, {"franky": {"collision_torque_thresholds_nm": [20.0] * 6}})
    with pytest.raises(ConfigError, match="min < max"):
        from_dict(ControlConfig, {"safety": {"joint_position_min_rad": [0.0] * 7, "joint_position_max_rad": [0.0] * 7}})
    with pytest.raises(ConfigError, match=r"safety.max_tilt_rad: 0.0 rad is out of range"):
        from_dict(ControlConfig, {"safety": {"max_tilt_rad": 0.0}})
    with pytest.raises(ConfigError, match=r"SafetyBox.floor_margin_m: -0.01 m is out of range"):
        from_dict(SafetyBox, {"floor_margin_m": -0.01})


def test_streaming_does_not_start_with_the_tool_outside_the_cone():
    R = tilted((0.45, 0.0, 0.25), 1.0)
    p, q = geometry.pos_quat_from_pose(R)
    robot = DryRunRobot(DryRunConfig(initial_position=tuple(p), initial_quaternion_xyzw=tuple(q)))
    robot.connect()
    ctl = Controller(robot, BOX, ControlConfig(), clock=FakeClock())
    with pytest.raises(RobotError, match="outside the 45 deg cone"):
        ctl.start(home=False, thread=False)
    assert list(robot.sent) == []  # nothing was sent


def test_go_home_glides_slowly_to_the_home_pose_and_is_refused_awaiting_acknowledgement():
    ctl, robot, clock = make_controller(start=(0.55, 0.1, 0.2))
    period = int(1e9 / ctl.config.control_hz)
    duration = ctl.go_home()
    distance = np.linalg.norm(np.subtract(ctl.config.home_position, (0.55, 0.1, 0.2)))
    assert duration == pytest.approx(distance / ctl.config.home_speed_m_s, rel=0.01)
    assert not ctl.submit(circle_chunk(clock.t, clock.t)) and "homing" in ctl.stats.last_rejection
    positions = []
    for _ in range(int((duration + 0.5) * ctl.config.control_hz)):
        clock.t += period
        positions.append(ctl.tick().target.pose[:3, 3])
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    assert steps.max() <= ctl.config.home_speed_m_s * 1.3 / ctl.config.control_hz  # slowly, at home speed
    np.testing.assert_allclose(positions[-1], ctl.config.home_position, atol=1e-6)
    assert [k for k, _, _ in robot.sent if k == "gripper"] == []  # the gripper left alone
    assert ctl.submit(PoseChunk(clock.t, np.array([clock.t + 200 * MS]), ctl.home_pose[None], np.ones(1) * 0.08))
    ctl.require_acknowledgement("a test stop")
    with pytest.raises(ChunkError, match="awaiting an operator's acknowledgement"):
        ctl.go_home()


# --- metrics ---------------------------------------------------------------------------------


def test_metrics_measure_what_they_claim():
    from equidiff_core.control import metrics

    t = np.arange(0.0, 4.0, 0.01)
    path = np.stack([circle(x) for x in t])

    def tangent(x):
        return np.array([-np.sin(x * 0.079 / 0.05), np.cos(x * 0.079 / 0.05), 0.0])

    assert metrics.tracking_rms(t, path, circle) == pytest.approx(0.0, abs=1e-12)
    lag, rms = metrics.tracking_lag(t[20:], path[:-20], circle)  # the same path, 0.2 s late
    assert lag == pytest.approx(0.2, abs=0.006) and rms < 1e-4
    assert metrics.velocity_reversals(t, path, tangent) == 0
    # Stop-and-go with a step back at every chunk switch (every 0.2 s): counted, once each.
    progress = t + 0.06 * np.sin(2 * np.pi * t / 0.2)  # runs backwards ~60 ms per period
    jerky = np.stack([circle(x) for x in progress])
    assert metrics.velocity_reversals(t, jerky, tangent) == pytest.approx(len(t) * 0.01 / 0.2, abs=2)
    assert metrics.max_outside_box(path, WS.lower, WS.upper) == 0.0
    assert metrics.max_outside_box(np.array([[0.7, 0.0, 0.4]]), WS.lower, WS.upper) == pytest.approx(
        np.hypot(0.05, 0.02)
    )
    settle = np.concatenate([path[:100], np.repeat(path[100:101], 300, axis=0)])
    assert metrics.settle_time(t, settle) == pytest.approx(t[100])
    assert metrics.percentiles_ms([0.1, 0.2, 0.3]) == [200.0, 290.0]


class DoneFuture:
    """A franky ``BoolFuture`` that has finished."""

    def wait(self, timeout: float) -> bool:
        return True


def test_franky_gripper_commands_never_block_the_caller_and_the_newest_width_wins():
    """The control loop calls move_gripper at 200 Hz; a franky gripper call that blocks (it did
    on franky-sim, freezing the arm) must only ever stall the gripper's own thread."""
    import threading
    import time

    from equidiff_core.robots.franky import FrankyRobot

    class SlowGripper:
        def __init__(self):
            self.sent, self.width = [], 0.08

        def move_async(self, width, speed):
            self.sent.append(round(width, 3))
            time.sleep(0.4)
            return DoneFuture()

        grasp_async = lambda self, width, speed, force, **kw: self.move_async(width, speed)

    robot = FrankyRobot("0.0.0.0")
    robot._gripper = gripper = SlowGripper()
    thread = threading.Thread(target=robot._poll_gripper, daemon=True)
    thread.start()
    try:
        robot.move_gripper(0.05)
        time.sleep(0.1)  # the thread picks 0.05 up and blocks in it
        t0 = time.monotonic()
        for width in (0.04, 0.03, 0.02):
            robot.move_gripper(width)
        assert time.monotonic() - t0 < 0.05
        time.sleep(1.0)
        assert gripper.sent == [0.05, 0.02]  # superseded widths are never sent
    finally:
        robot._gripper_stop.set()
        thread.join(timeout=2)


def test_franky_gripper_command_that_fails_is_retried_not_lost():
    import threading
    import time

    from equidiff_core.robots.franky import FrankyRobot

    class FlakyGripper:
        def __init__(self):
            self.calls, self.width = [], 0.08

        def move_async(self, width, speed):
            self.calls.append(round(width, 3))
            if len(self.calls) == 1:
                raise RuntimeError("gripper busy")
            return DoneFuture()

    robot = FrankyRobot("0.0.0.0")
    robot._gripper = gripper = FlakyGripper()
    thread = threading.Thread(target=robot._poll_gripper, daemon=True)
    thread.start()
    try:
        robot.move_gripper(0.08)
        time.sleep(1.0)
        assert gripper.calls == [0.08, 0.08]  # failed once, sent again after the back-off
    finally:
        robot._gripper_stop.set()
        thread.join(timeout=2)


def test_answer_schedule_answers_one_observation_per_executed_chunk_despite_stamp_jitter():
    from equidiff_core.wire.chunk import AnswerSchedule

    dt = 200_000_000
    answers = AnswerSchedule(0, 8, dt)  # 0: the whole chunk
    assert answers.steps == 8
    answered = []
    for k in range(20):
        stamp = k * dt + (3_000_000 if k % 2 else -3_000_000)  # +-3 ms camera jitter
        if answers.due(stamp):
            answers.answer(stamp)
            answered.append(k)
    assert answered == [0, 8, 16]
    every = AnswerSchedule(1, 8, dt)
    for k in range(3):
        assert every.due(k * dt)
        every.answer(k * dt)
        assert not every.due(k * dt + dt // 4)  # the same frame, a little later: already answered
    with pytest.raises(ValueError, match="execute_steps must be within 1..8"):
        AnswerSchedule(9, 8, dt)
    answers.restart()  # an episode begins: its first observation is answered at once
    assert answers.due(16 * dt + dt)


def test_sampling_seeds_follow_the_episode_and_repeat_with_it():
    """The rule policy_node and the in-process evaluation share: k-th answered observation of
    episode s gets s * 1000 + k; outside an episode, draws from the node's own seed."""
    from equidiff_core.wire.chunk import SamplingSeeds

    seeds = SamplingSeeds(0)
    outside = [seeds.next() for _ in range(3)]
    assert outside[0] == SamplingSeeds(0).next() and len(set(outside)) == 3  # the node's seed repeats them
    seeds.start_episode(100_004)
    assert [seeds.next() for _ in range(3)] == [100_004_000, 100_004_001, 100_004_002]
    seeds.start_episode(100_004)  # the same scene again: the same noise again
    assert seeds.next() == 100_004_000


def test_tf_message_carries_the_tcp_pose_in_the_base_frame():
    """franka_node's /tf (base -> TCP, for RViz and ROS hand-eye tools) where tf2_msgs exists:
    built here with the rosbags factory, which has the type."""
    from scipy.spatial.transform import Rotation

    from equidiff_core.wire import rosmsg
    from equidiff_core.wire.rosmsg import rosbags_factory

    pose = pose_at(np.array([0.4, -0.1, 0.25]))
    pose[:3, :3] = Rotation.from_euler("xyz", [170, 5, 30], degrees=True).as_matrix()
    msg = rosmsg.tf_message(rosbags_factory(), [("fr3_link0", rosmsg.TCP_FRAME, pose)], 1_500_000_123)
    (tf,) = msg.transforms
    assert tf.header.frame_id == "fr3_link0" and tf.child_frame_id == "fr3_hand_tcp"
    assert tf.header.stamp.sec == 1 and tf.header.stamp.nanosec == 500_000_123
    t, r = tf.transform.translation, tf.transform.rotation
    np.testing.assert_allclose([t.x, t.y, t.z], [0.4, -0.1, 0.25])
    np.testing.assert_allclose(Rotation.from_quat([r.x, r.y, r.z, r.w]).as_matrix(), pose[:3, :3], atol=1e-12)


def test_a_new_chunk_continues_the_motion_without_a_standstill_tick():
    """A chunk that continues the running straight line starts from the setpoint *now*, not from
    the one commanded a tick ago: the commanded step at every chunk switch equals the steady one."""
    ctl, _robot, clock = make_controller(start=np.array([0.40, 0.0, 0.25]))
    t0, period, speed = clock.t, int(1e9 / ctl.config.control_hz), 0.1

    def line_chunk(stamp_ns):
        times = stamp_ns + np.arange(8, dtype=np.int64) * 200 * MS
        poses = np.stack([pose_at((0.40 + speed * (t - t0) / 1e9, 0.0, 0.25)) for t in times])
        return PoseChunk(int(stamp_ns), times, poses, np.full(8, 0.08))

    steps, switches = [], []
    previous = ctl.tick().target.pose[:3, 3]
    clock.t += period
    for tick in range(1, 400):
        if tick % 40 == 0:
            assert ctl.submit(line_chunk(clock.t))
            switches.append(len(steps))
        elif tick == 1:
            assert ctl.submit(line_chunk(t0))
        position = ctl.tick().target.pose[:3, 3]
        steps.append(float(np.linalg.norm(position - previous)))
        previous = position
        clock.t += period
    steady = speed * period / 1e9
    assert len(switches) == 9
    for i in switches:
        assert steps[i] == pytest.approx(steady, rel=0.05), (i, steps[i - 2 : i + 2])


# --- time cannot disable safety ------------------------------------------------------------


def _tick_for(ctl, clock, seconds):
    """Tick the controller on its own clock for ``seconds``; the first instant it held (None: never)."""
    period = int(1e9 / ctl.config.control_hz)
    held_at = None
    for _ in range(round(seconds * ctl.config.control_hz)):
        clock.t += period
        ctl.tick()
        if ctl.holding and held_at is None:
            held_at = clock.t
    return held_at


@pytest.mark.parametrize(
    "stamp_ahead_s, first_step_s",
    [(86_400.0, 0.0), (0.2, 0.0), (0.0, 86_400.0), (0.0, 2.0)],
    ids=["stamped-a-day-ahead", "stamped-0.2s-ahead", "first-step-a-day-ahead", "first-step-2s-ahead"],
)
def test_a_far_future_chunk_is_refused_and_silence_after_it_still_holds_the_arm(stamp_ahead_s, first_step_s):
    """A chunk stamped (or starting) far ahead of franka_node's clock is refused and counted, and
    it does not keep the watchdog quiet: with silence after it, the arm holds watchdog_timeout_s
    after the last *accepted* chunk's final step, as without it."""
    ctl, _robot, clock = make_controller()
    t0 = clock.t
    accepted = circle_chunk(t0, t0)
    assert ctl.submit(accepted)
    clock.t += 100 * MS
    stamp = clock.t + int(stamp_ahead_s * 1e9)
    first = stamp + int(first_step_s * 1e9)
    bad = PoseChunk(stamp, first + np.arange(8, dtype=np.int64) * 200 * MS, accepted.poses, accepted.widths)
    assert not ctl.submit(bad)
    assert ctl.stats.future_rejected == 1 and ctl.stats.rejected_chunks == 1
    assert ctl.stats.last_rejection_reason == "future" and "future" in ctl.stats.last_rejection
    deadline = int(accepted.times_ns[-1]) + int(ctl.config.safety.watchdog_timeout_s * 1e9)
    held_at = _tick_for(ctl, clock, (deadline - clock.t) / 1e9 + 0.1)
    assert held_at is not None and held_at <= deadline + int(1e9 / ctl.config.control_hz)
    assert ctl.stats.watchdog_holds == 1


def test_a_chunk_stamped_slightly_ahead_is_accepted_but_does_not_stretch_the_watchdog():
    """Within max_future_stamp_s a stamp ahead of our clock (skew between machines) is accepted,
    and the watchdog counts the chunk's span from its receipt: silence after it holds the arm no
    later than for the same chunk stamped at its receipt."""
    config = ControlConfig()
    ahead = int(config.scheduler.max_future_stamp_s * 1e9)
    ctl, _robot, clock = make_controller(config)
    t0 = clock.t
    chunk = circle_chunk(t0 + ahead, t0 + ahead)
    assert ctl.submit(chunk)
    span = int(chunk.times_ns[-1]) - chunk.stamp_ns
    deadline = t0 + span + int(config.safety.watchdog_timeout_s * 1e9)
    held_at = _tick_for(ctl, clock, (deadline - t0) / 1e9 + 0.1)
    assert held_at is not None and held_at <= deadline + int(1e9 / config.control_hz)


def test_rejections_are_counted_by_their_reason_not_their_text():
    ctl, _robot, _clock = make_controller()
    expected = {
        "nan": ChunkError("anything at all", ChunkReason.NAN),
        "stale": ChunkError("no keyword here", ChunkReason.STALE),
        "future": ChunkError("x", ChunkReason.FUTURE),
        "malformed": ChunkError("chunk is stale NaN orthonormal"),  # the words no longer decide
        "cone": SafetyRejection("y", kind="cone"),
        "jump": SafetyRejection("z"),
    }
    for reason, err in expected.items():
        before = getattr(ctl.stats, f"{reason}_rejected")
        ctl.record_rejection(err)
        assert getattr(ctl.stats, f"{reason}_rejected") == before + 1
        assert ctl.stats.last_rejection_reason == reason
    assert ctl.stats.rejected_chunks == len(expected)
    with pytest.raises(ConfigError, match="max_future_stamp_s"):
        from_dict(ControlConfig, {"scheduler": {"max_future_stamp_s": -1.0}})


# --- the safety state machine ---------------------------------------------------------------


class FaultyRobot(StoppingRobot):
    """``StoppingRobot`` that can also run away from its command (a divergence) and whose planned
    move fails like the real one: stopped by a stop, refused by a fault recovery cannot clear.
    Keeps every motion command it was given, in order."""

    def __init__(self, position=None):
        super().__init__(position)
        self.offset = np.zeros(3)
        self.motions = []  # (kind, value): "target" pose, "move_to" pose, "gripper" width

    def read_state(self):
        state = super().read_state()
        state.ee_pose[:3, 3] += self.offset
        return state

    def stream_target(self, pose, v, w):
        super().stream_target(pose, v, w)
        self.motions.append(("target", np.array(pose)))

    def move_to(self, pose):
        if self.lost or self.stopped:
            raise RobotStopped(self.stopped or "connection_lost", "libfranka: Motion aborted")
        if self.manual:
            raise RobotError("libfranka: Move command rejected: manual error recovery required")
        super().move_to(pose)
        self.motions.append(("move_to", np.array(pose)))

    def move_gripper(self, width):
        super().move_gripper(width)
        self.motions.append(("gripper", width))


def test_the_docs_draw_the_state_machine_from_its_table():
    text = (Path(__file__).resolve().parents[1] / "docs" / "control.md").read_text()
    marker = "<!-- generated by equidiff_core.control.state_machine.mermaid_diagram(); test_control.py compares -->"
    assert marker in text
    drawn = text.split(marker, 1)[1].split("```mermaid\n", 1)[1].split("```", 1)[0]
    assert drawn == mermaid_diagram(), "paste state_machine.mermaid_diagram() into docs/control.md"


def test_the_table_leaves_no_stop_unhandled_and_no_held_state_without_an_acknowledgement():
    streaming = [state for state in SafetyState if state not in NOT_STREAMING]
    for state in streaming:  # the robot may stop, and the arm run away, whatever it streams
        assert TRANSITIONS[state, Event.ROBOT_STOPPED].target in AWAITING_OPERATOR
        assert TRANSITIONS[state, Event.DIVERGED].target in AWAITING_OPERATOR
        outside = TRANSITIONS.get((state, Event.DIVERGED_OUTSIDE))
        assert outside is None or outside.target is SafetyState.STOPPED  # never streams from outside
    acknowledgement = {Event.ACKNOWLEDGED, Event.RECOVERED, Event.RECOVERED_OUTSIDE}
    for (state, event), transition in TRANSITIONS.items():
        if state in AWAITING_OPERATOR and transition.target not in AWAITING_OPERATOR:
            assert event in acknowledgement, (state, event)
        if transition.target in MOVING and state not in MOVING:
            assert event in (Event.CHUNK_ACCEPTED, Event.HOME_REQUESTED), (state, event)
    accepting = {state for (state, event) in TRANSITIONS if event is Event.CHUNK_ACCEPTED}
    assert accepting == {SafetyState.HOLDING, SafetyState.TRACKING}
    assert set(STATUS) == set(SafetyState) and set(STATUS.values()) == set(STATES)


def test_a_runaway_that_ends_outside_the_box_stops_streaming_and_the_acknowledgement_moves_home():
    """Streaming seeded outside the box would pull the arm back in without an acknowledgement
    (every command is kept inside): it stays stopped, and the acknowledgement's planned move
    brings it home before streaming starts again."""
    robot = FaultyRobot(position=(0.60, 0.0, 0.25))
    ctl, _, clock = make_controller(robot=robot)
    run_ticks(ctl, clock, 0.1)
    robot._pose[0, 3] += 0.12  # the arm runs 12 cm out, past the box's x = 0.64 m wall, and stays there
    motions = len(robot.motions)
    assert all(c is None for c in run_ticks(ctl, clock, 1.0)) and len(robot.motions) == motions  # nothing sent
    status = ctl.status()
    assert status.state == "awaiting_ack" and ctl.safety_state is SafetyState.STOPPED
    assert "outside the safety box" in status.reason and "moves it home first" in status.reason
    assert not ctl.submit(circle_chunk(clock.t, clock.t))
    assert "moving home first" in ctl.acknowledge() and ctl.status().state == "homing"
    run_ticks(ctl, clock, 0.1)
    assert robot.motions[motions][0] == "move_to" and ctl.status().state == "holding"
    np.testing.assert_allclose(ctl.state.ee_pose[:3, 3], ctl.config.home_position)


class SafetyStateMachine(RuleBasedStateMachine):
    """Random stops, reflexes, dropped connections, runaways, acknowledgements, chunks (good, stale,
    far-future, NaN), homings and silences through the real Controller and a fake robot behind our
    ``Robot`` interface, on a simulated clock. After every step and every tick: nothing moves while
    an operator's acknowledgement is awaited, no chunk is accepted there, only an acknowledgement
    leaves it, and the arm never moves past the watchdog's (or the glide's) deadline."""

    config = dataclasses.replace(ControlConfig(), control_hz=10.0)  # fewer ticks per simulated second

    @initialize(start=st.sampled_from(["streaming", "held", "held outside the box"]))
    def start(self, start):
        self.robot = FaultyRobot((0.55, 0.0, 0.52) if start == "held outside the box" else None)
        self.robot.connect()
        self.clock = FakeClock()
        self.ctl = Controller(self.robot, BOX, self.config, clock=self.clock)
        self.ctl.start(home=True, thread=False, hold="" if start == "streaming" else "a test start")
        self.period = int(1e9 / self.config.control_hz)
        self.motion_deadline_ns = self.clock.t  # the arm may follow a trajectory until then
        self.previous_state = self.ctl.safety_state
        self.acknowledged = False  # by the step just taken
        self.held_pose = None  # the one pose commanded while an acknowledgement is awaited

    # --- time and the robot --------------------------------------------------------------
    def tick(self):
        motions, before = len(self.robot.motions), self.ctl.safety_state
        self.clock.t += self.period
        command = self.ctl.tick()
        state = self.ctl.safety_state
        if state in AWAITING_OPERATOR:  # no motion commanded: nothing, or the one held pose again
            if before in AWAITING_OPERATOR:  # (a tick that meets a fault may have moved before it)
                assert all(kind == "target" for kind, _ in self.robot.motions[motions:])
            if command is not None:
                assert command.holding
                self.held_pose = command.target.pose if self.held_pose is None else self.held_pose
                assert np.abs(command.target.pose - self.held_pose).max() <= 1e-9, (command.target.pose, self.held_pose)
        if state in MOVING:  # the watchdog is armed: silence ends every motion
            assert self.clock.t <= self.motion_deadline_ns

    @rule(seconds=st.sampled_from([0.05, 0.3, 1.0]))
    def advance(self, seconds):
        for _ in range(round(seconds * self.config.control_hz)):
            self.tick()

    @rule()
    def silence(self):
        """Longer than any chunk here plus the watchdog's timeout."""
        self.advance(2.0)

    @rule(stop=st.sampled_from(["user stop", "reflex", "connection lost"]))
    def robot_stops(self, stop):
        if stop == "user stop":
            self.robot.press()
        elif stop == "reflex":
            self.robot.stopped = "reflex"
        else:
            self.robot.lost = True
        self.tick()  # the next tick meets it

    @rule()
    def robot_fault_that_needs_manual_recovery(self):
        self.robot.stopped, self.robot.manual = "error", True
        self.tick()

    @rule(fix=st.sampled_from(["release the user stop", "clear the manual fault"]))
    def operator_fixes_the_robot(self, fix):
        if fix == "release the user stop":
            self.robot.pressed = False
        else:
            self.robot.manual = False

    @rule(metres=st.sampled_from([0.12, 0.3]))  # 0.3: out of the box from anywhere in it
    def runaway(self, metres):
        self.robot.offset = np.array([metres, 0.0, 0.0])
        self.tick()
        self.robot.offset = np.zeros(3)
        self.advance(0.3)

    # --- chunks -------------------------------------------------------------------------
    def chunk_here(self, stamp_ns, first_step_ns, direction=1.0):
        here = self.ctl.state.ee_pose
        times = first_step_ns + np.arange(4, dtype=np.int64) * 200 * MS
        poses = np.stack([pose_at(here[:3, 3] + [0.0, direction * 0.003 * i, 0.0], base=here) for i in range(4)])
        return PoseChunk(int(stamp_ns), times, poses, np.full(4, 0.08))

    @rule(direction=st.sampled_from([-1.0, 1.0]))
    def good_chunk(self, direction):
        before = self.ctl.safety_state
        chunk = self.chunk_here(self.clock.t, self.clock.t + 100 * MS, direction)
        accepted = self.ctl.submit(chunk)
        assert accepted == (before in (SafetyState.HOLDING, SafetyState.TRACKING)), (before, self.ctl.stats)
        if accepted:
            self.motion_deadline_ns = int(chunk.times_ns[-1]) + int(self.config.safety.watchdog_timeout_s * 1e9)

    @rule()
    def chunk_then_silence(self):
        self.good_chunk(1.0)
        self.silence()

    @rule(kind=st.sampled_from(["stale", "far future", "nan"]))
    def bad_chunk(self, kind):
        before, rejected = self.ctl.safety_state, self.ctl.stats.rejected_chunks
        if kind == "stale":
            assert not self.ctl.submit(self.chunk_here(self.clock.t - 2_000 * MS, self.clock.t - 2_000 * MS))
        elif kind == "far future":
            day = 86_400_000 * MS
            assert not self.ctl.submit(self.chunk_here(self.clock.t + day, self.clock.t + day))
        else:  # never becomes a PoseChunk: franka_node records the decoder's error
            msg = chunk_to_msg(self.chunk_here(self.clock.t, self.clock.t), rosbags_factory(), "fr3_link0")
            msg.points[1].transforms[0].translation.x = float("nan")
            with pytest.raises(ChunkError) as err:
                chunk_from_msg(msg)
            self.ctl.record_rejection(err.value)
        assert self.ctl.safety_state is before and self.ctl.stats.rejected_chunks == rejected + 1

    # --- operators ------------------------------------------------------------------------
    @rule()
    def acknowledge(self):
        before = self.ctl.safety_state
        try:
            acknowledged = self.ctl.acknowledge()
        except AcknowledgeRefused:
            assert before in (SafetyState.STOPPED, SafetyState.FAULTED)
            assert self.ctl.safety_state in (SafetyState.STOPPED, SafetyState.FAULTED)
            return
        if before in AWAITING_OPERATOR:
            assert acknowledged and self.ctl.safety_state in (SafetyState.HOLDING, SafetyState.MOVING_HOME)
            self.acknowledged = True
        else:
            assert acknowledged == "" and self.ctl.safety_state is before

    @rule()
    def operator_fixes_the_robot_and_acknowledges(self):
        """Once its cause is fixed at the robot, an acknowledgement always goes on."""
        before = self.ctl.safety_state
        self.robot.pressed = self.robot.manual = False
        acknowledged = self.ctl.acknowledge()
        assert bool(acknowledged) == (before in AWAITING_OPERATOR)
        self.acknowledged = True
        assert self.ctl.safety_state not in AWAITING_OPERATOR

    @rule()
    def go_home(self):
        before = self.ctl.safety_state
        try:
            seconds = self.ctl.go_home()
        except ChunkError as err:
            assert err.reason is ChunkReason.HELD and before not in (SafetyState.HOLDING, SafetyState.TRACKING)
            return
        assert before in (SafetyState.HOLDING, SafetyState.TRACKING, SafetyState.HOMING)
        assert self.ctl.safety_state is SafetyState.HOMING
        self.motion_deadline_ns = self.clock.t + int(seconds * 1e9)

    @rule()
    def require_acknowledgement(self):
        self.ctl.require_acknowledgement("an operator must look first")
        assert self.ctl.safety_state in AWAITING_OPERATOR

    # --- after every step -------------------------------------------------------------------
    @invariant()
    def never_resumes_on_its_own(self):
        state = self.ctl.safety_state
        if self.previous_state in AWAITING_OPERATOR and state not in AWAITING_OPERATOR:
            assert self.acknowledged, (self.previous_state, state)
        if state not in AWAITING_OPERATOR:
            self.held_pose = None
        self.previous_state, self.acknowledged = state, False

    @invariant()
    def the_status_reads_the_state(self):
        state, status = self.ctl.safety_state, self.ctl.status()
        assert status.state == STATUS[state] and status.state in STATES
        assert self.ctl.holding == (state not in MOVING) and self.ctl.faulted == (state is SafetyState.FAULTED)
        if state in (SafetyState.AWAITING_ACK, SafetyState.STOPPED):
            assert self.ctl.awaiting_ack and status.reason.startswith(self.ctl.awaiting_ack)
        elif state is not SafetyState.FAULTED:
            assert self.ctl.awaiting_ack == ""
        if state in MOVING:
            assert self.clock.t <= self.motion_deadline_ns


SafetyStateMachine.TestCase.settings = settings(max_examples=80, stateful_step_count=25, deadline=None)
test_safety_state_machine = SafetyStateMachine.TestCase
