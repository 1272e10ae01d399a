"""A bare franky-sim server (MuJoCo FR3 speaking libfranka's protocol) for tests and benchmarks.

``python -m equidiff_core.robots.franky.sim --host 127.0.0.1`` serves one robot until killed;
``SimServer`` starts that in a subprocess and always kills it. Faults (a user stop, a reflex,
an error recovery cannot clear, an aborted motion, a dropped connection, a jammed gripper) are
injected at the libfranka protocol level through the sim's fault channel
(``robots.franky.faults``: ``SimServer.inject``, or
``python -m equidiff_core.robots.franky.sim --host H --inject reflex``). The digital twin's full
scene lives in ``equidiff_core.twin``; this is the smallest thing the franka node can talk to.

We step the server ourselves instead of ``SimulationServer.run_async()``: the stock loop
sleeps "1 ms minus compute" and runs slower than real time (measured); sleeping to
fixed 1 ms deadlines holds 1000 steps/s, which the tracking numbers depend on.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import time
from typing import Self

from .faults import SimFaults, inject_fault


def serve(host: str, realtime: bool = True) -> None:
    import franky_sim
    from franky_sim.mujoco_simulator import MujocoSimulator

    stop = False

    def _stop(*_):
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    raise_priority()
    with MujocoSimulator() as sim:
        sim.add_robot()
        with franky_sim.SimulationServer(sim, hostname_candidates=[host]) as server:
            # a process entry point: its stdout is the READY/STATS protocol SimServer reads (other lines are its log)
            faults = SimFaults(server, host, log=lambda m: print(m, flush=True))
            print(f"READY {host}", flush=True)
            deadline = start = time.perf_counter()
            steps, missed, next_report = 0, 0, start + 1.0
            try:
                while not stop:
                    missed += step_server(server, faults=faults)
                    deadline += 0.001
                    steps += 1
                    now = time.perf_counter()
                    if now >= next_report:  # lets the parent report how close to real time the sim ran
                        print(f"STATS {steps} {now - start:.3f} {missed}", flush=True)
                        next_report += 1.0
                    delay = deadline - now
                    if delay > 0:
                        time.sleep(delay)
                    elif delay < -0.05:  # far behind (machine overloaded): don't try to catch up in a burst
                        deadline = time.perf_counter()
            finally:
                faults.close()


def step_server(server, command_timeout_s: float = 0.02, faults: SimFaults | None = None) -> int:
    """One 1 ms tick of a franky-sim ``SimulationServer``: the clients' commands, physics, state.

    Unlike the stock ``run_once``, each robot's tick waits for the command answering the last
    state (``await_command``), so the client's 1 kHz loop stays a 1 kHz loop on a loaded machine.
    With ``faults``, requested faults are applied first, and while the robot's connection is
    dropped it reads no command and sends no state (its joints held). Returns how many robots'
    commands did not arrive in time (their last command was reused).
    """
    if faults is not None:
        faults.poll()
        if faults.dropped:
            faults.hold()
            server.sim.step()
            return 0
    missed = sum(not await_command(rs, command_timeout_s) for rs in server.robot_servers)
    server.sim.step()
    for rs in server.robot_servers:
        rs.send_state()
    return missed


def await_command(robot_server, timeout_s: float = 0.02) -> bool:
    """Process the client's commands, waiting up to ``timeout_s`` for the one answering the last state.

    A real FR3 gets a command every 1 ms from a client on a real-time kernel (or stops with a
    reflex). On a loaded machine with few cores the franky client is sometimes starved for tens of ms, and
    stock franky-sim then keeps applying the stale torque while physics runs on: the
    1 kHz impedance loop becomes a delayed, sampled one and can swing the arm centimetres off
    (we saw 4-6 cm). Waiting for the command instead slows simulated time a little under load
    (visible as ``SimServer.realtime_factor``) but keeps the closed loop what it is on the robot.
    "Answering" is by libfranka's message id, not merely "a new command": a client that fell
    behind would answer its backlog of old states one per tick, closing the torque loop on a
    state that many ms old.
    Returns whether that command arrived (True also when no motion is running).
    """
    mode = getattr(robot_server, "_FrankaRobotServer__control_mode", None)
    robot_server.process_commands()
    if mode is None or getattr(mode, "name", "IDLE") == "IDLE":
        return True
    deadline = time.perf_counter() + timeout_s
    while not _answers_last_state(robot_server):
        if time.perf_counter() > deadline:
            return False
        time.sleep(0.0001)
        robot_server.process_commands()
    return True


def keep_alive(server) -> None:
    """Keep libfranka's connections alive while the sim pauses (no physics step, no new state).

    libfranka gives up 1 s after its last robot state (UDP receive timeout) and the connection
    is then dead for good: only a new ``franky.Robot`` recovers. Sending a *new* state without
    stepping physics is worse: libfranka's time (message id x 1 ms) would run ahead of the
    physics and a tracker timed by it swung the arm 394 mm in a probe. So we re-send the
    current state under the message id already sent: libfranka drops it as not newer, but its
    receive timeout restarts. The gripper's state goes out again too (gripper reads do not
    check ids and time out as well). Call it every 0.1-0.9 s of a pause. franky-sim keeps the
    id in a private, name-mangled field; without it (another layout) nothing is sent.
    """
    from franky_sim.franka_server import FrankaServer

    for rs in server.robot_servers:
        for channel in (rs, getattr(rs, "_FrankaRobotServer__gripper_server", None)):
            sent = getattr(channel, "_FrankaServer__message_id", 0)
            if channel is None or sent < 1 or not channel.udp_connected:
                continue  # nothing sent yet, no client, or an unknown layout: nothing to repeat
            channel._FrankaServer__message_id = sent - 1
            FrankaServer.send_state(channel)  # this channel only (the robot's send_state adds the gripper's)


def _answers_last_state(robot_server) -> bool:
    """Whether the command in effect answers the newest state sent (franky-sim's private fields)."""
    command = getattr(robot_server, "_FrankaRobotServer__current_control_command", None)
    next_id = getattr(robot_server, "_FrankaServer__message_id", None)
    if command is None or next_id is None:  # another franky-sim layout: fall back to "any new command"
        return getattr(robot_server, "_FrankaRobotServer__has_new_command", True)
    return next_id == 0 or command.message_id >= next_id - 1


def raise_priority(niceness: int = -10) -> bool:
    """Run this process at a higher CPU priority when permitted (root / CAP_SYS_NICE).

    franky-sim stands in for the FR3's own controller, which never competes with our
    Python for a CPU; on a loaded machine with few cores an ordinary-priority sim fell to 10 % of
    real time and every tracking number became meaningless. Returns whether it worked.
    """
    try:
        os.setpriority(os.PRIO_PROCESS, 0, niceness)
        return True
    except (PermissionError, OSError):
        return False


class SimServer:
    """franky-sim in a subprocess: ``with SimServer() as sim: franky.Robot(sim.host, ...)``.

    ``module`` serves it (``--host`` plus ``args``) and prints ``READY <host> [words...]`` once
    it listens; the words are kept in ``ready``. The default is this module's bare robot;
    ``twin.sim`` serves the twin's scene the same way.
    """

    def __init__(
        self,
        host: str | None = None,
        startup_timeout_s: float = 60.0,
        module: str = "equidiff_core.robots.franky.sim",
        args: tuple[str, ...] = (),
    ):
        # A random 127.x.y.z by default: parallel tests / twins each get their own robot.
        self.host = host or free_loopback_host()
        self.startup_timeout_s = startup_timeout_s
        self.module, self.args = module, tuple(args)
        self.process: subprocess.Popen | None = None
        self.ready: list[str] = []  # the words after READY <host>
        # (monotonic, steps, server wall s, ticks that reused a late client's command), once a second
        self.stats: list[tuple[float, int, float, int]] = []

    def start(self) -> SimServer:
        _check_port_free(self.host)
        env = dict(os.environ, OMP_NUM_THREADS="1")
        self.process = subprocess.Popen(
            [sys.executable, "-u", "-m", self.module, "--host", self.host, *self.args],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
        )
        deadline = time.monotonic() + self.startup_timeout_s
        lines = []
        while time.monotonic() < deadline:
            line = self.process.stdout.readline()
            if not line:
                break
            lines.append(line)
            if line.startswith("READY"):
                self.ready = line.split()[2:]
                # Keep reading its output (a full pipe would block the server), noting its speed.
                import threading

                threading.Thread(target=self._read_stats, args=(self.process.stdout,), daemon=True).start()
                return self
        self.stop()
        raise RuntimeError("franky-sim did not start:\n" + "".join(lines[-20:]))

    def _read_stats(self, stream) -> None:
        for line in stream:
            if line.startswith("STATS"):
                _, steps, wall, missed = line.split()
                self.stats.append((time.monotonic(), int(steps), float(wall), int(missed)))

    def inject(self, fault: str, seconds: float | None = None) -> str:
        """Inject ``fault`` into the running server (``robots.franky.faults``); its status once applied."""
        if self.process is None or self.process.poll() is not None:
            raise RuntimeError("franky-sim is not running")
        return inject_fault(self.host, fault, seconds)

    def jam_gripper(self, jammed: bool = True) -> None:
        """Jam (or free) the hand: the fingers stay and the running gripper command is never answered."""
        self.inject("jam_gripper" if jammed else "free_gripper")

    def realtime_factor(self, since: float | None = None) -> float | None:
        """Simulated seconds per wall second (1.0 = real time) since monotonic time ``since``."""
        rows = [r for r in self.stats if since is None or r[0] >= since]
        if len(rows) < 2:
            return None
        (_, s0, w0, _), (_, s1, w1, _) = rows[0], rows[-1]
        return (s1 - s0) / 1000.0 / (w1 - w0)

    def missed_commands(self) -> int | None:
        """Ticks so far that reused the client's last command (it was starved past the sim's wait):
        each is a tick of a delayed torque loop, which an FR3 would have stopped with a reflex."""
        return self.stats[-1][3] if self.stats else None

    def stop(self) -> None:
        if self.process is None:
            return
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.process = None

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def free_loopback_host() -> str:
    import random

    rng = random.Random()
    for _ in range(50):
        host = f"127.{rng.randint(1, 254)}.{rng.randint(0, 255)}.{rng.randint(1, 254)}"
        try:
            _check_port_free(host)
            return host
        except RuntimeError:
            continue
    raise RuntimeError("no free loopback address for franky-sim")


def _check_port_free(host: str, port: int = 1337) -> None:
    # libfranka's command port; a leftover server would silently answer instead of ours.
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as err:
            raise RuntimeError(
                f"{host}:{port} is taken: another franky-sim (or robot) is already "
                f"serving there; pick another 127.x.y.z address"
            ) from err


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--host", default="127.0.0.1", help="loopback address to serve on (or of the sim to fault)")
    parser.add_argument(
        "--inject",
        metavar="FAULT",
        default=None,
        help="do not serve: inject FAULT into the sim serving on --host (user_stop, release, reflex, error, "
        "abort, drop, clear, jam_gripper, free_gripper, status) and print its status",
    )
    parser.add_argument("--seconds", type=float, default=None, help="with --inject drop: how long")
    args = parser.parse_args(argv)
    if args.inject is None:
        serve(args.host)
        return
    print(inject_fault(args.host, args.inject, args.seconds))  # the command's answer, for whoever ran it


if __name__ == "__main__":
    main()
