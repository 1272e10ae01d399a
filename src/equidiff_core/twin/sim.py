"""Running the twin: franky-sim's server with the task scene in a real-time loop, or a direct sim.

``TwinSim`` serves libfranka's protocol (franky connects to ``host`` exactly as to a real
FR3). franky-sim's stock ``run_async`` sleeps "1 ms minus compute" and drifts 8-16 % slow
(NOTES.md); our loop sleeps to fixed 1 ms deadlines instead and skips ahead (counting the
overrun) when it falls more than ``max_lag_s`` behind, so sim time tracks wall time.

``DirectSim`` is the same scene with no server and no clock: franky-sim's own Cartesian
controller is driven in-process and stepped as fast as the CPU allows (tests, fast expert
roll-outs).
"""

from __future__ import annotations

import math
import socket
import threading
import time
from dataclasses import dataclass

import numpy as np

from .config import TwinConfig
from .scene import ScenePoses, apply_scene, object_state, sample_scene, success_details
from .shared_state import StateWriter


def free_loopback_host(seed: int | None = None) -> str:
    """A 127.x.y.z address whose libfranka port (1337) is free, so parallel twins do not collide."""
    rng = np.random.default_rng(seed)
    for _ in range(50):
        host = f"127.{rng.integers(1, 255)}.{rng.integers(0, 255)}.{rng.integers(2, 255)}"
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind((host, 1337))
            except OSError:
                continue
        return host
    raise RuntimeError("no free loopback address for franky-sim")


@dataclass
class LoopStats:
    steps: int = 0
    overruns: int = 0  # times the loop fell behind and skipped ahead
    started: float = 0.0

    def steps_per_s(self) -> float:
        dt = time.monotonic() - self.started
        return self.steps / dt if dt > 0 else 0.0


class TwinSim:
    """franky-sim + task scene + real-time loop + shared-memory state for the cameras."""

    def __init__(self, cfg: TwinConfig, host: str | None = None, shm_name: str | None = None,
                 max_lag_s: float = 0.05):
        self.cfg = cfg
        self.host = host or cfg.sim.host
        if self.host == "auto":
            self.host = free_loopback_host()
        self.shm_name = shm_name
        self.max_lag_s = max_lag_s
        self.lock = threading.Lock()  # held while stepping; take it to read or edit sim state
        self.stats = LoopStats()
        self.poses: ScenePoses | None = None
        self._sim = self._robot = self._server = self._writer = None
        self._thread: threading.Thread | None = None
        self._running = False

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self, seed: int = 0) -> "TwinSim":
        from franky_sim import SimulationServer

        from .scene import build_simulator

        self._sim, self._robot = build_simulator(self.cfg)
        self._sim.init()
        self._server = SimulationServer(self._sim, hostname_candidates=[self.host])
        self._server.init()  # binds host:1337 and starts the simulation
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

    # -- the loop ----------------------------------------------------------------------------
    def _loop(self) -> None:
        period = 0.001
        state_every = max(1, round(1.0 / (self.cfg.sim.state_hz * period)))
        self.stats = LoopStats(started=time.monotonic())
        deadline = time.monotonic()
        while self._running:
            with self.lock:
                self._server.run_once(realtime=False)
                self.stats.steps += 1
                if self.stats.steps % state_every == 0:
                    self._publish_state()
            deadline += period
            lag = time.monotonic() - deadline
            if lag < 0:
                time.sleep(-lag)
            elif lag > self.max_lag_s:  # hopelessly behind (CPU starved): do not sprint to catch up
                self.stats.overruns += 1
                deadline = time.monotonic()

    def _publish_state(self) -> None:
        self._writer.write(self.data.qpos, float(self.data.time), time.time_ns())

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
            sim_time = float(self.data.time)
        return {"seed": self.poses.seed if self.poses else None, "sim_time": round(sim_time, 4),
                "success": details["success"], "details": details, "objects": objects,
                "steps_per_s": round(self.stats.steps_per_s(), 1), "overruns": self.stats.overruns,
                "host": self.host}


class DirectSim:
    """The twin scene driven in-process by franky-sim's Cartesian controller, as fast as possible.

    ``command(pose, width)`` sets the TCP target (4x4, base frame) and gripper width; ``step(n)``
    advances n ms. The physics (contacts, gripper PD, arm PD on the IK solution) is franky-sim's.
    """

    def __init__(self, cfg: TwinConfig):
        from .scene import build_simulator

        self.cfg = cfg
        self._sim, self.robot = build_simulator(cfg)
        self._sim.init()
        self._sim.start()
        self.model, self.data = self._sim.model, self._sim.data
        self._target = None
        self._width = 0.08
        self.poses: ScenePoses | None = None

    def reset(self, seed: int) -> ScenePoses:
        import mujoco

        from franky_sim.mujoco_simulator import FrankaMujocoRobot  # noqa: F401  (type only)

        r = self.robot
        for addr, q in zip(r._qpos_addrs, self.cfg.sim.initial_q):  # noqa: SLF001
            self.data.qpos[addr] = q
        for addr in r._finger_qpos_addrs:  # noqa: SLF001
            self.data.qpos[addr] = 0.04
        self.data.qvel[:] = 0.0
        self.poses = sample_scene(self.cfg.scene, seed)
        apply_scene(self.model, self.data, self.poses, self.cfg.scene)
        mujoco.mj_forward(self.model, self.data)
        self._target = self.tcp_pose()
        self._width = 0.08
        return self.poses

    def tcp_pose(self) -> np.ndarray:
        q = np.array([self.data.qpos[a] for a in self.robot._qpos_addrs])  # noqa: SLF001
        return np.asarray(self.robot.kinematics(q).homogeneous)

    def gripper_width(self) -> float:
        return float(self.robot.hand_width)

    def command(self, pose: np.ndarray, width: float) -> None:
        self._target = np.asarray(pose, dtype=float)
        self._width = float(width)

    def step(self, n: int = 1) -> None:
        from scipy.spatial.transform import Rotation

        quat = Rotation.from_matrix(self._target[:3, :3]).as_quat()
        target = np.concatenate([self._target[:3, 3], quat])
        self.robot.set_hand_goal(self._width, 0.05, 70.0)
        for _ in range(n):
            self.robot.cartesian_position_control(target, None)
            self._sim.step()

    @property
    def time(self) -> float:
        return float(self.data.time)

    def success(self) -> dict:
        return success_details(self.model, self.data, self.cfg.scene, self.cfg.success)

    def close(self) -> None:
        self._sim.cleanup()


def wrap_to_pi(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi
