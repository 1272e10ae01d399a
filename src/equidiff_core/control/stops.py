"""The controller's stops, the acknowledgement that ends them, and going home.

Every method here raises events (``state_machine.Event``) through ``Controller._fire``; none
sets a state. The states and transitions named below are ``state_machine.TRANSITIONS``.

**One held state for every stop.** A user stop, a reflex, a lost connection or any other
robot error (``RobotStopped`` from the backend), a divergence stop (tracking error, joint
speed, a joint moving into its position limit) and a held start (``start(hold=...)``: franka_node
after any restart) all lead to a state only an acknowledgement leaves (``AWAITING_ACK`` while
streaming goes on, ``STOPPED`` while it does not): the arm holds (the robot holds itself while it
is stopped), every chunk is refused and ``status()`` says ``awaiting_ack`` with the reason. No
failing tick is counted and nothing is retried: while the robot is stopped the loop only polls
its state at ``STOPPED_POLL_HZ`` (is the user stop still pressed?). ``acknowledge`` (franka_node's
``/franka/acknowledge``, ``equidiff lab ack``) is the only way on: it is refused while the user
stop is pressed; otherwise it recovers the robot (reconnecting after a lost connection),
restarts streaming where the arm is and holds; chunks are accepted again. A fault after that
holds again. If the arm is outside the safety box or cone at that moment, streaming cannot
start there (every command is clipped into the box): the acknowledgement then moves it home
with the robot's own planned move first (``MOVING_HOME``, ``homing`` on the status).

``FAULTED`` means an acknowledged recovery failed: the robot refused it (e.g. "manual error
recovery required": a joint past its limit, to be guided out in Desk), could not be reached,
or would not start streaming. Nothing is sent; once the cause is fixed at the robot, another
acknowledgement retries. A restart of franka_node is never needed.

``go_home`` glides to the home pose through the same filter (``/franka/home``).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from .. import geometry
from ..robots.base import STOP_KINDS, RobotError, RobotStopped, UserStopPressed
from ..wire.chunk import ChunkError, ChunkReason, PoseChunk
from .state_machine import Event, SafetyState, permits

# How often a stopped robot's state is read (the user stop released? the arm's pose for the
# topics): often enough for an operator, rare enough to leave the robot's link alone.
STOPPED_POLL_HZ = 10.0
# After a divergence stop or a recovery the arm may still move while it brakes: no new divergence stop meanwhile.
DIVERGENCE_GRACE_S = 1.0


class AcknowledgeRefused(RuntimeError):
    """The acknowledgement could not be granted (the user stop is pressed, or recovery failed)."""


class HeldState:
    """Stops, acknowledgement and homing of ``controller.Controller``, kept apart from its streaming loop.

    A mixin: it works on what ``Controller.__init__`` sets up (robot, locks, scheduler, stats, the
    stopped robot's ``_stop_kind`` / ``_robot_mode`` / ``_next_poll_ns``) and calls its helpers
    (``_fire``, ``_held_text``, ``_read_state``, ``_current_setpoint``, ``_outside``, ``record_fault``)."""

    # --- stops -----------------------------------------------------------------------------
    def _robot_stopped(self, err: RobotError) -> None:
        """The robot ended the motion on its own: hold (it holds itself) and wait for an operator.
        Nothing is retried: the loop only polls the robot's state from now on."""
        kind = err.kind if isinstance(err, RobotStopped) else "error"
        reason = err.reason if isinstance(err, RobotStopped) else str(err)
        text = f"{STOP_KINDS[kind]}: {reason}"
        self._robot_mode, self._next_poll_ns = "", 0
        self.stats.robot_stops += 1
        self.stats.last_recovery_reason = reason
        self.record_fault(text)
        self._fire(Event.ROBOT_STOPPED, text, stop_kind=kind)
        self.log.error(f"{text}: the robot stopped; holding until an operator acknowledges (`equidiff lab ack`)")

    def _while_stopped(self, now: int) -> None:
        """A stopped robot: read its state now and then (for the topics, and whether the user stop
        is still pressed); after an acknowledgement with the TCP outside, move it home."""
        if self._safety_state is SafetyState.MOVING_HOME:
            self._home_then_stream()
            return
        if now < self._next_poll_ns or self._stop_kind == "connection_lost":
            return  # a dead connection has nothing to read: the acknowledgement connects again
        self._next_poll_ns = now + int(1e9 / STOPPED_POLL_HZ)
        try:
            self._state = self._read_state()
            self._robot_mode = self._state.mode
        except RobotError:
            self._robot_mode = "unreachable"

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
        """Stop the motion, restart it seeded where the arm is and hold there (the arm brakes
        meanwhile). Where the arm ended outside the box or cone streaming is not restarted (it
        would pull the arm back in): the acknowledgement moves it home first. If it runs away
        again while already holding for an operator, streaming stays stopped (the robot holds
        itself) until the acknowledgement restarts it."""
        self.stats.divergence_stops += 1
        self.stats.last_divergence = reason
        self._divergence_grace_until_ns = now + int(DIVERGENCE_GRACE_S * 1e9)
        again = self._safety_state is SafetyState.AWAITING_ACK
        text = f"divergence stop: {reason}"
        self.record_fault(text)
        outside = ""
        try:
            self.robot.stop_streaming()
            if not again:
                self._state = self._read_state()  # the restarted motion holds here
                outside = self._outside(self._state.ee_pose)
                if not outside:
                    self.robot.start_streaming()
        except RobotError as err:
            self._robot_stopped(err)
            return
        if outside:
            self._robot_mode = ""
            self._fire(
                Event.DIVERGED_OUTSIDE,
                f"{text}; {outside}: the acknowledgement moves it home first",
                stop_kind="outside",
            )
            self.log.error(f"the arm diverged from its command ({reason}) and {outside}: streaming stopped")
            return
        if again:
            self._robot_mode = ""
            self._fire(Event.DIVERGED, f"{text} (again while holding: streaming stopped)", stop_kind="divergence")
            self.log.error(f"the arm diverged from its command again while holding ({reason}): streaming stopped")
            return
        self.log.error(
            f"the arm diverged from its command ({reason}): stopping the motion and holding where it "
            f"is until an operator acknowledges"
        )
        self._fire(Event.DIVERGED, text)

    # --- operator actions ------------------------------------------------------------------
    def go_home(self) -> float:
        """Glide to the configured home pose at ``home_speed_m_s`` / ``home_angular_speed_rad_s``
        through the ordinary safety filter (box, cone, speed limits, watchdog), the gripper left as
        it is; chunks are refused until it arrives. Returns the glide's duration (s). Raises
        ChunkError while a stop awaits acknowledgement or the controller is faulted: an operator
        looks at the arm first."""
        now = self.clock.now_ns()
        with self._lock:
            if not permits(self._safety_state, Event.HOME_REQUESTED):
                raise ChunkError(f"awaiting an operator's acknowledgement after: {self._held_text()}", ChunkReason.HELD)
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
            self._valid_until_ns = self._home_arrival_ns = int(times[-1])
            self._fire(Event.HOME_REQUESTED)
        self.log.info(
            f"homing: {distance * 1000:.0f} mm and {np.degrees(angle):.0f} deg to {cfg.home_position} "
            f"in {duration:.1f} s"
        )
        return duration

    def require_acknowledgement(self, reason: str) -> None:
        """Hold and refuse every chunk until an operator acknowledges ``reason`` (faulted: it awaits one already).
        Waits for a move home in progress, which then waits for the acknowledgement too."""
        with self._robot_lock, self._lock:
            if not permits(self._safety_state, Event.HOLD_REQUESTED):
                return
            self._fire(Event.HOLD_REQUESTED, reason)
        self.log.warning(f"holding until an operator acknowledges: {reason}")

    def acknowledge(self) -> str:
        """An operator's go-ahead after a stop. Returns what was acknowledged ("" when nothing
        awaited it). A stopped robot is recovered first (see the module docstring); raises
        AcknowledgeRefused while its user stop is pressed or when recovery fails (``faulted``).
        The arm holds afterwards, until the next chunk (or moves home first if it is outside)."""
        with self._robot_lock:
            state = self._safety_state
            reason = self._pending_ack or self._reason
            if state is SafetyState.AWAITING_ACK:
                done = ""
                self._fire(Event.ACKNOWLEDGED, "acknowledged: waiting for a chunk")
            elif state in (SafetyState.STOPPED, SafetyState.FAULTED):
                try:
                    done = self._recover()
                except AcknowledgeRefused:
                    self.stats.ack_refused += 1
                    raise
            else:
                return ""
            self.stats.acknowledged += 1
        self.log.warning(f"acknowledged: {reason}{f' ({done})' if done else ''}; accepting chunks again")
        return reason + (f" ({done})" if done else "")

    def _recover(self) -> str:
        """Bring a stopped robot back to streaming, holding where it is (called with the robot lock)."""
        now = self.clock.now_ns()
        if self._stop_kind != "connection_lost":
            try:
                mode = self._read_state().mode
            except RobotError:
                mode = "unreachable"  # the backend reconnects in recover()
            if mode == "user_stopped":
                self._robot_mode = mode
                self._fire(Event.ACK_REFUSED)
                raise AcknowledgeRefused("the user stop is still pressed: release it, then acknowledge")
        try:
            done = self.robot.recover()
        except UserStopPressed as err:
            self._robot_mode = "user_stopped"
            self._fire(Event.ACK_REFUSED)
            raise AcknowledgeRefused(f"{err}: release it, then acknowledge") from err
        except RobotError as err:
            self._faulted(f"recovery after '{self._pending_ack or self._reason}' failed: {err}")
        try:
            state = self._read_state()
        except RobotError as err:
            self._faulted(f"the robot cannot be read after recovery: {err}")
        outside = self._outside(state.ee_pose)
        if outside:
            self._state = state
            self._fire(Event.RECOVERED_OUTSIDE, stop_kind="outside")
            return f"{done + '; ' if done else ''}{outside}: moving home first"
        try:
            self.robot.start_streaming()
        except RobotError as err:
            self._faulted(f"streaming would not start again: {err}")
        self._state = state  # the restarted motion holds where the arm was read
        self._streaming_again(now, Event.RECOVERED)
        return done

    def _streaming_again(self, now: int, event: Event) -> None:
        """Streaming started again (the controller's state just read): hold there, waiting for a chunk."""
        self._robot_mode = ""
        self.stats.recoveries += 1
        self._divergence_grace_until_ns = now + int(DIVERGENCE_GRACE_S * 1e9)
        self._fire(event, "acknowledged: waiting for a chunk")

    def _home_then_stream(self) -> None:
        """Acknowledged with the TCP outside the box or cone: the robot's own planned move home,
        then streaming (the control thread, with the robot lock; chunks are refused meanwhile)."""
        self.log.info(f"moving to the home pose {self.config.home_position} (the TCP was outside), then holding")
        try:
            self.robot.move_to(self.home_pose)
            state = self._read_state()
            # Streaming from outside would pull the arm in unasked: the move must have got it in.
            failed = self._outside(state.ee_pose)
            if not failed:
                self.robot.start_streaming()
                self._state = state
        except RobotError as err:
            if isinstance(err, RobotStopped):
                self._robot_stopped(err)
                return
            failed = str(err)
        if failed:
            text = f"the move home failed: {failed}"
            self.record_fault(text)
            self._fire(Event.MOVE_HOME_FAILED, text)
            self.log.error(f"{text}; holding until an operator acknowledges again")
            return
        self._streaming_again(self.clock.now_ns(), Event.MOVED_HOME)

    def _faulted(self, text: str) -> None:
        self.record_fault(text)
        self._fire(Event.RECOVERY_FAILED, text)
        self.log.error(f"faulted: {text}; nothing is sent until an acknowledgement succeeds")
        raise AcknowledgeRefused(text)
