"""Running the twin: franky-sim's server with the task scene on simulated or real time, or a direct sim.

``TwinSim`` serves libfranka's protocol (franky connects to ``host`` exactly as to a real
FR3). Each tick waits for the client's command like the bare server
(``robots.franky.sim.step_server``), so a starved client sees the 1 kHz loop a real FR3
gives it; the stock tick ran on without it, and the twin's home move failed now and then in
CI (ruckig error -101) while the bare server's never did.

Two clocks:

* **Simulated time** (``lockstep`` given, the twin's default): the sim owns time, counted in
  1 ms ticks, and reports it through ``on_clock`` (twin_node publishes it on ``/clock``). It
  steps in lockstep with the pipeline (``twin.lockstep``): camera frames are taken at their
  instants and a policy chunk is in place by its observation's time + L before the sim
  passes it; while it waits it keeps libfranka's connection alive
  (``robots.franky.sim.keep_alive``). It never runs faster than ``max_speed`` x real time.
* **Real time**: fixed 1 ms wall-clock deadlines (franky-sim's stock ``run_async`` sleeps
  "1 ms minus compute" and drifts 8-16 % slow); when the loop falls more than ``max_lag_s``
  behind it skips ahead (counting the overrun) instead of sprinting.

``DirectSim`` is the same scene with no server and no clock: franky-sim's own Cartesian
controller is driven in-process and stepped as fast as the CPU allows (tests, fast expert
roll-outs).

``python -m equidiff_core.twin.sim --host H --config twin.yaml`` serves a real-time TwinSim in a
process of its own (``robots.franky.sim.SimServer(module="equidiff_core.twin.sim", ...)``),
sharing its state for cameras under ``--shm``: a sim thread inside a busy Python process
waits for that process's GIL, and on a loaded machine it went silent past libfranka's 1 s
receive timeout (the calibration twin, CI).

Both clocks take franky-sim faults at the libfranka protocol level (``robots.franky.faults``:
a user stop, a reflex, an error recovery cannot clear, an aborted motion, a dropped
connection, a jammed gripper) on the sim's fault channel, ``FAULT_PORT`` at ``host``.
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import mujoco
import numpy as np
from franky_sim import SimulationServer
from franky_sim.mujoco_simulator import MUJOCO_DEFAULT_KP, MUJOCO_DEFAULT_KV
from scipy.spatial.transform import Rotation

from ..robots.base import RobotState
from ..robots.franky.faults import SimFaults
from ..robots.franky.hand import TCP_OFFSET
from ..robots.franky.sim import (
    free_loopback_host,
    keep_alive,
    raise_priority,
    step_server,
)
from .config import TwinConfig, load_twin_config
from .lockstep import NS_PER_TICK, Lockstep, LockstepConfig
from .scene import (
    ScenePoses,
    apply_scene,
    build_simulator,
    object_state,
    sample_scene,
    success_details,
)
from .shared_state import StateWriter

logger = logging.getLogger(__name__)


@dataclass
class LoopStats:
    steps: int = 0
    overruns: int = 0  # times the loop fell behind and skipped ahead
    missed_commands: int = 0  # ticks that reused the client's last command (it was starved past the wait)
    started: float = 0.0
    wait_s: dict = field(default_factory=lambda: {"cameras": 0.0, "policy": 0.0})  # lockstep waits, wall s

    def steps_per_s(self) -> float:
        dt = time.monotonic() - self.started
        return self.steps / dt if dt > 0 else 0.0


class TwinSim:
    """franky-sim + task scene + real-time loop + shared-memory state for the cameras."""

    def __init__(
        self,
        cfg: TwinConfig,
        host: str | None = None,
        shm_name: str | None = None,
        max_lag_s: float = 0.05,
        command_wait_s: float = 0.02,
        lockstep: LockstepConfig | None = None,
        on_clock: Callable[[int], None] | None = None,
        camera_names: tuple[str, ...] = (),
        log: Callable[[str], None] | None = None,
    ):
        self.cfg = cfg
        self.log = log or logger.info  # where the fault channel's lines go
        self.host = host or cfg.sim.host
        if self.host == "auto":
            self.host = free_loopback_host()
        self.shm_name = shm_name
        self.max_lag_s = max_lag_s
        # real time: how long a tick waits for franky's command answering the newest state before
        # physics runs on with the last one (a starved client's stale torque, which an FR3 would
        # answer with a reflex). Longer keeps the closed loop what it is on the robot, slower
        # than real time on a busy machine (equidiff bench safety passes 0.5, as simulated time does).
        self.command_wait_s = command_wait_s
        self.lockstep = Lockstep(lockstep) if lockstep is not None else None
        self.on_clock = on_clock  # called with the sim time in ns (simulated time only)
        self.camera_names = tuple(camera_names)  # lab.yaml order = the cameras' shared-memory slots
        self.tick = 0  # 1 ms steps since start: simulated time
        self.state_every = max(1, round(1000 / cfg.sim.state_hz))  # ticks between snapshots for the cameras
        self.lock = threading.Lock()  # held while stepping; take it to read or edit sim state
        self.stats = LoopStats()
        self.poses: ScenePoses | None = None
        self._sim = self._robot = self._server = self._writer = None
        self.faults: SimFaults | None = None  # protocol-level fault injection (robots.franky.faults)
        self._thread: threading.Thread | None = None
        self._running = False
        self._frame_tick = 0

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self, seed: int = 0) -> TwinSim:
        self._sim, self._robot = build_simulator(self.cfg)
        self._sim.init()
        self._server = SimulationServer(self._sim, hostname_candidates=[self.host])
        self._server.init()  # binds host:1337 and starts the simulation
        self.faults = SimFaults(self._server, self.host, log=self.log)
        self._writer = StateWriter(self.model.nq, self.shm_name)
        self.shm_name = self._writer.name
        self.reset(seed)
        self._running = True
        self._thread = threading.Thread(target=self._loop, name="twin-sim", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self.faults is not None:
            self.faults.close()
            self.faults = None
        if self._server is not None:
            self._server.cleanup()
            self._server = None
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def __enter__(self):
        return self.start() if self._server is None else self

    def __exit__(self, *exc):
        self.stop()

    @property
    def model(self):
        return self._sim.model

    @property
    def data(self):
        return self._sim.data

    # -- the loops ---------------------------------------------------------------------------
    def _loop(self) -> None:
        raise_priority()  # this thread only (Linux nice is per thread): it stands in for the FR3's controller
        self.stats = LoopStats(started=time.monotonic())
        if self.lockstep is None:
            self._loop_realtime()
        else:
            self._loop_lockstep()

    def _step(self, command_timeout_s: float) -> None:
        with self.lock:
            self.stats.missed_commands += step_server(self._server, command_timeout_s, self.faults)
            self.stats.steps += 1
            self.tick += 1
            if self.stats.steps % self.state_every == 0:
                self._publish_state()

    def _loop_realtime(self) -> None:
        period = 0.001
        deadline = time.monotonic()
        while self._running:
            self._step(self.command_wait_s)
            deadline += period
            lag = time.monotonic() - deadline
            if lag < 0:
                time.sleep(-lag)
            elif lag > self.max_lag_s:  # hopelessly behind (CPU starved): do not sprint to catch up
                self.stats.overruns += 1
                deadline = time.monotonic()

    def _loop_lockstep(self) -> None:
        ls, cfg = self.lockstep, self.lockstep.config
        period = 0.001 / cfg.max_speed if cfg.max_speed > 0 else 0.0
        frame, published = 0, -1
        deadline = time.monotonic()
        while self._running:
            kind, why = self._blocker(frame)
            if self.tick != published and (kind or self.tick % cfg.clock_period_ticks == 0):
                self._publish_clock()  # before any wait: whoever must act at this instant sees it
                published = self.tick
            if kind:
                self._wait_while_blocked(frame, kind, why)
                deadline = time.monotonic()
                continue
            # On simulated time a late client command is waited for (0.5 s, not 20 ms): the
            # closed loop must not depend on how busy the machine is.
            self._step(0.5)
            if ls.is_frame_tick(self.tick):
                with self.lock:
                    frame = self._writer.request_frame(self.data.qpos, self.tick / 1000, self.tick * NS_PER_TICK)
                self._frame_tick = self.tick
                ls.frame_taken(self.tick)  # owed a chunk from now on (cameras take it before we step on)
            if period:
                deadline += period
                lag = time.monotonic() - deadline
                if lag < 0:
                    time.sleep(-lag)
                elif lag > self.max_lag_s:
                    deadline = time.monotonic()

    def _blocker(self, frame: int) -> tuple[str, str]:
        """(kind, why) of what the sim waits for before its next step; ('', '') when nothing."""
        behind = self._writer.cameras_behind(frame) if frame else []
        if behind:
            names = [self.camera_names[i] if i < len(self.camera_names) else f"slot {i}" for i in behind]
            return "cameras", (
                f"camera_node ({', '.join(names)}): did not take the frame at t={self._frame_tick / 1000:.3f} s"
            )
        why = self.lockstep.chunk_blocker(self.tick)
        return ("policy", why) if why else ("", "")

    def _wait_while_blocked(self, frame: int, kind: str, why: str) -> None:
        """Wait (keeping libfranka alive) until nothing blocks the next step, or the wait stalls."""
        cfg = self.lockstep.config
        start = last_keepalive = time.monotonic()
        while self._running and kind:
            now = time.monotonic()
            if now - start > cfg.stall_timeout_s:
                stall = f"t={self.tick / 1000:.3f} s: {why} within {cfg.stall_timeout_s:.0f} s"
                if kind == "cameras":
                    for slot in self._writer.cameras_behind(frame):
                        self._writer.drop_camera(slot)
                    self.lockstep.record_stall(stall)
                else:
                    self.lockstep.give_up_oldest(stall)
                break
            if now - last_keepalive > cfg.keepalive_s:
                with self.lock:
                    self.faults.poll()  # a fault requested while the sim waits
                    if not self.faults.dropped:  # a dropped connection stays silent
                        keep_alive(self._server)
                self._publish_clock()  # again: /clock is best effort, and a lost one could hold up the waited-for
                last_keepalive = now
            time.sleep(0.0005)
            kind_now, why = self._blocker(frame)
            self.stats.wait_s[kind] += time.monotonic() - now
            kind = kind_now

    def _publish_clock(self) -> None:
        if self.on_clock is not None:
            self.on_clock(self.tick * NS_PER_TICK)

    def _publish_state(self) -> None:
        # stamps on the clock the nodes use: simulated time, or the wall clock the cameras pace by
        stamp = self.tick * NS_PER_TICK if self.lockstep is not None else time.time_ns()
        self._writer.write(self.data.qpos, self.tick / 1000, stamp)

    # -- episode control ---------------------------------------------------------------------
    def reset(self, seed: int) -> ScenePoses:
        """New object poses drawn from ``seed`` (the robot is not teleported: it is commanded home)."""
        poses = sample_scene(self.cfg.scene, seed)
        with self.lock:
            apply_scene(self.model, self.data, poses, self.cfg.scene)
            self.poses = poses
            self._publish_state()
        return poses

    def status(self) -> dict:
        with self.lock:
            details = success_details(self.model, self.data, self.cfg.scene, self.cfg.success)
            objects = object_state(self.model, self.data)
        ls = self.lockstep
        return {
            "seed": self.poses.seed if self.poses else None,
            "sim_time": round(self.tick / 1000, 4),
            "success": details["success"],
            "details": details,
            "objects": objects,
            "steps_per_s": round(self.stats.steps_per_s(), 1),
            "overruns": self.stats.overruns,
            "missed_commands": self.stats.missed_commands,
            "host": self.host,
            "clock": "realtime" if ls is None else "sim",
            **(
                {}
                if ls is None
                else {
                    "awaiting_policy": ls.awaiting,
                    "stalls": len(ls.stalls),
                    "last_stall": ls.stalls[-1] if ls.stalls else "",
                    "wait_s": {k: round(v, 2) for k, v in self.stats.wait_s.items()},
                }
            ),
        }


class DirectSim:
    """The twin scene stepped in-process as fast as the CPU allows (tests, fast expert roll-outs).

    ``command(pose, width)`` sets the TCP target (4x4, base frame) and gripper width; ``step(n)``
    advances n ms. Contacts and the gripper are franky-sim's (its finger PD runs every step);
    the arm follows the target like franky-sim's joint-impedance path: damped least-squares IK
    to a joint target, then PD with the same gains plus gravity/Coriolis compensation. We do
    the arm control with MuJoCo's own Jacobian and bias forces instead of franky-sim's
    per-step pinocchio calls and state tracking, which made the twin's tests several times slower.
    """

    def __init__(self, cfg: TwinConfig):
        self.cfg = cfg
        self._sim, self.robot = build_simulator(cfg)
        self._sim.init()
        self._sim.start()
        self.model, self.data = self._sim.model, self._sim.data
        self._ik_data = mujoco.MjData(self.model)
        self._hand = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, "robot0_hand")
        self._qadr = np.array(self.robot._qpos_addrs)
        self._dadr = np.array(self.robot._dof_addrs)
        self._kp, self._kv = np.array(MUJOCO_DEFAULT_KP), np.array(MUJOCO_DEFAULT_KV)
        self._tau_limit = np.array([87, 87, 87, 87, 12, 12, 12], dtype=float)
        self._q_target = np.array(cfg.sim.initial_q, dtype=float)
        self._target = None
        self._width = 0.08
        self.poses: ScenePoses | None = None

    def reset(self, seed: int) -> ScenePoses:
        self.data.qpos[self._qadr] = self.cfg.sim.initial_q
        for addr in self.robot._finger_qpos_addrs:
            self.data.qpos[addr] = 0.04
        self.data.qvel[:] = 0.0
        self.data.qfrc_applied[:] = 0.0
        self.data.time = 0.0
        self.poses = sample_scene(self.cfg.scene, seed)
        apply_scene(self.model, self.data, self.poses, self.cfg.scene)
        mujoco.mj_forward(self.model, self.data)
        self._q_target = np.array(self.cfg.sim.initial_q, dtype=float)
        self._target = self.tcp_pose()
        self._width = 0.08
        return self.poses

    def _tcp(self, data) -> np.ndarray:
        R = data.xmat[self._hand].reshape(3, 3)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = data.xpos[self._hand] + R @ TCP_OFFSET
        return T

    def tcp_pose(self) -> np.ndarray:
        return self._tcp(self.data)

    def gripper_width(self) -> float:
        return float(self.robot.hand_width)

    def joint_positions(self) -> np.ndarray:
        return self.data.qpos[self._qadr].copy()

    def joint_velocities(self) -> np.ndarray:
        return self.data.qvel[self._dadr].copy()

    def robot_state(self, stamp_ns: int | None = None) -> RobotState:
        """The arm as a robot backend reports it (stamped ``stamp_ns``, default the sim time)."""
        stamp = round(self.time * 1e9) if stamp_ns is None else int(stamp_ns)
        return RobotState(
            stamp,
            self.tcp_pose(),
            self.joint_positions(),
            self.joint_velocities(),
            self.gripper_width(),
            robot_time_s=self.time,
        )

    def _solve_ik(self, target: np.ndarray, iterations: int = 8, damping: float = 1e-4) -> np.ndarray:
        d = self._ik_data
        d.qpos[:] = self.data.qpos
        q = self._q_target.copy()
        jacp, jacr = np.zeros((3, self.model.nv)), np.zeros((3, self.model.nv))
        for _ in range(iterations):
            d.qpos[self._qadr] = q
            mujoco.mj_kinematics(self.model, d)
            mujoco.mj_comPos(self.model, d)  # mj_jac needs the com-based dof axes
            T = self._tcp(d)
            err = np.concatenate(
                [target[:3, 3] - T[:3, 3], Rotation.from_matrix(target[:3, :3] @ T[:3, :3].T).as_rotvec()]
            )
            if np.linalg.norm(err) < 1e-5:
                break
            mujoco.mj_jac(self.model, d, jacp, jacr, T[:3, 3], self._hand)
            J = np.vstack([jacp[:, self._dadr], jacr[:, self._dadr]])
            q = q + J.T @ np.linalg.solve(J @ J.T + damping * np.eye(6), err)
        return q

    def command(self, pose: np.ndarray, width: float) -> None:
        self._target = np.asarray(pose, dtype=float)
        self._width = float(width)
        self._q_target = self._solve_ik(self._target)

    def step(self, n: int = 1) -> None:
        self.robot.set_hand_goal(self._width, 0.05, 70.0)
        d = self.data
        for _ in range(n):
            q, dq = d.qpos[self._qadr], d.qvel[self._dadr]
            tau = self._kp * (self._q_target - q) - self._kv * dq
            d.qfrc_applied[self._dadr] = np.clip(tau, -self._tau_limit, self._tau_limit) + d.qfrc_bias[self._dadr]
            self.robot._pre_step()
            mujoco.mj_step(self.model, d)

    @property
    def time(self) -> float:
        return float(self.data.time)

    def success(self) -> dict:
        return success_details(self.model, self.data, self.cfg.scene, self.cfg.success)

    def close(self) -> None:
        self._sim.cleanup()


def main(argv: list[str] | None = None) -> None:
    """Serve a real-time TwinSim until SIGTERM; prints ``READY <host> <shm name> <nq>``."""
    parser = argparse.ArgumentParser(description="serve the twin's scene on franky-sim, real time")
    parser.add_argument("--host", required=True, help="loopback address to serve on")
    parser.add_argument("--config", required=True, help="twin.yaml")
    parser.add_argument("--shm", default=None, help="shared-memory name for the cameras' state")
    parser.add_argument("--seed", type=int, default=0, help="scene seed")
    parser.add_argument(
        "--command-wait-s",
        type=float,
        default=0.02,
        help="how long a tick waits for franky's command before reusing the last (0.5: the loop stays closed under load)",
    )
    args = parser.parse_args(argv)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    cfg = load_twin_config(args.config)
    # a process entry point: its stdout is the READY/STATS protocol SimServer reads (other lines are its log)
    log = lambda m: print(f"[twin sim] {m}", flush=True)
    with TwinSim(cfg, host=args.host, shm_name=args.shm, command_wait_s=args.command_wait_s, log=log).start(
        seed=args.seed
    ) as sim:
        print(f"READY {sim.host} {sim.shm_name} {sim.model.nq}", flush=True)
        start = time.perf_counter()
        while not stop.wait(1.0):  # as the bare server: SimServer.realtime_factor reads these
            print(f"STATS {sim.stats.steps} {time.perf_counter() - start:.3f} {sim.stats.missed_commands}", flush=True)


if __name__ == "__main__":
    main()
