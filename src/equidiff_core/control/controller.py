"""The control loop of the franka node, ROS-free: chunks in, filtered targets out to a ``Robot``.

One thread ticks at ``control_hz`` to fixed deadlines of its ``Clock`` (the wall clock in the
lab, simulated time in the twin): read the robot state, sample the
chunk scheduler at *now*, apply the watchdog and the safety filter, stream the target to the
robot, move the gripper when its target changes. ``submit`` (called from a ROS callback)
checks a chunk and swaps the scheduler's trajectory under a lock, so callbacks never wait for
the robot.

Which state the controller is in (holding, tracking a chunk, homing, awaiting an operator's
acknowledgement, ...) and how events move it are one table, ``state_machine.TRANSITIONS``;
``_fire`` is the only place that applies it. Stops (every one leads to a state only an
acknowledgement leaves), the acknowledgement and ``go_home`` live in ``stops.HeldState``, which
``Controller`` inherits.
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
from ..config import SafetyBox
from ..robots.base import Robot, RobotError, RobotState
from ..runtime.clock import Clock, WallClock
from ..wire.chunk import ChunkError, ChunkReason, PoseChunk
from .config import ControlConfig
from .safety import FilteredTarget, SafetyFilter, check_chunk
from .scheduler import ChunkScheduler, Setpoint
from .state_machine import (
    AWAITING_OPERATOR,
    INITIAL,
    MOVING,
    NOT_STREAMING,
    STATUS,
    Action,
    Event,
    SafetyState,
    Transition,
    next_transition,
    permits,
)
from .stops import HeldState

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
    future_rejected: int = 0  # stamped further ahead than scheduler.max_future_stamp_s (or a first step too far ahead)
    malformed_rejected: int = 0  # did not decode: wrong joint names, frame, step layout, times out of order
    watchdog_holds: int = 0
    robot_stops: int = 0  # the robot stopped on its own: user stop, reflex, lost connection, robot error
    recoveries: int = 0  # acknowledged recoveries of a stopped robot
    divergence_stops: int = 0  # the arm ran away from its command: motion restarted where it was
    clipped_ticks: int = 0
    speed_limited_ticks: int = 0
    gripper_commands: int = 0
    ack_rejected: int = 0  # chunks refused while a stop awaits acknowledgement (subset of rejected_chunks)
    acknowledged: int = 0
    ack_refused: int = 0  # acknowledgements refused (user stop still pressed, recovery failed)
    last_rejection: str = ""
    last_rejection_reason: str = ""  # the last rejection's ChunkReason ("" before the first)
    last_recovery_reason: str = ""  # the robot's own text for its last stop
    last_divergence: str = ""

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass(frozen=True)
class ControllerStatus:
    """What franka_node publishes on /franka/status (``topics.TOPIC_FRANKA_STATUS``)."""

    state: str  # one of STATES
    reason: str  # why it holds, homes or faulted ("" while moving)
    last_fault: str  # the newest fault's text ("" before the first)
    last_fault_ns: int  # when, on the controller's clock (0 before the first)

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class Command:
    stamp_ns: int
    target: FilteredTarget
    holding: bool


class Controller(HeldState):
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
        # The state and the trajectory (scheduler, hold), shared with submit(); reentrant so that
        # a caller holding it can fire an event.
        self._lock = threading.RLock()
        # the robot: one tick, a stopped robot's poll or an acknowledgement's recovery at a time
        self._robot_lock = threading.RLock()
        self._state: RobotState | None = None
        self._setpoint: FilteredTarget | None = None  # the last command sent
        self.last_command: Command | None = None
        self._safety_state = INITIAL  # changed only by _fire
        self._reason = "no chunk yet"  # why the state (holding, awaiting an acknowledgement, faulted)
        self._pending_ack = ""  # what the next acknowledgement acknowledges
        self._hold_pose: np.ndarray | None = None  # what a hold holds (None: the last command)
        # The last instant the current command is valid: its trajectory's last step, or its arrival
        # for a one-step chunk already due. The watchdog counts from here, not from the arrival:
        # a chunk is a plan for its whole span (policy_node answers once per 1.6 s with 1.4 s of
        # steps), so counting from the arrival cut every chunk short.
        self._valid_until_ns: int | None = None
        self._last_tick_ns: int | None = None
        self._last_robot_time_s: float | None = None
        self._gripper_sent = float("nan")
        self._divergence_grace_until_ns = 0
        self._home_arrival_ns = 0  # HOMING: when go_home's glide arrives
        # STOPPED and FAULTED: why the robot stopped streaming: "user_stop" | "reflex" | "connection_lost" |
        # "error" (RobotStopped.kind), "divergence" (it ran away again while held), "outside" (the TCP outside
        # the box or cone: streaming may only start after the planned home move).
        self._stop_kind = ""
        self._robot_mode = ""  # a stopped robot's mode at the last poll ("unreachable" when it could not be read)
        self._next_poll_ns = 0
        self._last_fault, self._last_fault_ns = "", 0
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    # --- lifecycle -------------------------------------------------------------------------
    @property
    def home_pose(self) -> np.ndarray:
        return geometry.pose_from_pos_quat(self.config.home_position, self.config.home_quaternion_xyzw)

    def start(self, home: bool | None = None, thread: bool = True, hold: str = "") -> None:
        """Start streaming seeded at the current pose and start ticking.

        Without ``hold``: move home first (``home``, default control.yaml's ``home_on_start``);
        the TCP must then be inside the safety box and cone (else RobotError). With ``hold`` (why
        an operator must look first: franka_node after any restart) nothing moves: the arm holds
        where it is and every chunk is refused until ``acknowledge``; if the TCP is outside the box
        or cone it is not streamed to at all, and (with ``home``) the acknowledgement moves it home
        first."""
        home = home if home is not None else self.config.home_on_start
        if home:
            self._check_home_pose()
        if home and not hold:
            self.log.info(f"moving to the home pose {self.config.home_position}")
            self.robot.move_to(self.home_pose)
        pose = self.robot.read_state().ee_pose
        outside = self._outside(pose)
        if outside and not (hold and home):
            # Every command is clipped into the box, so streaming from outside would pull the
            # arm in at full speed: refuse instead of moving unexpectedly.
            raise RobotError(f"{outside}; move it inside (or enable home_on_start) before streaming")
        if outside:
            self._state = self._read_state()
            reason = f"{hold}; {outside}: the acknowledgement moves it home first"
            self._fire(Event.STARTED_OUTSIDE, reason, stop_kind="outside")
            self.log.warning(f"holding until an operator acknowledges: {reason}")
        else:
            self.robot.start_streaming()
            self._state = self._read_state()
            self._fire(Event.STARTED)
            if hold:
                self.require_acknowledgement(hold)
        if thread:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="control-loop", daemon=True)
            self._thread.start()

    def _check_home_pose(self) -> None:
        home_pose = self.home_pose
        if not self.safety.inside(home_pose[:3, 3]):
            raise ValueError(f"home position {self.config.home_position} is outside the safety box")
        if geometry.tilt_angle(home_pose[:3, :3]) > self.config.safety.max_tilt_rad:
            raise ValueError(f"home orientation {self.config.home_quaternion_xyzw} is outside the orientation cone")

    def _outside(self, pose: np.ndarray) -> str:
        """Why streaming must not start at ``pose`` ('' if it may)."""
        position = pose[:3, 3]
        if not self.safety.inside(position, tol=1e-3):
            return (
                f"the TCP is at {np.round(position, 3).tolist()}, outside the safety box "
                f"{np.round(self.safety.lower, 3).tolist()} .. {np.round(self.safety.upper, 3).tolist()}"
            )
        tilt = geometry.tilt_angle(pose[:3, :3])
        if tilt > self.config.safety.max_tilt_rad + 1e-3:  # the same: every command is swung into the cone
            return (
                f"the tool is tilted {np.degrees(tilt):.0f} deg from straight down, outside the "
                f"{np.degrees(self.config.safety.max_tilt_rad):.0f} deg cone"
            )
        return ""

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
                with self._lock:
                    if permits(self._safety_state, Event.TICK_FAILED):
                        self._fire(Event.TICK_FAILED, f"the control tick failed: {err!r}")
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
        """The arm is not following a trajectory (whatever the reason)."""
        return self._safety_state not in MOVING

    @property
    def safety_state(self) -> SafetyState:
        return self._safety_state

    @property
    def faulted(self) -> bool:
        """An acknowledged recovery failed (/diagnostics ``faulted``)."""
        return self._safety_state is SafetyState.FAULTED

    @property
    def awaiting_ack(self) -> str:
        """Why the arm holds until an operator acknowledges ("" when it does not; /diagnostics ``awaiting_ack``)."""
        return self._pending_ack if self._safety_state in AWAITING_OPERATOR else ""

    def _fire(self, event: Event, reason: str | None = None, stop_kind: str = "") -> Transition:
        """The one place the state changes: ``(state, event)`` looked up in ``TRANSITIONS``, the
        state moved on and the transition's action applied to the trajectory. ``reason`` says why
        (None: the state's reason stays); ``stop_kind`` why a state that streams nothing does not."""
        with self._lock:
            transition = next_transition(self._safety_state, event)
            target = transition.target
            self._safety_state = target
            if reason is not None:
                self._reason = reason
            if target in (SafetyState.AWAITING_ACK, SafetyState.STOPPED):
                self._pending_ack = self._reason
            elif target is not SafetyState.FAULTED:  # faulted: the acknowledgement still acknowledges the stop
                self._pending_ack = ""
            if stop_kind:
                self._stop_kind = stop_kind
            self._act(transition.action)
        return transition

    def _act(self, action: Action) -> None:
        """What a transition does to the commanded trajectory (called by ``_fire``, under the lock)."""
        if action is Action.NONE:
            return
        self._hold_pose = None
        if action is Action.FOLLOW:
            return
        self.scheduler.clear()
        if action is Action.HOLD_MEASURED:
            self._hold_pose = self._state.ee_pose.copy()
        elif action is Action.HOLD_HOME:
            self._hold_pose = self.home_pose
        elif action is Action.RESEED:  # the caller has just read the measured state
            self._setpoint = FilteredTarget(self._state.ee_pose, np.zeros(3), np.zeros(3), False, False)
            self._last_robot_time_s = None  # the robot's clock may have restarted (a new connection)

    def _held_text(self) -> str:
        """Why chunks and go_home are refused in a state only an acknowledgement leaves (or while moving home)."""
        if self._safety_state is SafetyState.MOVING_HOME:
            return "the TCP was outside: the robot's planned move home runs first"
        return self._pending_ack or self._reason

    def submit(self, chunk: PoseChunk) -> bool:
        """Check ``chunk`` and make it the trajectory to follow; False (and a warning) if rejected."""
        now = self.clock.now_ns()
        try:
            with self._lock:
                if self._safety_state is SafetyState.HOMING:
                    raise ChunkError(
                        f"homing: chunks are refused for {max(0, self._home_arrival_ns - now) / 1e9:.1f} s more",
                        ChunkReason.HELD,
                    )
                if not permits(self._safety_state, Event.CHUNK_ACCEPTED):
                    self.stats.ack_rejected += 1
                    raise ChunkError(
                        f"awaiting an operator's acknowledgement after: {self._held_text()} "
                        f"(franka_node's /franka/acknowledge, `equidiff lab ack`)",
                        ChunkReason.HELD,
                    )
                live = self.scheduler.live_steps(chunk, now)
                state = self._state
                check_chunk(live, None if state is None else state.ee_pose, self.config.safety)
                current = self._current_setpoint(now)
                self.scheduler.schedule(live, now, current)
                # Counted from the receipt: a stamp ahead of our clock (within max_future_stamp_s)
                # must not stretch the time until the watchdog holds the arm.
                ahead = max(0, int(chunk.stamp_ns) - now)
                self._valid_until_ns = max(now, (self.scheduler.end_ns() or now) - ahead)
                self._fire(Event.CHUNK_ACCEPTED)
            self.stats.accepted_chunks += 1
            return True
        except ChunkError as err:
            self.record_rejection(err)
            return False

    def record_rejection(self, err: ChunkError) -> None:
        """Count a chunk that never became a PoseChunk (decode failed) or failed the checks, by its reason."""
        text = str(err)
        reason = getattr(err, "reason", ChunkReason.MALFORMED)
        self.stats.rejected_chunks += 1
        counter = {
            ChunkReason.NAN: "nan_rejected",
            ChunkReason.STALE: "stale_rejected",
            ChunkReason.FUTURE: "future_rejected",
            ChunkReason.JUMP: "jump_rejected",
            ChunkReason.CONE: "cone_rejected",
            ChunkReason.MALFORMED: "malformed_rejected",
        }.get(reason)  # HELD: counted as ack_rejected where it is raised
        if counter is not None:
            setattr(self.stats, counter, getattr(self.stats, counter) + 1)
        self.stats.last_rejection = text
        self.stats.last_rejection_reason = str(reason)
        self._fire(Event.CHUNK_REJECTED)
        self.log.warning(f"rejected chunk: {text}; holding the current trajectory")

    # --- what an operator sees -------------------------------------------------------------
    def status(self) -> ControllerStatus:
        """The operator's view (franka_node's /franka/status): moving, holding, homing, awaiting_ack, faulted."""
        with self._lock:
            state, reason = self._safety_state, self._reason
            if state is SafetyState.TRACKING:
                reason = ""
            elif state is SafetyState.HOMING:
                reason = f"gliding home, {max(0, self._home_arrival_ns - self.clock.now_ns()) / 1e9:.1f} s to go"
            elif state is SafetyState.MOVING_HOME:
                reason = "moving home (the robot's planned move) before streaming: the TCP was outside"
            elif state is SafetyState.STOPPED:
                reason += self._stopped_detail()
        return ControllerStatus(STATUS[state], reason, self._last_fault, self._last_fault_ns)

    def _stopped_detail(self) -> str:
        if self._stop_kind == "user_stop":
            if self._robot_mode == "user_stopped":
                return " (the user stop is still pressed: release it, then acknowledge)"
            if self._robot_mode and self._robot_mode != "unreachable":
                return " (the user stop is released: acknowledge to go on)"
        if self._stop_kind == "connection_lost" or self._robot_mode == "unreachable":
            return " (the robot cannot be read: the acknowledgement connects again)"
        return ""

    def record_fault(self, text: str) -> None:
        """Note ``text`` as the newest fault (``status().last_fault``), e.g. an unclean exit found at start."""
        self._last_fault, self._last_fault_ns = text, self.clock.now_ns()

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
        moving = self._safety_state in MOVING
        if moving and self._last_tick_ns is not None:
            elapsed = float(np.clip((now_ns - self._last_tick_ns) / 1e9, 0.0, 1.0 / self.config.control_hz))
            pose = geometry.make_pose(
                Rotation.from_rotvec(sp.angular_velocity * elapsed).as_matrix() @ sp.pose[:3, :3],
                sp.pose[:3, 3] + sp.linear_velocity * elapsed,
            )
        return Setpoint(pose, sp.linear_velocity, sp.angular_velocity, float("nan"), moving)

    def _read_state(self) -> RobotState:
        """The robot's state stamped on the controller's clock (simulated time in the twin)."""
        return dataclasses.replace(self.robot.read_state(), stamp_ns=self.clock.now_ns())

    def tick(self) -> Command | None:
        with self._robot_lock:
            return self._tick()

    def _tick(self) -> Command | None:
        now = self.clock.now_ns()
        if self._safety_state in NOT_STREAMING:
            self._while_stopped(now)
            return None
        try:
            self._state = self._read_state()
        except RobotError as err:
            self._robot_stopped(err)
            return None
        diverged = self._divergence(now)
        if diverged:
            self._stop_diverged(now, diverged)
            return None
        dt = self._tick_dt(now)
        with self._lock:
            if self._safety_state is SafetyState.HOMING and now >= self._home_arrival_ns:
                self._fire(Event.HOME_REACHED, "at home")
            elif self._safety_state is SafetyState.TRACKING and (
                now - self._valid_until_ns > self.config.safety.watchdog_timeout_s * 1e9
            ):
                # Hold where the arm *is* (not where the setpoint had got to, ~0.1 s ahead of a
                # moving arm): stopping there takes the shortest way.
                timeout = self.config.safety.watchdog_timeout_s
                self._fire(
                    Event.WATCHDOG_EXPIRED, f"watchdog: no new chunk within {timeout} s of the last one's final step"
                )
                self.stats.watchdog_holds += 1
                self.log.warning(
                    f"no new command for {timeout} s after the last one's final step: holding the current pose"
                )
            moving = self._safety_state in MOVING
            homing = self._safety_state is SafetyState.HOMING
            sp = self.scheduler.sample(now) if moving else None
            previous = self._setpoint
            hold_pose = self._hold_pose
        if sp is None:
            filtered = self.safety.filter(previous.pose, previous.pose if hold_pose is None else hold_pose, dt)
        else:
            filtered = self.safety.filter(previous.pose, sp.pose, dt, sp.linear_velocity, sp.angular_velocity)
        try:
            self.robot.stream_target(filtered.pose, filtered.linear_velocity, filtered.angular_velocity)
        except RobotError as err:
            self._robot_stopped(err)
            return None
        self._setpoint = filtered
        self.stats.ticks += 1
        self.stats.clipped_ticks += int(filtered.clipped)
        self.stats.speed_limited_ticks += int(filtered.speed_limited)
        if sp is not None and np.isfinite(sp.width) and not homing:  # go_home leaves the gripper alone
            width = self.safety.clip_width(sp.width)
            if not abs(width - self._gripper_sent) <= self.config.gripper_deadband_m:  # NaN-safe
                self.robot.move_gripper(width)
                self._gripper_sent = width
                self.stats.gripper_commands += 1
        command = Command(now, filtered, not moving)
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
