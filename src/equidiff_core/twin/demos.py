"""Scripted-expert demonstrations recorded in-process (``equidiff twin collect --direct``).

Sim (``DirectSim``), the three simulated cameras, the voxeliser and the expert run in this
process on the *sim* clock, faster than real time, and the episode is written with the same
``EpisodeWriter`` and the same topics and message layouts the recorder node writes:
``/voxels`` (5 Hz), ``/franka/ee_pose`` and ``/franka/joint_states`` (100 Hz),
``/franka/command_chunk`` (the expert's one-point teleop-style targets, 20 Hz), ``/tf_static``,
and each camera's JPEG colour image on ``/cameras/<name>/color/image_raw/compressed`` at the
observation instants (the frames the grid was fused from, as camera_node publishes them).
So ``equidiff train`` and ``equidiff export lerobot`` read these bags exactly like recorded ones. Stamps are
``epoch + sim time``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from ..cameras import limit_depth
from ..cameras.color import color_image_msg
from ..cameras.twin import TwinCamera
from ..config import LabConfig
from ..data.bags import EpisodeMeta
from ..data.recording import EpisodeWriter, next_episode_path
from ..perception.voxels import Voxelizer
from ..wire import rosmsg
from ..wire.chunk import PoseChunk, chunk_to_msg
from ..wire.pointcloud import grid_to_voxel_msg
from ..wire.topics import (
    COMPRESSED_IMAGE_TYPE,
    TOPIC_COMMAND_CHUNK,
    TOPIC_EE_POSE,
    TOPIC_JOINT_STATES,
    TOPIC_VOXELS,
    TRAINING_TOPICS,
    camera_color_topic,
)
from .config import TwinConfig
from .episode import run_episode
from .expert import plan_pick_place, tcp_pose
from .scene import BLOCK, BOWL, body_pose, scene_record
from .sim import DirectSim


class DirectRecorder:
    """Everything needed to turn DirectSim states into an episode bag.

    With ``reuse_instant`` a second ``voxel_grid`` call at the same sim instant returns the first's grid: a
    recorded roll-out (``twin.corrections``) asks twice, for the bag and for the policy, which must see the
    same grid, and the second must draw no new depth noise."""

    def __init__(self, cfg: TwinConfig, lab: LabConfig, reuse_instant: bool = False):
        self.cfg, self.lab, self.reuse_instant = cfg, lab, reuse_instant
        self.sim = DirectSim(cfg)
        self._qpos = None
        self.cameras = [
            TwinCamera(cam, state_source=lambda t: (self._qpos, 0.0, self._stamp), paced=False, twin_config=cfg)
            for cam in lab.cameras
        ]
        for c in self.cameras:
            c.connect()
        self.voxelizer = Voxelizer(lab.workspace, [c.extrinsics.matrix() for c in lab.cameras])
        self.factory = rosmsg.rosbags_factory()
        self._stamp = 0
        self.images: list[np.ndarray | None] = []  # each camera's colour image of the latest grid
        self._grid_at: tuple[float, np.ndarray] | None = None  # (sim time, grid) of the latest grid

    def reset(self, seed: int):
        """The sim at the seed's scene (``DirectSim.reset``, its ``ScenePoses`` returned) and each camera's
        depth noise started from the seed, so an episode is the same whatever ran before it."""
        for c in self.cameras:
            c.reseed(seed)
        self._grid_at = None
        return self.sim.reset(seed)

    def close(self) -> None:
        for c in self.cameras:
            c.disconnect()
        self.sim.close()

    def voxel_grid(self, stamp_ns: int) -> np.ndarray:
        """The fused grid the voxel node would publish for the current sim state (with ``reuse_instant``, the
        same one again when asked twice at one sim instant)."""

        if self.reuse_instant and self._grid_at is not None and self._grid_at[0] == self.sim.time:
            return self._grid_at[1]
        self._qpos, self._stamp = self.sim.data.qpos.copy(), stamp_ns
        frames = []
        for cam, cfg in zip(self.cameras, self.lab.cameras):
            frames.append(limit_depth(cam.read(), cfg.min_depth, cfg.max_depth))
        self.images = [f.image for f in frames]
        grid = self.voxelizer(frames)
        self._grid_at = (self.sim.time, grid)
        return grid


class DirectWorld:
    """The in-process twin as a ``twin.episode.EpisodeWorld``: DirectSim, its cameras and an
    ``EpisodeWriter`` on the sim clock, writing what recorder_node would record.

    While recording, ``step`` writes /franka/ee_pose and /franka/joint_states at the robot's
    state rate, /voxels and (``record_images``) each camera's colour image at the observation rate;
    ``command`` sends a teleop-style target and writes it as /franka/command_chunk. Stamps are ``epoch_ns`` + sim time since the start.
    Without ``out`` it records nothing (the in-process evaluation, ``twin.evaluate``)."""

    def __init__(
        self,
        rec: DirectRecorder,
        out: Path | None = None,
        task: str = "",
        epoch_ns: int = 0,
        operator: str = "",
        record_images: bool = True,
    ):
        self.rec, self.sim, self.lab = rec, rec.sim, rec.lab
        self.record_images = record_images
        self.out, self.task, self.epoch_ns, self.operator = out, task, epoch_ns, operator
        self.seed: int | None = None
        self.scene = None  # the seed's ScenePoses
        self.writer = None
        self.path: Path | None = None
        self.ms = 0  # sim ms since the recording started
        self.t0 = 0.0
        self.state_every = round(1000 / self.lab.robot.state_hz)
        self.obs_every = round(1000 / self.lab.observation_hz)

    def home(self) -> None:
        """Nothing to do here: ``DirectSim.reset`` re-poses the arm, so ``reset_scene`` homes after it."""

    def reset_scene(self, seed: int) -> None:
        ex = self.rec.cfg.expert
        self.seed = seed
        self.scene = self.rec.reset(seed)  # puts the arm back at its initial posture ...
        self.sim.command(tcp_pose(ex.ready_position, 0.0), ex.open_width)
        self.sim.step(1500)  # ... from which it reaches the ready pose, where the live twin's homing leaves it

    def settle(self, seconds: float) -> None:
        self.sim.step(round(seconds * 1000))

    def now_s(self) -> float:
        return self.sim.time

    def success(self) -> bool:
        return bool(self.sim.success()["success"])

    def start_recording(self) -> str:
        if self.out is None:
            return ""
        self.path = next_episode_path(self.out, self.task)
        meta = EpisodeMeta(
            task=self.task, operator=self.operator, seed=self.seed, extra=scene_record(self.rec.cfg.scene, self.scene)
        )
        self.writer = EpisodeWriter(self.path, meta).open()
        for topic, msgtype in TRAINING_TOPICS.items():
            self.writer.add_topic(topic, msgtype)
        if self.record_images:
            for cam in self.lab.cameras:
                self.writer.add_topic(camera_color_topic(cam.name), COMPRESSED_IMAGE_TYPE)
        self.writer.write_tf_static(self.lab, self.epoch_ns)
        self.ms, self.t0 = 0, self.sim.time
        return str(self.path)

    def stop_recording(self, keep: bool, success: bool, note: str) -> None:
        writer, self.writer = self.writer, None
        if writer is None:
            return
        if keep:
            writer.close(success=success, notes=note)
        else:
            writer.discard()

    def stamp_ns(self) -> int:
        return self.epoch_ns + int((self.sim.time - self.t0) * rosmsg.NS_PER_S)

    def command(self, pose: np.ndarray, width: float, lead_ns: int = 50_000_000) -> None:
        """Send a target reached ``lead_ns`` later (teleop's lead) and record it as a one-point chunk."""

        t_ns = self.stamp_ns()
        self.sim.command(pose, width)
        chunk = PoseChunk(t_ns, np.array([t_ns + lead_ns], np.int64), pose[None], np.array([width]))
        self.writer.write(TOPIC_COMMAND_CHUNK, chunk_to_msg(chunk, self.rec.factory, self.lab.base_frame), t_ns)

    def step(self) -> None:
        """Write the messages due at this instant, then advance 1 ms."""

        sim, f, frame, t_ns = self.sim, self.rec.factory, self.lab.base_frame, self.stamp_ns()
        if self.ms % self.state_every == 0:  # the messages franka_node publishes
            state = sim.robot_state(t_ns)
            self.writer.write(TOPIC_EE_POSE, rosmsg.pose_stamped(f, state.ee_pose, t_ns, frame), t_ns)
            self.writer.write(TOPIC_JOINT_STATES, rosmsg.joint_state(f, state, t_ns), t_ns)
        if self.ms % self.obs_every == 0:
            ws = self.lab.workspace
            grid = self.rec.voxel_grid(t_ns)
            self.writer.write(TOPIC_VOXELS, grid_to_voxel_msg(grid, ws.lower, ws.voxel_size, t_ns, frame, f), t_ns)
            if self.record_images:
                for cam, image in zip(self.lab.cameras, self.rec.images):
                    msg = color_image_msg(image, t_ns, cam.frame_id, f)
                    self.writer.write(camera_color_topic(cam.name), msg, t_ns, COMPRESSED_IMAGE_TYPE)
        sim.step(1)
        self.ms += 1


class DirectExpert:
    """The scripted expert as a ``twin.episode.Actor`` in a ``DirectWorld``: its plan's target every
    1/``command_hz``, success judged at each observation instant once the plan is done, and
    ``extra_s`` after it at most."""

    def __init__(self, world: DirectWorld, extra_s: float = 3.0):
        self.world, self.extra_s = world, extra_s
        self.cmd_every = round(1000 / world.rec.cfg.expert.command_hz)
        self.plan = None

    def begin(self) -> float:
        sim, cfg = self.world.sim, self.world.rec.cfg
        self.plan = plan_pick_place(
            sim.tcp_pose(),
            sim.gripper_width(),
            body_pose(sim.model, sim.data, BLOCK),
            body_pose(sim.model, sim.data, BOWL),
            cfg.scene.block_size[2],
            cfg.expert,
        )
        self.t0 = sim.time
        return self.t0

    def advance(self) -> None:
        world = self.world
        while True:
            if world.ms % self.cmd_every == 0:
                world.command(*self.plan.target_at(world.sim.time - self.t0))
            world.step()
            if world.ms % world.obs_every == 0:
                return

    def judging(self) -> bool:
        return self.world.sim.time - self.t0 > self.plan.duration

    def done(self) -> bool:
        return self.world.sim.time - self.t0 > self.plan.duration + self.extra_s

    def stalled(self) -> str:
        return ""  # one process, one clock: nothing can fail to deliver

    def end(self) -> None:
        pass  # the next reset re-poses the arm


def collect_direct(
    cfg: TwinConfig,
    lab: LabConfig,
    out: Path,
    seeds: Iterable[int],
    task: str = "twin_block_in_bowl",
    keep_failures: bool = False,
    log: Callable[[str], None] = print,
    stop_after: int | None = None,
) -> list[tuple[int, bool, str]]:
    """Record one bag per seed under ``out`` (``twin.episode.run_episode`` with the scripted expert);
    failed episodes are deleted unless ``keep_failures``; stop once ``stop_after`` successful
    demos exist."""

    rec = DirectRecorder(cfg, lab)
    world = DirectWorld(rec, out, task, epoch_ns=time.time_ns(), operator="scripted expert (direct)")
    results = []
    try:
        for seed in seeds:
            t0 = time.monotonic()
            world.epoch_ns = time.time_ns()
            result = run_episode(
                world,
                DirectExpert(world),
                seed,
                float("inf"),
                cfg.success.hold_s,
                keep=lambda ok: ok or keep_failures,
                note="scripted expert (direct)",
            )
            results.append((seed, result.success, result.bag))
            log(
                f"[collect] seed {seed}: {'success' if result.success else 'failure'} in "
                f"{time.monotonic() - t0:.1f} s{'' if result.bag else ' (discarded)'} {world.path.name}"
            )
            if stop_after is not None and sum(1 for _, s, _ in results if s) >= stop_after:
                break
    finally:
        rec.close()
    return results
