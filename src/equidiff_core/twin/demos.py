"""Scripted-expert demonstrations recorded in-process (``equidiff twin collect --direct``).

Sim (``DirectSim``), the three simulated cameras, the voxeliser and the expert run in this
process on the *sim* clock, faster than real time, and the episode is written with the same
``EpisodeWriter`` and the same topics and message layouts the recorder node writes:
``/voxels`` (5 Hz), ``/franka/ee_pose`` and ``/franka/joint_states`` (100 Hz),
``/franka/command_chunk`` (the expert's one-point teleop-style targets, 20 Hz), ``/tf_static``.
So ``equidiff train`` reads these bags exactly like recorded ones. Stamps are
``epoch + sim time``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from ..config import LabConfig
from ..topics import (
    TOPIC_COMMAND_CHUNK,
    TOPIC_EE_POSE,
    TOPIC_JOINT_STATES,
    TOPIC_VOXELS,
    TRAINING_TOPICS,
)
from .config import TwinConfig
from .metrics import SuccessHold

NS = 1_000_000_000


class DirectRecorder:
    """Everything needed to turn DirectSim states into an episode bag."""

    def __init__(self, cfg: TwinConfig, lab: LabConfig):
        from ..cameras.twin import TwinCamera
        from ..rosmsg import rosbags_factory
        from ..voxels import Voxelizer
        from .sim import DirectSim

        self.cfg, self.lab = cfg, lab
        self.sim = DirectSim(cfg)
        self._qpos = None
        self.cameras = [TwinCamera(cam, state_source=lambda t: (self._qpos, 0.0, self._stamp), paced=False,
                                   twin_config=cfg) for cam in lab.cameras]
        for c in self.cameras:
            c.connect()
        self.voxelizer = Voxelizer(lab.workspace, [c.extrinsics.matrix() for c in lab.cameras])
        self.factory = rosbags_factory()
        self._stamp = 0

    def close(self) -> None:
        for c in self.cameras:
            c.disconnect()
        self.sim.close()

    def voxel_grid(self, stamp_ns: int) -> np.ndarray:
        """The fused grid the voxel node would publish for the current sim state."""
        from ..cameras import limit_depth

        self._qpos, self._stamp = self.sim.data.qpos.copy(), stamp_ns
        frames = []
        for cam, cfg in zip(self.cameras, self.lab.cameras):
            frames.append(limit_depth(cam.read(), cfg.min_depth, cfg.max_depth))
        return self.voxelizer(frames)

    def record(self, path: Path, seed: int, task: str, epoch_ns: int) -> tuple[bool, dict]:
        """Run one expert episode for ``seed`` and write it to ``path``; returns (success, details)."""
        from ..bags import EpisodeMeta
        from ..chunk import PoseChunk, chunk_to_msg
        from ..control import messages as cm
        from ..pointcloud import grid_to_voxel_msg
        from ..recording import EpisodeWriter
        from ..robots.base import ARM_JOINT_NAMES, FINGER_JOINT_NAMES
        from .expert import plan_pick_place, tcp_pose
        from .scene import BLOCK, BOWL, body_pose

        sim, ex, f = self.sim, self.cfg.expert, self.factory
        sim.reset(seed)
        sim.command(tcp_pose(ex.ready_position, 0.0), ex.open_width)
        sim.step(1500)  # the arm is homed before the recording starts, as in the ROS path
        plan = plan_pick_place(sim.tcp_pose(), sim.gripper_width(), body_pose(sim.model, sim.data, BLOCK),
                               body_pose(sim.model, sim.data, BOWL), self.cfg.scene.block_size[2], ex)
        writer = EpisodeWriter(path, EpisodeMeta(task=task, operator="scripted expert (direct)", seed=seed)).open()
        for topic, msgtype in TRAINING_TOPICS.items():
            writer.add_topic(topic, msgtype)
        t0 = sim.time
        writer.write_tf_static(self.lab, epoch_ns)
        frame = self.lab.base_frame
        obs_every = round(1000 / self.lab.observation_hz)
        cmd_every = round(1000 / ex.command_hz)
        state_every = round(1000 / self.lab.robot.state_hz)
        lead_ns = 50_000_000  # teleop's command lead
        step, hold = 0, SuccessHold(self.cfg.success.hold_s)
        end_ms = int((plan.duration + 3.0) * 1000)
        try:
            while step <= end_ms:
                t_ns = epoch_ns + int((sim.time - t0) * NS)
                if step % cmd_every == 0:
                    pose, width = plan.target_at(sim.time - t0)
                    sim.command(pose, width)
                    chunk = PoseChunk(t_ns, np.array([t_ns + lead_ns], np.int64), pose[None], np.array([width]))
                    writer.write(TOPIC_COMMAND_CHUNK, chunk_to_msg(chunk, f, frame), t_ns)
                if step % state_every == 0:
                    tcp = sim.tcp_pose()
                    w = sim.gripper_width()
                    writer.write(TOPIC_EE_POSE, cm.pose_stamped(f, tcp, t_ns, frame), t_ns)
                    q = sim.joint_positions()
                    js = f.make("sensor_msgs/msg/JointState", header=f.header(t_ns, ""),
                                name=[*ARM_JOINT_NAMES, *FINGER_JOINT_NAMES],
                                position=f.float64_array([*map(float, q), w / 2, w / 2]),
                                velocity=f.float64_array([0.0] * 9), effort=f.float64_array([]))
                    writer.write(TOPIC_JOINT_STATES, js, t_ns)
                if step % obs_every == 0:
                    grid = self.voxel_grid(t_ns)
                    ws = self.lab.workspace
                    writer.write(TOPIC_VOXELS, grid_to_voxel_msg(grid, ws.lower, ws.voxel_size, t_ns, frame, f), t_ns)
                    if sim.time - t0 > plan.duration and hold.update(sim.success()["success"], sim.time):
                        break
                sim.step(1)
                step += 1
            details = sim.success()
            writer.close(success=bool(details["success"]), notes=f"scripted expert (direct), seed={seed}")
        except BaseException:
            writer.discard()
            raise
        return bool(details["success"]), details


def collect_direct(cfg: TwinConfig, lab: LabConfig, out: Path, seeds: Iterable[int], task: str = "twin_block_in_bowl",
                   keep_failures: bool = False, log: Callable[[str], None] = print,
                   stop_after: int | None = None) -> list[tuple[int, bool, str]]:
    """Record one bag per seed under ``out``; failed episodes are deleted unless ``keep_failures``;
    stop once ``stop_after`` successful demos exist."""
    import shutil

    from ..recording import next_episode_path

    rec = DirectRecorder(cfg, lab)
    results = []
    try:
        for seed in seeds:
            t0 = time.monotonic()
            path = next_episode_path(out, task)
            ok, _details = rec.record(path, seed, task, epoch_ns=time.time_ns())
            if not ok and not keep_failures:
                shutil.rmtree(path, ignore_errors=True)
            results.append((seed, ok, str(path) if ok or keep_failures else ""))
            log(f"[collect] seed {seed}: {'success' if ok else 'failure'} in {time.monotonic() - t0:.1f} s"
                f"{'' if ok or keep_failures else ' (discarded)'} {path.name}")
            if stop_after is not None and sum(1 for _, s, _ in results if s) >= stop_after:
                break
    finally:
        rec.close()
    return results
