"""Chunks executed in-process on the sim clock: franka_node's own ``Controller`` over DirectSim as a ``twin.episode.Actor``.

``DirectPolicy`` answers observations with the policy (``evaluate.evaluate_policy``),
``RecordedChunks`` replays a recorded episode's chunks (``evaluate.replay_chunks``); both track
how far the episode got (``EpisodeProgress``). See ``evaluate``'s module doc for the timing.
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

from ..control import Controller
from ..perception.observation import ee_input
from ..policy.doubt import DoubtTracker
from ..robots.base import Robot, RobotError, RobotState
from ..wire.chunk import AnswerSchedule, ChunkError, PoseChunk, RealTimeChunking, SamplingSeeds, chunk_from_actions
from .scene import BLOCK, BOWL, body_pose

# Rate at which the controller's newest target is sent to DirectSim.command.
# franka_node streams at control_hz (200 Hz), but every DirectSim.command solves IK, which costs
# as much as several ms of sim stepping, so 200 Hz would double the sim's cost (docs/evaluation_scheme.md
# has the figures). Between commands the joint PD holds the last IK target (1 kHz); the
# trajectory moves at most a few mm in 20 ms, within the arm's tracking lag at these speeds.
COMMAND_HZ = 50.0

REACH_M, LOW_M, LIFT_M = 0.02, 0.03, 0.03

# The controller's warnings (a rejected chunk, a watchdog hold) are counted in its stats and
# reported once per episode, not logged at every occurrence.
_QUIET = logging.getLogger(__name__ + ".controller")
_QUIET.addHandler(logging.NullHandler())
_QUIET.propagate = False


class EpisodeProgress:
    """Tracks the stages an episode reaches, from the sim's block, bowl and TCP poses."""

    def __init__(self, sim):
        self.sim = sim
        self.block_z0 = self._position(BLOCK)[2]
        self.reached = self.lifted = False
        self.closest_to_bowl_m = self.closest_to_block_m = float("inf")

    def _position(self, body: str) -> np.ndarray:
        return body_pose(self.sim.model, self.sim.data, body)[:3, 3]

    def update(self) -> None:
        block, bowl, tcp = self._position(BLOCK), self._position(BOWL), self.sim.tcp_pose()[:3, 3]
        self.reached |= bool(np.hypot(*(tcp[:2] - block[:2])) < REACH_M and tcp[2] - block[2] < LOW_M)
        self.lifted |= bool(block[2] - self.block_z0 > LIFT_M)
        self.closest_to_bowl_m = min(self.closest_to_bowl_m, float(np.hypot(*(block[:2] - bowl[:2]))))
        self.closest_to_block_m = min(self.closest_to_block_m, float(np.linalg.norm(tcp - block)))


class _SimClock:
    """The evaluation's clock for franka_node's ``Controller``: the episode's integer-ms sim time."""

    def __init__(self):
        self.ms = 0

    def now_ns(self) -> int:
        return self.ms * 1_000_000

    def sleep_until(self, t_ns: int, stop) -> bool:  # the Controller runs without its thread here
        raise RuntimeError("the evaluation ticks the controller itself")


class _DirectArm(Robot):
    """DirectSim behind the ``Robot`` interface, so franka_node's own ``Controller`` (watchdog,
    safety filter, jump check, gripper deadband) drives it. The streamed target reaches the
    sim at ``COMMAND_HZ`` (see there), when the evaluation calls ``send``."""

    def __init__(self, sim, width: float):
        self.sim = sim
        self.target: np.ndarray | None = None
        self.width = float(width)

    def connect(self) -> None:
        pass

    def disconnect(self) -> None:
        pass

    @property
    def is_connected(self) -> bool:
        return True

    def read_state(self) -> RobotState:
        return self.sim.robot_state()

    def move_to(self, pose: np.ndarray) -> None:
        raise RobotError("the evaluation homes the arm itself")

    def start_streaming(self) -> None:
        pass

    def stream_target(self, pose: np.ndarray, linear_velocity: np.ndarray, angular_velocity: np.ndarray) -> None:
        self.target = pose

    def stop_streaming(self) -> None:
        pass

    def move_gripper(self, width: float) -> None:
        self.width = float(width)

    def recover(self) -> str:
        return ""

    @property
    def has_errors(self) -> bool:
        return False

    def send(self) -> None:
        """The newest streamed target and gripper width to the sim (solves the IK)."""
        if self.target is not None:
            self.sim.command(self.target, self.width)


class _DirectExecution:
    """franka_node's own ``Controller`` over DirectSim as a ``twin.episode.Actor`` in a
    ``demos.DirectWorld``, on simulated time (1 ms sim ticks), executing the chunks ``observe``
    queues; ``DirectPolicy`` answers observations with the policy, ``RecordedChunks`` replays a
    recorded episode's chunks.

    Four event streams on one integer-millisecond clock from the episode's start: observations
    every dt (success is judged at each but the first, as the supervisor does; every
    ``execute_steps``-th is answered); each answered observation's chunk reaching the Controller
    ``latency_s`` later (several can be in flight when latency_s > the answering period); the
    controller's ticks at control_hz; and its newest target sent to the sim at COMMAND_HZ. The
    episode ends at the first observation instant at or past ``max_duration_s`` (judged first)."""

    def __init__(
        self,
        world,
        seed: int,
        control,
        max_duration_s: float,
        latency_s: float,
        dt_s: float,
        n_action_steps: int,
        execute_steps: int,
        probe=None,
    ):
        self.world, self.sim, self.seed, self.control = world, world.sim, seed, control
        self.dt_ms = round(float(dt_s) * 1000)
        self.latency_ms = round(latency_s * 1000)
        self.tick_ms = max(1, round(1000 / control.control_hz))
        self.cmd_ms = max(self.tick_ms, round(1000 / COMMAND_HZ))
        self.max_ms = round(max_duration_s * 1000)
        self.n_action_steps, self.execute_steps, self.probe = int(n_action_steps), execute_steps, probe
        self.observations = 0
        self.finished = False

    def begin(self) -> float:
        sim = self.sim
        if self.probe is not None:
            self.probe.start_episode(self.seed)
        self.t0 = sim.time
        self.progress = EpisodeProgress(sim)
        self.clock, self.arm = _SimClock(), _DirectArm(sim, self.world.rec.cfg.expert.open_width)
        self.controller = Controller(
            self.arm,
            self.world.lab.safety_box,
            self.control,
            clock=self.clock,
            logger=_QUIET,
            on_command=None if self.probe is None else self.probe.command,
        )
        self.controller.start(home=False, thread=False)  # the arm is at the ready pose: hold it, as franka_node does
        self.pending: deque = deque()  # (ms at which it arrives, PoseChunk), in order
        self.answers = AnswerSchedule(self.execute_steps, self.n_action_steps, self.dt_ms * 1_000_000)
        self.now = self.next_obs = self.next_tick = self.next_cmd = 0
        return self.t0

    def observe(self, stamp_ns: int) -> None:
        """Answer the observation at ``stamp_ns`` (the current sim state): queue its chunk in ``pending``."""
        raise NotImplementedError

    def advance(self) -> None:
        if self.now >= self.max_ms:
            self.finished = True
            return
        stamp = self.now * 1_000_000
        if self.answers.due(stamp):
            self.answers.answer(stamp)
            self.observe(stamp)
        self.next_obs += self.dt_ms
        pending, now = self.pending, self.now
        while now < self.next_obs:
            self.clock.ms = now
            while pending and pending[0][0] <= now:  # a chunk arrives: franka_node's subscription callback
                chunk = pending.popleft()[1]
                accepted = self.controller.submit(chunk)
                if self.probe is not None:
                    self.probe.chunk(self.clock.now_ns(), chunk, accepted)
            if now >= self.next_tick:
                self.controller.tick()
                self.next_tick += self.tick_ms
            if now >= self.next_cmd:
                self.arm.send()
                self.next_cmd += self.cmd_ms
            upcoming = min(self.next_obs, self.next_tick, self.next_cmd, pending[0][0] if pending else self.next_obs)
            self.step_sim(upcoming - now)
            now = upcoming
        self.now = self.clock.ms = now
        self.progress.update()

    def step_sim(self, ms: int) -> None:
        """Advance the sim ``ms`` milliseconds (a recording subclass steps its world instead, one ms at a time)."""
        self.sim.step(ms)

    def judging(self) -> bool:
        return self.now > 0

    def done(self) -> bool:
        return self.finished

    def stalled(self) -> str:
        return ""  # one process, one clock: nothing can fail to deliver

    def end(self) -> None:
        if self.probe is not None:
            self.probe.end_episode()


class DirectPolicy(_DirectExecution):
    """The policy as a ``twin.episode.Actor`` in a ``demos.DirectWorld``: policy_node's answering rule
    and sampling seeds (``wire.chunk.SamplingSeeds`` for the episode's seed, as policy_node's in the
    live twin) and franka_node's own ``Controller`` over DirectSim (``_DirectExecution``)."""

    def __init__(
        self,
        world,
        policy,
        seed: int,
        control,
        max_duration_s: float,
        latency_s: float,
        execute_steps: int,
        publish_steps: int,
        rtc: bool,
        probe=None,
        doubt_samples: int = 1,
        on_doubt=None,
    ):
        preset = policy.preset
        super().__init__(
            world, seed, control, max_duration_s, latency_s, preset.dt, preset.n_action_steps, execute_steps, probe
        )
        self.policy, self.publish_steps, self.rtc = policy, publish_steps, rtc
        self.delay_steps = RealTimeChunking.delay_for(latency_s, self.dt_ms / 1000)
        self.seeds = SamplingSeeds()
        self.seeds.start_episode(seed)
        # policy_node's doubt of each chunk (policy.doubt), from doubt_samples samples per observation;
        # on_doubt(seed, ChunkDoubt, samples (K, horizon, 10)) sees each
        self.doubt_samples, self.on_doubt = int(doubt_samples), on_doubt
        self.doubt = DoubtTracker(self.dt_ms * 1_000_000)
        self.failed_predictions = 0  # answers policy_node would have skipped: no valid chunk in them

    def begin(self) -> float:
        t0 = super().begin()
        # policy_node's rtc: a previous chunk farther from the TCP than franka_node's jump limit was rejected
        max_gap_m = self.control.safety.max_first_step_jump_m
        self.chunking = RealTimeChunking(self.delay_steps, self.dt_ms * 1_000_000, max_gap_m) if self.rtc else None
        return t0

    def observe(self, stamp_ns: int) -> None:
        """Answer the observation at ``stamp_ns`` (the current sim state): its chunk is due ``latency_s`` later."""
        sim = self.sim
        grid = self.world.rec.voxel_grid(stamp_ns)
        ee = ee_input(sim.tcp_pose(), sim.gripper_width())  # the state at the stamp itself: no matching needed
        seed = self.seeds.next()
        guided = {} if self.chunking is None else {"guide": self.chunking.guide(stamp_ns, ee)}
        if self.doubt_samples > 1:
            samples = self.policy.predict_samples(grid, ee, self.doubt_samples, seed=seed, **guided)
        else:  # plain predict, as before the doubt (a scripted stand-in need not take a guide)
            samples = self.policy.predict(grid, ee, seed=seed, **guided)[None]
        actions = samples[0]
        if self.chunking is not None:
            self.chunking.remember(stamp_ns, actions)
        doubt = self.doubt.update(stamp_ns, samples)
        if self.on_doubt is not None:
            self.on_doubt(self.seed, doubt, samples)
        self.observations += 1
        try:
            chunk = chunk_from_actions(actions[: self.publish_steps], stamp_ns, self.dt_ms * 1_000_000)
        except ChunkError:  # as policy_node: a bad prediction is skipped (counted per episode), the chunk runs on
            self.failed_predictions += 1
            return
        self.pending.append((self.now + self.latency_ms, chunk))


class RecordedChunks(_DirectExecution):
    """A recorded episode's policy chunks, replayed open loop through franka_node's own
    ``Controller`` over DirectSim: each reaches the Controller at its observation's time +
    ``latency_s``, on the episode clock that starts at the first chunk's observation. So the same
    commands drive the in-process arm that drove the recorded one (``replay_chunks``)."""

    def __init__(self, world, chunks: list[PoseChunk], seed: int, control, max_duration_s: float, latency_s: float):
        if not chunks:
            raise ValueError("no chunks to replay")
        steps = chunks[0].times_ns
        dt_s = (steps[1] - steps[0]) / 1e9 if len(steps) > 1 else 0.2
        # answer every observation: the recorded chunks are queued up front, nothing is inferred
        super().__init__(world, seed, control, max_duration_s, latency_s, dt_s, 1, 1)
        self.recorded = chunks
        self.path_ms: list[int] = []  # episode ms of each observation instant
        self.path: list[np.ndarray] = []  # the TCP position there

    def begin(self) -> float:
        t0 = super().begin()
        origin = self.recorded[0].stamp_ns
        for chunk in self.recorded:
            moved = PoseChunk(chunk.stamp_ns - origin, chunk.times_ns - origin, chunk.poses, chunk.widths)
            self.pending.append((round(moved.stamp_ns / 1e6) + self.latency_ms, moved))
        return t0

    def observe(self, stamp_ns: int) -> None:
        self.path_ms.append(self.now)
        self.path.append(self.sim.tcp_pose()[:3, 3].copy())
