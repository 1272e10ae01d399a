"""Faults injected into a franky-sim server at the libfranka protocol level, for tests and benches.

franky-sim's server only ever reports ``kMove`` or ``kIdle`` and acknowledges every error
recovery, yet libfranka's protocol can say much more: a robot mode (``kReflex``,
``kUserStopped``), 41 error flags twice (``errors``, which libfranka reports as
``current_errors``, and ``reflex_reason``, its ``last_motion_errors``), and the status of the
running motion's ``Move`` command (``kReflexAborted``, ``kEmergencyAborted``, ``kAborted``).
``SimFaults`` sets those on one robot server, so the real franky client sees what a real FR3
sends, and raises the real exceptions:

* ``user_stop``: the user stop is pressed. The running motion ends with ``kEmergencyAborted``
  (libfranka: "Move command aborted: User Stop pressed!"), the mode turns ``kUserStopped`` and
  the joints are held where they are. While it is pressed every ``Move`` and every automatic
  error recovery is answered ``kEmergencyAborted``. ``release`` lets go of it (mode ``kIdle``).
* ``reflex``: a collision reflex. The motion ends with ``kReflexAborted`` and the
  ``cartesian_reflex`` flag, the mode turns ``kReflex``; ``Move`` is refused ("command not
  possible in the current mode") until an automatic error recovery clears it.
* ``error``: a fault automatic recovery cannot clear (a joint past its position limit: on an
  FR3 the operator guides it out in Desk). As ``reflex``, with the
  ``joint_position_limits_violation`` flag, and every recovery is answered
  ``kManualErrorRecoveryRequiredRejected`` until ``clear`` (the manual recovery).
* ``abort``: the running motion ends with ``kAborted``; the robot stays usable.
* ``drop <seconds>``: the robot stops answering: no state, no command is read, the joints are
  held (an FR3 stops when its client's commands stop). libfranka gives up 1 s after its last
  state ("UDP receive: Timeout") and its ``Robot`` is dead from then on. When the drop ends
  the server closes the old connection (so a new ``franky.Robot`` is accepted) and reports the
  ``communication_constraints_violation`` reflex until a recovery clears it.
* ``jam_gripper`` / ``free_gripper``: the hand's fingers hold their width whatever goal
  arrives and the running gripper command is never answered, until freed.
* ``clear``: every fault above ends; ``status`` only reports.

Faults are requested over a small UDP control channel of the sim process: one datagram
``"<fault> [seconds]"`` to ``FAULT_PORT`` on the sim's own loopback address, answered
``"ok <status>"`` or ``"error <why>"`` once the sim loop applied it (``inject_fault``;
``SimServer.inject``; ``python -m equidiff_core.robots.franky.sim --host H --inject reflex``).
The twin's ``TwinSim`` opens the same channel, so a twin_node's robot takes them too.

This reaches into franky-sim 1.0.4's private layout (name-mangled fields of
``FrankaRobotServer``, its command map), as ``sim.py``'s command wait does.
"""

from __future__ import annotations

import socket
import time

FAULT_PORT = 1339  # next to libfranka's command (1337) and gripper (1338) ports, on the sim's address
FAULTS = ("user_stop", "release", "reflex", "error", "abort", "drop", "clear", "jam_gripper", "free_gripper", "status")

# libfranka's Errors flags (franka/errors.h, in order): the ones injected here
JOINT_POSITION_LIMITS_VIOLATION = 0
CARTESIAN_REFLEX = 7
COMMUNICATION_CONSTRAINTS_VIOLATION = 31
N_ERRORS = 41


class FaultError(RuntimeError):
    """A fault request was malformed, refused, or not answered."""


def _flags(*indices: int) -> tuple[bool, ...]:
    return tuple(i in indices for i in range(N_ERRORS))


class SimFaults:
    """Fault injection for the first robot of a franky-sim ``SimulationServer`` (see the module
    docstring). Call ``poll`` once per sim tick (the sim loop's thread owns the server); while
    ``dropped`` the loop must neither read commands nor send states (``step_server`` does so)."""

    def __init__(self, server, host: str, port: int = FAULT_PORT, log=print):
        from franky_sim.franka_robot_protocol import RobotCommand

        self.rs = server.robot_servers[0]
        self.robot = self.rs.robot
        self.gripper = getattr(self.rs, "_FrankaRobotServer__gripper_server", None)
        self.log = log
        self.mode = None  # RobotMode reported instead of kMove/kIdle (None: franky-sim's own)
        self.current_errors = _flags()
        self.motion_errors = _flags()
        self.move_refusal = None  # MoveStatus every new motion gets while a fault lasts
        self.recovery_refusal = None  # AutomaticErrorRecoveryStatus while recovery cannot clear it
        self.pressed = False  # the user stop
        self.drop_until = 0.0  # monotonic s: the robot answers nothing until then
        self.jammed = False
        self._install_state()
        commands = self.rs._FrankaServer__command_class_map
        commands[RobotCommand.kMove] = self._guarded_move(commands[RobotCommand.kMove])
        commands[RobotCommand.kAutomaticErrorRecovery] = self._guarded_recovery(
            commands[RobotCommand.kAutomaticErrorRecovery]
        )
        self._install_jam()
        self.sock = None
        try:
            self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.sock.bind((host, port))
            self.sock.setblocking(False)
        except OSError as err:  # the sim must serve anyway; only injection is lost
            self.sock = None
            self.log(f"fault channel unavailable on {host}:{port}: {err}")

    # --- what the robot reports and answers ----------------------------------------------
    def _install_state(self) -> None:
        rs, faults = self.rs, self

        def state_bytes():
            state = rs.robot_state
            if faults.mode is not None or any(faults.current_errors) or any(faults.motion_errors):
                state = state.replace(
                    robot_mode=faults.mode if faults.mode is not None else state.robot_mode,
                    errors=faults.current_errors,
                    reflex_reason=faults.motion_errors,
                )
            return state.pack_state()

        rs._get_state_bytes = state_bytes  # send_state calls it for every state message

    def _guarded_move(self, move_cls):
        faults = self

        class GuardedMove(move_cls):
            def handle(self, server):
                if faults.move_refusal is None:
                    return super().handle(server)
                faults.log(f"fault: Move refused ({faults.move_refusal.name})")
                self.reply(faults.move_refusal)

        return GuardedMove

    def _guarded_recovery(self, recovery_cls):
        faults = self

        class GuardedRecovery(recovery_cls):
            def handle(self, server):
                from franky_sim.franka_robot_protocol import AutomaticErrorRecoveryStatus

                if faults.recovery_refusal is not None:
                    faults.log(f"fault: error recovery refused ({faults.recovery_refusal.name})")
                    self.reply(faults.recovery_refusal)
                    return
                faults.mode = None  # franky-sim's own kIdle / kMove again
                faults.current_errors = faults.motion_errors = _flags()
                faults.move_refusal = None
                self.reply(AutomaticErrorRecoveryStatus.kSuccess)

        return GuardedRecovery

    def _install_jam(self) -> None:
        robot, faults = self.robot, self
        set_goal = robot.set_hand_goal

        def guarded(width, max_velocity, max_force):
            set_goal(robot.hand_width if faults.jammed else width, max_velocity, max_force)

        robot.set_hand_goal = guarded
        if self.gripper is not None and hasattr(self.gripper, "_check_motion_state"):
            check_motion = self.gripper._check_motion_state

            def unanswered():  # the running gripper command never finishes while jammed
                if not faults.jammed:
                    check_motion()

            self.gripper._check_motion_state = unanswered
        self._set_goal = set_goal

    # --- faults --------------------------------------------------------------------------
    def _abort(self, status) -> None:
        """End the running motion with ``status`` (None: silently) and hold the joints where they are."""
        from franky_sim.franka_robot_protocol import RobotCommand
        from franky_sim.franka_server import BaseCommand

        rs = self.rs
        motion_id = rs.current_motion_id
        rs.stop_motion(send_preemption_signal=False)
        # stop_motion holds q_d, which in torque control is whatever a position motion last set
        rs._FrankaRobotServer__holding_q = tuple(self.robot.inner_state.q)
        if motion_id and status is not None and rs._tcp_socket is not None:
            BaseCommand.send_response(rs._tcp_socket, RobotCommand.kMove, motion_id, status)
        rs.reset_current_motion_id()

    def apply(self, fault: str, seconds: float | None = None) -> str:
        from franky_sim.franka_robot_protocol import AutomaticErrorRecoveryStatus as Recovery
        from franky_sim.franka_robot_protocol import MoveStatus, RobotMode

        if fault == "user_stop":
            self.pressed = True
            self._abort(MoveStatus.kEmergencyAborted)
            self.mode = RobotMode.kUserStopped
            self.move_refusal, self.recovery_refusal = MoveStatus.kEmergencyAborted, Recovery.kEmergencyAborted
        elif fault == "release":
            if self.pressed:  # back to franky-sim's own kIdle / kMove (a kIdle kept during a new motion
                self.pressed = False  # would make libfranka read it as aborted)
                self.mode = self.move_refusal = self.recovery_refusal = None
        elif fault == "reflex":
            self._abort(MoveStatus.kReflexAborted)
            self._set_reflex(CARTESIAN_REFLEX)
        elif fault == "error":
            self._abort(MoveStatus.kReflexAborted)
            self._set_reflex(JOINT_POSITION_LIMITS_VIOLATION)
            self.recovery_refusal = Recovery.kManualErrorRecoveryRequiredRejected
        elif fault == "abort":
            self._abort(MoveStatus.kAborted)
        elif fault == "drop":
            if seconds is None or not seconds > 0:
                raise FaultError("drop needs a positive number of seconds")
            self._abort(None)
            self.drop_until = time.monotonic() + float(seconds)
        elif fault == "clear":
            self.pressed = self.jammed = False
            self.mode, self.move_refusal, self.recovery_refusal = None, None, None
            self.current_errors = self.motion_errors = _flags()
            if self.dropped:
                self.drop_until = time.monotonic()
        elif fault in ("jam_gripper", "free_gripper"):
            self.jammed = fault == "jam_gripper"
            if self.jammed:
                self._set_goal(self.robot.hand_width, 0.05, 70.0)
        elif fault != "status":
            raise FaultError(f"unknown fault {fault!r}; one of {', '.join(FAULTS)}")
        if fault != "status":
            self.log(f"fault: {fault}{'' if seconds is None else f' {seconds}'} -> {self.status()}")
        return self.status()

    def _set_reflex(self, flag: int) -> None:
        from franky_sim.franka_robot_protocol import MoveStatus, RobotMode

        self.mode = RobotMode.kReflex
        self.current_errors = self.motion_errors = _flags(flag)
        self.move_refusal = MoveStatus.kCommandNotPossibleRejected

    def status(self) -> str:
        mode = "default" if self.mode is None else self.mode.name
        flags = [i for i, on in enumerate(self.current_errors) if on]
        return (
            f"mode={mode} errors={flags} pressed={self.pressed} dropped={self.dropped} "
            f"jammed={self.jammed} recovery_refused={self.recovery_refusal is not None}"
        )

    # --- the sim loop's side -------------------------------------------------------------
    @property
    def dropped(self) -> bool:
        return self.drop_until > 0.0

    def poll(self) -> None:
        """Apply requests that arrived, and end a drop that is over. Once per sim tick."""
        if self.dropped and time.monotonic() >= self.drop_until:
            self._end_drop()
        while self.sock is not None:
            try:
                data, addr = self.sock.recvfrom(256)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            words = data.decode(errors="replace").split()
            try:
                if not words:
                    raise FaultError("empty request")
                seconds = float(words[1]) if len(words) > 1 else None
                reply = "ok " + self.apply(words[0], seconds)
            except (FaultError, ValueError) as err:
                reply = f"error {err}"
            try:
                self.sock.sendto(reply.encode(), addr)
            except OSError:
                pass

    def _end_drop(self) -> None:
        """The robot answers again, but not its old client: libfranka gave that connection up
        (its Robot is dead), and franky-sim accepts one client at a time."""
        from franky_sim.franka_robot_protocol import RobotMode

        self.drop_until = 0.0
        for server in (self.rs, self.gripper):
            if server is not None:
                server.reset_state()
        self.mode = RobotMode.kReflex
        self.current_errors = self.motion_errors = _flags(COMMUNICATION_CONSTRAINTS_VIOLATION)
        self.log(f"fault: drop over -> {self.status()}")

    def hold(self) -> None:
        """While dropped: keep the joints held (the motion was stopped), reading no command."""
        self.rs._post_process_commands()

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None


def inject_fault(host: str, fault: str, seconds: float | None = None, timeout_s: float = 5.0) -> str:
    """Ask the franky-sim serving on ``host`` for ``fault`` (see the module docstring); returns its
    status once applied. Raises FaultError if refused or unanswered within ``timeout_s``."""
    request = fault if seconds is None else f"{fault} {seconds}"
    deadline = time.monotonic() + timeout_s
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.settimeout(0.5)
        while time.monotonic() < deadline:
            sock.sendto(request.encode(), (host, FAULT_PORT))
            try:
                reply = sock.recv(512).decode(errors="replace")
            except TimeoutError:
                continue  # lost on a loaded machine: ask again
            if reply.startswith("ok"):
                return reply[3:]
            raise FaultError(f"franky-sim at {host} refused {request!r}: {reply.removeprefix('error ')}")
    raise FaultError(f"franky-sim at {host} did not answer {request!r} within {timeout_s:.0f} s")
