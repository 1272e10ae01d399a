"""The control loop of the franka node, ROS-free: chunks in, filtered targets out to a ``Robot``.

One thread ticks at ``control_hz`` to fixed deadlines of its ``Clock`` (the wall clock in the
lab, simulated time in the twin): read the robot state, sample the
chunk scheduler at *now*, apply the watchdog and the safety filter, stream the target to the
robot, move the gripper when its target changes. ``submit`` (called from a ROS callback)
checks a chunk and swaps the scheduler's trajectory under a lock, so callbacks never wait for
the robot. Errors reported by the robot trigger ``recover`` with a logged reason, at most
``max_recoveries`` times in a row; after that the controller stays faulted and holds nothing
(the robot's own brakes/reflexes take over) until restarted.

It never resumes on its own: after a recovered robot error, a divergence stop (tracking error,
joint speed, a joint moving into its position limit) or ``require_acknowledgement`` (franka_node
after an unclean exit of its predecessor) the arm holds where it is and every chunk is refused
("awaiting acknowledgement") until an operator calls ``acknowledge`` (franka_node's
``/franka/acknowledge`` service, ``equidiff lab ack``). ``go_home`` glides to the home pose
through the same filter (``/franka/home``).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .. import geometry
from ..chunk import ChunkError, PoseChunk
from ..clock import Clock, WallClock
from ..config import SafetyBox
from ..robots.base import Robot, RobotError, RobotState
from .config import ControlConfig
from .safety import FilteredTarget, SafetyFilter, SafetyRejection, check_chunk
from .scheduler import ChunkScheduler, Setpoint

log = logging.getLogger("equidiff.control")


@dataclass
class ControllerStats:
    ticks: int = 0
    overruns: int = 0  # ticks that started more than one period late
    accepted_chunks: int = 0
    rejected_chunks: int = 0
    nan_rejected: int = 0  # NaN / inf / non-orthonormal (subset of rejected_chunks)
    jump_rejected: int = 0
    cone_rejected: int = 0  # a step tilted past the orientation cone
    stale_rejected: int = 0
    watchdog_holds: int = 0
    recoveries: int = 0
    divergence_stops: int = 0  # the arm ran away from its command: motion restarted where it was
    clipped_ticks: int = 0
    speed_limited_ticks: int = 0
    gripper_commands: int = 0
    faulted: bool = False
    awaiting_ack: str = ""  # why the arm holds until an operator acknowledges ("" when it does not)
    ack_rejected: int = 0  # chunks refused while awaiting acknowledgement (subset of rejected_chunks)
    acknowledged: int = 0
    last_rejection: str = ""
    last_recovery_reason: str = ""
    last_divergence: str = ""

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass(frozen=True)
class Command:
    stamp_ns: int
    target: FilteredTarget
    holding: bool


class Controller:
    def __init__(
        self,
        robot: Robot,
        box: SafetyBox,
        config: ControlConfig = ControlConfig(),
        clock: Clock | None = None,
        logger: logging.Logger | None = None,
        on_command: Callable[[Command], None] | None = None,
    ):
        self.robot = robot
        self.config = config
        self.clock = clock or WallClock()
        self.log = logger or log
        self.on_command = on_command
        self.safety = SafetyFilter(box, config.safety)
        self.scheduler = ChunkScheduler(config.scheduler)
        self.stats = ControllerStats()
        self._lock = threading.Lock()
        self._state: RobotState | None = None
        self._setpoint: FilteredTarget | None = None  # the last command sent
        self.last_command: Command | None = None
        self._hold_pose: np.ndarray | None = None  # watchdog target (None: hold the last command)
        # The last instant the current command is valid: its trajectory's last step, or its arrival
        # for a one-step chunk already due. The watchdog counts from here, not from the arrival:
        # a chunk is a plan for its whole span (policy_node answers once per 1.6 s with 1.4 s of
        # steps), so counting from the arrival cut every chunk short.
        self._valid_until_ns: int | None = None
        self._holding = True
        self._last_tick_ns: int | None = None
        self._last_robot_time_s: float | None = None
        self._gripper_sent = float("nan")
        self._failures_in_row = 0  # failures since the last acknowledgement
        self._divergence_grace_until_ns = 0
        self._homing_until_ns = 0  # go_home's trajectory runs until then: chunks are refused
        self._homing = False  # the trajectory is go_home's (until the next chunk): the gripper is left alone
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    # --- lifecycle -------------------------------------------------------------------------
    @property
    def home_pose(self) -> np.ndarray:
        return geometry.pose_from_pos_quat(self.config.home_position, self.config.home_quaternion_xyzw)

    def start(self, home: bool | None = None, thread: bool = True) -> None:
        """Move home (if configured), start streaming seeded at the current pose, start ticking."""
        if home if home is not None else self.config.home_on_start:
            home_pose = self.home_pose
            if not self.safety.inside(home_pose[:3, 3]):
                raise ValueError(f"home position {self.config.home_position} is outside the safety box")
            if geometry.tilt_angle(home_pose[:3, :3]) > self.config.safety.max_tilt_rad:
                raise ValueError(f"home orientation {self.config.home_quaternion_xyzw} is outside the orientation cone")
            self.log.info(f"moving to the home pose {self.config.home_position}")
            self.robot.move_to(home_pose)
        pose = self.robot.read_state().ee_pose
        position = pose[:3, 3]
        if not self.safety.inside(position, tol=1e-3):
            # Every command is clipped into the box, so streaming from outside would pull the
            # arm in at full speed: refuse instead of moving unexpectedly.
            raise RobotError(
                f"the TCP is at {np.round(position, 3).tolist()}, outside the safety box "
                f"{np.round(self.safety.lower, 3).tolist()} .. {np.round(self.safety.upper, 3).tolist()}; "
                f"move it inside (or enable home_on_start) before streaming"
            )
        tilt = geometry.tilt_angle(pose[:3, :3])
        if tilt > self.config.safety.max_tilt_rad + 1e-3:  # the same: every command is swung into the cone
            raise RobotError(
                f"the tool is tilted {np.degrees(tilt):.0f} deg from straight down, outside the "
                f"{np.degrees(self.config.safety.max_tilt_rad):.0f} deg cone; point it down "
                f"(or enable home_on_start) before streaming"
            )
        self.robot.start_streaming()
        self._reset_to_measured()
        if thread:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="control-loop", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        try:
            self.robot.stop_streaming()
        except RobotError as err:
            self.log.warning(f"stopping the robot: {err}")

    def _run(self) -> None:
        period_ns = int(1e9 / self.config.control_hz)
        deadline = self.clock.now_ns()
        while not self._stop.is_set():
            try:
                self.tick()
            except Exception as err:  # noqa: BLE001 - keep the loop alive; a bug here must not leave the arm streaming stale targets
                self.log.error(f"control tick failed: {err!r}")
                self._holding = True
            deadline += period_ns
            if self.clock.now_ns() - deadline > period_ns:
                self.stats.overruns += 1
                deadline = self.clock.now_ns()
            elif not self.clock.sleep_until(deadline, self._stop):
                return

    # --- inputs ------------------------------------------------------------------------------
    @property
    def state(self) -> RobotState | None:
        return self._state

    @property
    def holding(self) -> bool:
        return self._holding

    def submit(self, chunk: PoseChunk) -> bool:
        """Check ``chunk`` and make it the trajectory to follow; False (and a warning) if rejected."""
        now = self.clock.now_ns()
        try:
            with self._lock:
                if self.stats.awaiting_ack:
                    self.stats.ack_rejected += 1
                    raise ChunkError(
                        f"awaiting an operator's acknowledgement after: {self.stats.awaiting_ack} "
                        f"(franka_node's /franka/acknowledge, `equidiff lab ack`)"
                    )
                if now < self._homing_until_ns:
                    raise ChunkError(f"homing: chunks are refused for {(self._homing_until_ns - now) / 1e9:.1f} s more")
                live = self.scheduler.live_steps(chunk, now)
                state = self._state
                check_chunk(live, None if state is None else state.ee_pose, self.config.safety)
                current = self._current_setpoint(now)
                self.scheduler.schedule(live, now, current)
                self._valid_until_ns = max(now, self.scheduler.end_ns() or now)
                self._holding = False
                self._hold_pose = None
                self._homing = False
            self.stats.accepted_chunks += 1
            return True
        except ChunkError as err:
            self.record_rejection(err)
            return False

    def record_rejection(self, err: ChunkError) -> None:
        """Count a chunk that never became a PoseChunk (decode failed) or failed the checks."""
        text = str(err)
        self.stats.rejected_chunks += 1
        if isinstance(err, SafetyRejection):
            if err.kind == "cone":
                self.stats.cone_rejected += 1
            else:
                self.stats.jump_rejected += 1
        elif "stale" in text:
            self.stats.stale_rejected += 1
        elif any(word in text for word in ("NaN", "inf", "orthonormal", "unit length", "determinant")):
            self.stats.nan_rejected += 1
        self.stats.last_rejection = text
        self.log.warning(f"rejected chunk: {text}; holding the current trajectory")

    # --- the tick ------------------------------------------------------------------------
    def _current_setpoint(self, now_ns: int) -> Setpoint:
        """Where the command is at ``now_ns``: the last one sent, moved on by its twist for the
        time since its tick (at most a period). A new trajectory starting from the last command
        itself stood still for one tick at every chunk switch."""
        sp = self._setpoint
        if sp is None:
            pose = self._state.ee_pose if self._state is not None else self.robot.read_state().ee_pose
            return Setpoint(pose, np.zeros(3), np.zeros(3), float("nan"), False)
        pose = sp.pose
        if not self._holding and self._last_tick_ns is not None:
            elapsed = float(np.clip((now_ns - self._last_tick_ns) / 1e9, 0.0, 1.0 / self.config.control_hz))
            pose = geometry.make_pose(
                Rotation.from_rotvec(sp.angular_velocity * elapsed).as_matrix() @ sp.pose[:3, :3],
                sp.pose[:3, 3] + sp.linear_velocity * elapsed,
            )
        return Setpoint(pose, sp.linear_velocity, sp.angular_velocity, float("nan"), not self._holding)

    def _reset_to_measured(self) -> None:
        state = self._read_state()
        self._state = state
        with self._lock:
            self.scheduler.clear()
            self._holding = True
            self._hold_pose = None
            self._setpoint = FilteredTarget(state.ee_pose, np.zeros(3), np.zeros(3), False, False)

    def _read_state(self) -> RobotState:
        """The robot's state stamped on the controller's clock (simulated time in the twin)."""
        return dataclasses.replace(self.robot.read_state(), stamp_ns=self.clock.now_ns())

    def tick(self) -> Command | None:
        now = self.clock.now_ns()
        if self.stats.faulted:
            return None
        self._state = self._read_state()
        diverged = self._divergence(now)
        if diverged:
            self._stop_diverged(now, diverged)
            return None
        dt = self._tick_dt(now)
        with self._lock:
            if (
                not self._holding
                and self._valid_until_ns is not None
                and now - self._valid_until_ns > self.config.safety.watchdog_timeout_s * 1e9
            ):
                # Hold where the arm *is* (not where the setpoint had got to, ~0.1 s ahead of a
                # moving arm): stopping there takes the shortest way.
                self.scheduler.clear()
                self._holding = True
                self._hold_pose = self._state.ee_pose.copy()
                self.stats.watchdog_holds += 1
                self.log.warning(
                    f"no new command for {self.config.safety.watchdog_timeout_s} s after the last "
                    f"one's final step: holding the current pose"
                )
            sp = None if self._holding else self.scheduler.sample(now)
            previous = self._setpoint
            hold_pose = self._hold_pose
        if sp is None:
            filtered = self.safety.filter(previous.pose, previous.pose if hold_pose is None else hold_pose, dt)
        else:
            filtered = self.safety.filter(previous.pose, sp.pose, dt, sp.linear_velocity, sp.angular_velocity)
        try:
            self.robot.stream_target(filtered.pose, filtered.linear_velocity, filtered.angular_velocity)
        except RobotError as err:
            self._handle_failure(now, err)
            return None
        self._setpoint = filtered
        self.stats.ticks += 1
        self.stats.clipped_ticks += int(filtered.clipped)
        self.stats.speed_limited_ticks += int(filtered.speed_limited)
        if sp is not None and np.isfinite(sp.width) and not self._homing:
            width = self.safety.clip_width(sp.width)
            if not abs(width - self._gripper_sent) <= self.config.gripper_deadband_m:  # NaN-safe
                self.robot.move_gripper(width)
                self._gripper_sent = width
                self.stats.gripper_commands += 1
        command = Command(now, filtered, self._holding)
        self.last_command = command
        if self.on_command is not None:
            self.on_command(command)
        return command

    def _tick_dt(self, now: int) -> float:
        """Seconds since the last tick on the robot's own clock when it has one, else on ours.

        The speed limits apply in the robot's time: a twin running slower than real time (every
        process on two cores: 0.4-0.5x) was otherwise commanded 2x too fast for its arm, lagged
        up to 8 cm behind the command, and the 3000 N/m spring then whipped it at 3 rad/s. On a
        real FR3 both clocks run together and nothing changes."""
        period = 1.0 / self.config.control_hz
        robot_now = self._state.robot_time_s
        if np.isfinite(robot_now) and self._last_robot_time_s is not None:
            dt, low = robot_now - self._last_robot_time_s, 1e-4  # robot time stands still while the robot stalls
        else:
            dt, low = (period if self._last_tick_ns is None else (now - self._last_tick_ns) / 1e9), 0.5 * period
        self._last_tick_ns, self._last_robot_time_s = now, robot_now if np.isfinite(robot_now) else None
        return float(np.clip(dt, low, 3 * period))

    def _divergence(self, now: int) -> str:
        """Why the arm is running away from its command ('' when it is not, or while it brakes after a stop)."""
        if self._setpoint is None or now < self._divergence_grace_until_ns:
            return ""
        limits = self.config.safety
        error = float(np.linalg.norm(self._state.ee_pose[:3, 3] - self._setpoint.pose[:3, 3]))
        if error > limits.max_tracking_error_m:
            return f"TCP {error * 1000:.0f} mm from the command (limit {limits.max_tracking_error_m * 1000:.0f} mm)"
        velocities = np.asarray(self._state.joint_velocities, dtype=float)
        speeds = np.abs(velocities)
        over = speeds - np.asarray(limits.max_joint_speeds_rad_s)[: len(speeds)]
        if over.size and over.max() > 0:
            j = int(np.argmax(over))
            return f"joint {j + 1} at {speeds[j]:.1f} rad/s (limit {limits.max_joint_speeds_rad_s[j]:.1f} rad/s)"
        return self._joint_limit_reached(np.asarray(self._state.joint_positions, dtype=float), velocities)

    def _joint_limit_reached(self, q: np.ndarray, dq: np.ndarray) -> str:
        """A joint within ``joint_limit_margin_rad`` of a position limit and still moving towards it
        ('' otherwise). Moving away is allowed, so the arm can be brought back after the stop."""
        limits, moving = self.config.safety, 0.05  # rad/s: slower is holding still (sensor noise, drift)
        lo = np.asarray(limits.joint_position_min_rad)[: len(q)] + limits.joint_limit_margin_rad
        hi = np.asarray(limits.joint_position_max_rad)[: len(q)] - limits.joint_limit_margin_rad
        for j in range(len(q)):
            if (q[j] < lo[j] and dq[j] < -moving) or (q[j] > hi[j] and dq[j] > moving):
                return (
                    f"joint {j + 1} at {q[j]:.2f} rad moving towards its limit "
                    f"[{limits.joint_position_min_rad[j]:.2f}, {limits.joint_position_max_rad[j]:.2f}] rad"
                )
        return ""

    def _stop_diverged(self, now: int, reason: str) -> None:
        """Stop the motion, restart it seeded where the arm is and hold there (the arm brakes meanwhile)."""
        self.stats.divergence_stops += 1
        self.stats.last_divergence = reason
        self._divergence_grace_until_ns = now + int(1e9)
        if not self._count_failure(f"the arm diverged from its command again ({reason})"):
            return
        self.log.error(
            f"the arm diverged from its command ({reason}): stopping the motion and holding where it "
            f"is until an operator acknowledges"
        )
        try:
            self.robot.stop_streaming()
            self.robot.start_streaming()
        except RobotError as err:
            self._handle_failure(now, err)
            return
        self._reset_to_measured()
        self.stats.awaiting_ack = f"divergence stop: {reason}"

    def _count_failure(self, what: str) -> bool:
        """Count a failure; past ``max_recoveries`` since the last acknowledgement the node faults
        (False): nothing more is sent."""
        self._failures_in_row += 1
        limit = self.config.franky.max_recoveries
        if self._failures_in_row > limit:
            self.stats.faulted = True
            self.log.error(
                f"{what} after {limit} recoveries in a row: giving up; restart the node once the cause is fixed"
            )
            return False
        return True

    def _handle_failure(self, now: int, err: Exception) -> None:
        if not self._count_failure(f"robot error '{err}'"):
            return
        limit = self.config.franky.max_recoveries
        try:
            reason = self.robot.recover()
        except RobotError as rec_err:
            self.log.error(f"recovery {self._failures_in_row}/{limit} failed: {rec_err}")
            return
        self.stats.recoveries += 1
        self.stats.last_recovery_reason = reason
        self.log.warning(
            f"robot error ({reason}); recovered ({self._failures_in_row}/{limit}), holding until "
            f"an operator acknowledges"
        )
        self._reset_to_measured()
        self.stats.awaiting_ack = f"robot error: {reason}"

    def go_home(self) -> float:
        """Glide to the configured home pose at ``home_speed_m_s`` / ``home_angular_speed_rad_s``
        through the ordinary safety filter (box, cone, speed limits, watchdog), the gripper left as
        it is; chunks are refused until it arrives. Returns the glide's duration (s). Raises
        ChunkError while a stop awaits acknowledgement or the controller is faulted: an operator
        looks at the arm first."""
        from scipy.spatial.transform import Rotation, Slerp

        if self.stats.faulted:
            raise ChunkError("faulted: restart franka_node once the cause is fixed")
        now = self.clock.now_ns()
        with self._lock:
            if self.stats.awaiting_ack:
                raise ChunkError(f"awaiting an operator's acknowledgement after: {self.stats.awaiting_ack}")
            start = (self._state or self._read_state()).ee_pose
            goal, cfg = self.home_pose, self.config
            distance = float(np.linalg.norm(goal[:3, 3] - start[:3, 3]))
            angle = geometry.rotation_angle(start[:3, :3], goal[:3, :3])
            duration = max(distance / cfg.home_speed_m_s, angle / cfg.home_angular_speed_rad_s, 0.5)
            s = np.linspace(0.0, 1.0, int(np.ceil(duration / 0.1)) + 1)
            rotations = Slerp([0.0, 1.0], Rotation.from_matrix([start[:3, :3], goal[:3, :3]]))(s).as_matrix()
            poses = np.stack(
                [geometry.make_pose(R, (1 - a) * start[:3, 3] + a * goal[:3, 3]) for a, R in zip(s, rotations)]
            )
            times = now + (s * duration * 1e9).astype(np.int64)
            chunk = PoseChunk(now, times, poses, np.zeros(len(s)))  # widths unused: no gripper command while homing
            self.scheduler.schedule(chunk, now, self._current_setpoint(now))
            self._valid_until_ns = int(times[-1])
            self._homing_until_ns = int(times[-1])
            self._homing = True
            self._holding = False
            self._hold_pose = None
        self.log.info(
            f"homing: {distance * 1000:.0f} mm and {np.degrees(angle):.0f} deg to {cfg.home_position} "
            f"in {duration:.1f} s"
        )
        return duration

    def require_acknowledgement(self, reason: str) -> None:
        """Hold and refuse every chunk until an operator acknowledges ``reason`` (franka_node calls
        it when it starts after an unclean exit: the policy may still be publishing)."""
        with self._lock:
            self.stats.awaiting_ack = reason
            self.scheduler.clear()
            self._holding = True
        self.log.warning(f"holding until an operator acknowledges: {reason}")

    def acknowledge(self) -> str:
        """An operator's go-ahead after a stop: chunks are accepted again (the arm keeps holding
        until the next one) and the count of failures in a row starts over. Returns what was
        acknowledged ("" when nothing was awaiting acknowledgement); a faulted controller stays
        faulted (restart the node)."""
        with self._lock:
            reason, self.stats.awaiting_ack = self.stats.awaiting_ack, ""
            if reason:
                self._failures_in_row = 0
                self.stats.acknowledged += 1
        if reason:
            self.log.warning(f"acknowledged: {reason}; accepting chunks again")
        return reason
