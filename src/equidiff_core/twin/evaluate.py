"""Closed-loop evaluation of a policy in the twin, in-process on the sim clock.

Used by ``equidiff twin evaluate``, ``bench generalization`` and ``bench chunking``: the same
scene, cameras (rendered from the sim state), voxeliser and inference code as the live stack,
but stepped synchronously, so the result does not depend on how fast this machine is. Each
episode is ``episode.run_episode`` (the sequence ``twin run`` and ``twin collect`` run) in a
``demos.DirectWorld`` that records nothing, with ``DirectPolicy`` acting.

Chunks execute exactly as the live stack executes them on simulated time (policy_node +
franka_node, docs/evaluation_scheme.md): an observation is due every ``dt`` (the preset's,
0.2 s: the cameras' frame rate); the policy answers one every ``execute_steps`` of them (0:
``n_action_steps``, policy_node's default). The answer to the observation at t_k (its first
k + ceil(L/dt) + 1 actions, enough to last until the next answer arrives, as policy_node sizes
them; step i stamped t_k + i*dt by ``chunk.chunk_from_actions`` as policy_node does) reaches
franka_node at t_k + ``latency_s`` (the twin's latency budget L);
until then the previous chunk keeps running. franka_node's own ``control.Controller``
(configured by ``config/control.yaml``, ticked at its ``control_hz`` on the sim clock) then
does what it does in the lab: the jump and staleness checks, dropping the steps already due
and replacing the rest of the trajectory from the current setpoint, the watchdog, the
workspace clip and speed limits, the gripper deadband. Its streamed target reaches the sim's
arm at ``COMMAND_HZ``. The policy samples each scene's observations with ``chunk.SamplingSeeds``,
as policy_node does in the live twin. What still differs from the live twin is the arm itself:
DirectSim's IK and joint PD instead of franky's Cartesian impedance tracker in franky-sim;
``replay_chunks`` replays a live run's chunks on this arm to measure what that changes.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from ..chunk import (
    DEFAULT_EXECUTE_STEPS,
    DEFAULT_RTC,
    AnswerSchedule,
    PoseChunk,
    RealTimeChunking,
    SamplingSeeds,
    bridging_execute_steps,
    chunk_from_actions,
    steps_to_publish,
)
from ..config import LabConfig
from ..control import Controller
from ..episode import run_episode
from ..observation import ee_input
from ..robots.base import Robot, RobotError, RobotState
from ..rosmsg import position_from_msg
from ..topics import TOPIC_COMMAND_CHUNK, TOPIC_EE_POSE
from .config import TwinConfig
from .scene import BLOCK, BOWL, body_pose, sample_scene

# Rate at which the controller's newest target is sent to DirectSim.command.
# franka_node streams at control_hz (200 Hz), but every DirectSim.command solves IK (2.2 ms on
# the 2-core EPYC, as much as 5 ms of sim stepping), so 200 Hz would double the sim's cost;
# at 50 Hz it adds ~25 %. Between commands the joint PD holds the last IK target (1 kHz); the
# trajectory moves at most a few mm in 20 ms, within the arm's tracking lag at these speeds.
COMMAND_HZ = 50.0


@dataclass(frozen=True)
class EvalEpisode:
    seed: int
    success: bool
    duration_s: float
    observations: int
    block_yaw_deg: float
    # how far a failure got: the stages of the task the episode reached at some point
    reached: bool = False  # the TCP within REACH_M of the block (horizontally) and below LOW_M above it
    lifted: bool = False  # the block LIFT_M above where it started
    closest_to_bowl_m: float = float("nan")  # nearest the block's centre came to the bowl's axis
    closest_to_block_m: float = float("nan")  # nearest the TCP came to the block's centre


REACH_M, LOW_M, LIFT_M = 0.02, 0.03, 0.03

# The controller's warnings (a rejected chunk, a watchdog hold) are counted in its stats and
# reported once per episode, not logged at every occurrence.
_QUIET = logging.getLogger(__name__ + ".controller")
_QUIET.addHandler(logging.NullHandler())
_QUIET.propagate = False


class _Progress:
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


def evaluate_policy(
    policy,
    cfg: TwinConfig,
    lab: LabConfig,
    seeds: Iterable[int],
    max_duration_s: float = 30.0,
    log: Callable[[str], None] = print,
    recorder=None,
    latency_s: float = 0.1,
    execute_steps: int = DEFAULT_EXECUTE_STEPS,
    publish_steps: int | None = None,
    rtc: bool = DEFAULT_RTC,
    probe=None,
) -> list[EvalEpisode]:
    """Roll ``policy`` (an ``inference.InferencePolicy``) out from each seed's scene; returns per-episode results.

    Each answered observation's chunk takes effect ``latency_s`` after it (default 0.1 s, the
    twin's default budget); the policy answers every ``execute_steps``-th observation (0: every
    ``n_action_steps``-th, policy_node's default) and publishes ``publish_steps`` steps of each
    chunk (None, the default: enough to bridge ``latency_s``, as policy_node given that latency, which
    the live twin passes it, with ``execute_steps`` 0 lowered as policy_node lowers it when L is too
    long for n_action_steps; 0: ``n_action_steps``); with ``rtc`` (default policy_node's) each chunk is
    denoised towards the previous one (``chunk.RealTimeChunking``, its delay from ``latency_s``); see the
    module doc. The policy's sampling seeds are ``chunk.SamplingSeeds``' for the episode's seed. ``probe``
    (e.g. ``twin.chunking.ChunkingProbe``) sees each episode's chunks as franka_node's
    Controller receives them and its every command."""
    from .demos import DirectRecorder, DirectWorld

    preset = policy.preset
    if not (math.isfinite(latency_s) and latency_s >= 0):
        raise ValueError(f"latency_s must be finite and >= 0, got {latency_s}")
    available = preset.horizon - preset.n_obs_steps + 1  # the predicted steps from the observation on
    if publish_steps is None and not execute_steps:  # policy_node's default k while it bridges L
        execute_steps = bridging_execute_steps(preset.n_action_steps, latency_s, preset.dt, available)
    execute_steps = AnswerSchedule(execute_steps, int(preset.n_action_steps), 1).steps  # checked up front
    if publish_steps is None:
        publish_steps = steps_to_publish(execute_steps, latency_s, preset.dt, available)
    if publish_steps and not 1 <= publish_steps <= available:
        raise ValueError(f"publish_steps must be within 1..{available}, got {publish_steps}")
    publish_steps = int(publish_steps) or int(preset.n_action_steps)
    control = _control_config()
    rec = recorder or DirectRecorder(cfg, lab)
    world = DirectWorld(rec)  # records nothing
    results = []
    try:
        for seed in seeds:
            actor = DirectPolicy(
                world, policy, seed, control, max_duration_s, latency_s, execute_steps, publish_steps, rtc, probe
            )
            # settle_s 0: the cameras render the sim state itself, no pipeline to flush; the actor
            # ends the episode at the time limit's observation instant, after it has been judged
            episode = run_episode(world, actor, seed, float("inf"), cfg.success.hold_s, settle_s=0.0)
            progress, t = actor.progress, world.now_s() - actor.t0
            block_yaw = world.scene.block_yaw
            results.append(
                EvalEpisode(
                    seed,
                    episode.success,
                    round(t, 2),
                    actor.observations,
                    round(float(np.degrees(block_yaw)), 1),
                    progress.reached,
                    progress.lifted,
                    round(progress.closest_to_bowl_m, 3),
                    round(progress.closest_to_block_m, 3),
                )
            )
            stats = actor.controller.stats
            control_note = "".join(
                [
                    f"; {stats.rejected_chunks} chunks rejected ({stats.last_rejection})"
                    if stats.rejected_chunks
                    else "",
                    f"; {stats.watchdog_holds} watchdog holds" if stats.watchdog_holds else "",
                    f"; {stats.divergence_stops} divergence stops" if stats.divergence_stops else "",
                ]
            )
            log(
                f"[eval] seed {seed} (block yaw {np.degrees(block_yaw):+.0f} deg): "
                f"{'success' if episode.success else 'failure'} after {t:.1f} s sim, {actor.observations} "
                f"observations; TCP within {progress.closest_to_block_m * 1000:.0f} mm of the block, "
                f"reached it: {'yes' if progress.reached else 'no'}, lifted it: "
                f"{'yes' if progress.lifted else 'no'}, block came within {progress.closest_to_bowl_m * 1000:.0f} mm "
                f"of the bowl's centre{control_note}"
            )
    finally:
        if recorder is None:
            rec.close()
    return results


def _control_config():
    """franka_node's control configuration (config/control.yaml): the scheduler and gripper deadband."""
    from ..config import default_config_dir
    from ..control import load_control_config

    return load_control_config(default_config_dir() / "control.yaml")


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
    """franka_node's own ``Controller`` over DirectSim as an ``episode.Actor`` in a
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
        self.progress = _Progress(sim)
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
            self.sim.step(upcoming - now)
            now = upcoming
        self.now = self.clock.ms = now
        self.progress.update()

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
    """The policy as an ``episode.Actor`` in a ``demos.DirectWorld``: policy_node's answering rule
    and sampling seeds (``chunk.SamplingSeeds`` for the episode's seed, as policy_node's in the
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
    ):
        preset = policy.preset
        super().__init__(
            world, seed, control, max_duration_s, latency_s, preset.dt, preset.n_action_steps, execute_steps, probe
        )
        self.policy, self.publish_steps, self.rtc = policy, publish_steps, rtc
        self.delay_steps = RealTimeChunking.delay_for(latency_s, self.dt_ms / 1000)
        self.seeds = SamplingSeeds()
        self.seeds.start_episode(seed)

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
        if self.chunking is None:
            actions = self.policy.predict(grid, ee, seed=seed)
        else:
            actions = self.policy.predict(grid, ee, seed=seed, guide=self.chunking.guide(stamp_ns, ee))
            self.chunking.remember(stamp_ns, actions)
        self.observations += 1
        chunk = chunk_from_actions(actions[: self.publish_steps], stamp_ns, self.dt_ms * 1_000_000)
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


def _tcp_gaps(actor: RecordedChunks, poses, origin_ns: int) -> list[float]:
    """mm between the replayed TCP and the recorded /franka/ee_pose (within 5 ms) at each observation instant."""
    stamps = poses.header_ns() - origin_ns
    positions = np.array([position_from_msg(m) for m in poses.messages])
    gaps = []
    for ms, tcp in zip(actor.path_ms, actor.path, strict=True):
        i = int(np.argmin(np.abs(stamps - ms * 1_000_000)))
        if abs(stamps[i] - ms * 1_000_000) <= 5_000_000:
            gaps.append(1000 * float(np.linalg.norm(tcp - positions[i])))
    return gaps


@dataclass(frozen=True)
class ReplayedEpisode:
    bag: str
    seed: int
    recorded_success: bool | None  # the bag's outcome (None: not judged)
    success: bool  # the replay's
    reached: bool
    lifted: bool
    chunks: int
    tcp_gap_mean_mm: float  # the replayed TCP against the recorded /franka/ee_pose, same episode time (nan: none)
    tcp_gap_p95_mm: float


def replay_chunks(
    bags: Iterable,
    cfg: TwinConfig,
    lab: LabConfig,
    latency_s: float = 0.1,
    max_duration_s: float | None = None,
    log: Callable[[str], None] = print,
) -> list[ReplayedEpisode]:
    """Replay each twin bag's policy chunks open loop in the in-process twin (``RecordedChunks``) from
    the bag's scene seed, and judge the outcome as the in-process evaluation does.

    Given the very commands the live arm (franky's impedance tracker in franky-sim) got, does the
    in-process arm (DirectSim's IK + joint PD) end the same way? Policy chunks are the bag's
    /franka/command_chunk messages with more than one step (the supervisor's one-point hold
    targets after an episode are not the policy's). The TCP gap compares the replayed TCP with
    the bag's /franka/ee_pose at each observation instant (within 5 ms)."""
    from ..bags import BagError, read_episode
    from ..chunk import ChunkError, chunk_from_msg
    from .demos import DirectRecorder, DirectWorld

    control = _control_config()
    max_duration_s = max_duration_s or cfg.episode.max_duration_s
    rec = DirectRecorder(cfg, lab)
    world = DirectWorld(rec)
    results = []
    try:
        for bag in bags:
            episode = read_episode(bag, [TOPIC_COMMAND_CHUNK, TOPIC_EE_POSE])
            if episode.meta.seed is None:
                raise BagError(f"{bag}: no scene seed in its metadata (only twin episodes can be replayed)")
            try:
                chunks = [c for c in map(chunk_from_msg, episode[TOPIC_COMMAND_CHUNK].messages) if len(c) > 1]
            except ChunkError as err:
                raise BagError(f"{bag}: a malformed chunk on {TOPIC_COMMAND_CHUNK}: {err}") from err
            if not chunks:
                raise BagError(f"{bag}: no policy chunks on {TOPIC_COMMAND_CHUNK}")
            actor = RecordedChunks(world, chunks, episode.meta.seed, control, max_duration_s, latency_s)
            result = run_episode(world, actor, episode.meta.seed, float("inf"), cfg.success.hold_s, settle_s=0.0)
            gaps = _tcp_gaps(actor, episode[TOPIC_EE_POSE], chunks[0].stamp_ns) if TOPIC_EE_POSE in episode else []
            gaps = np.array(gaps) if gaps else np.array([np.nan])
            row = ReplayedEpisode(
                str(bag),
                int(episode.meta.seed),
                episode.meta.success,
                result.success,
                actor.progress.reached,
                actor.progress.lifted,
                len(chunks),
                round(float(np.mean(gaps)), 1),
                round(float(np.percentile(gaps, 95)), 1),
            )
            results.append(row)
            recorded = {True: "success", False: "failure", None: "not judged"}[row.recorded_success]
            log(
                f"[replay] {bag} (seed {row.seed}): recorded {recorded}, replayed "
                f"{'success' if row.success else 'failure'} (reached {'yes' if row.reached else 'no'}, lifted "
                f"{'yes' if row.lifted else 'no'}); {row.chunks} chunks; TCP {row.tcp_gap_mean_mm} mm from the "
                f"recorded one on average, p95 {row.tcp_gap_p95_mm} mm"
            )
    finally:
        rec.close()
    return results


def unseen_yaw_seeds(
    cfg: TwinConfig, train_yaw_deg: tuple[float, float], n: int, start: int = 10_000_000, margin_deg: float = 15.0
) -> list[int]:
    """Seeds whose block yaw lies at least ``margin_deg`` outside the training range, modulo 180 deg.

    The block is a box grasped across its short side: at yaw and yaw + 180 deg it looks and is
    grasped the same, so a yaw 180 deg from the training range is not unseen. The bowl is a
    ring of ``bowl_segments`` walls, the same every 360/segments deg (22.5 for 16), so no bowl
    yaw is unseen by a 15 deg margin and it is left free."""
    lo, hi = train_yaw_deg
    centre, half = (lo + hi) / 2, (hi - lo) / 2 + margin_deg
    if half >= 90.0:
        raise ValueError(
            f"training yaw range {train_yaw_deg} plus a {margin_deg} deg margin leaves no unseen block yaw"
        )
    return _seeds_where(cfg, n, start, lambda yaw: abs(block_yaw_offset_deg(yaw, centre)) > half)


def in_range_yaw_seeds(
    cfg: TwinConfig, train_yaw_deg: tuple[float, float], n: int, start: int = 20_000_000
) -> list[int]:
    """Seeds whose block yaw lies inside the training range (modulo 180 deg, as above): the
    control for ``unseen_yaw_seeds`` (a policy that fails here has not learned the task)."""
    lo, hi = train_yaw_deg
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    return _seeds_where(cfg, n, start, lambda yaw: abs(block_yaw_offset_deg(yaw, centre)) <= half)


def _seeds_where(cfg: TwinConfig, n: int, start: int, keep: Callable[[float], bool]) -> list[int]:
    """The first ``n`` seeds from ``start`` whose scene's block yaw passes ``keep``."""
    seeds, seed = [], start
    while len(seeds) < n:
        if seed - start > 10_000 + 1_000 * n:
            raise ValueError(
                f"only {len(seeds)} of {n} scenes from seed {start} have such a block yaw (is the yaw range empty?)"
            )
        if keep(sample_scene(cfg.scene, seed).block_yaw):
            seeds.append(seed)
        seed += 1
    return seeds


def block_yaw_offset_deg(yaw_rad: float, centre_deg: float = 0.0) -> float:
    """Block yaw minus ``centre_deg``, wrapped to [-90, 90): the box's half-turn symmetry."""
    return float((np.degrees(yaw_rad) - centre_deg + 90.0) % 180.0 - 90.0)


def _distance_to_multiple(x_deg: float, period_deg: float) -> float:
    """|x| to the nearest multiple of ``period_deg`` (degrees)."""
    r = x_deg % period_deg
    return min(r, period_deg - r)


# offset bins (degrees from the training range's centre, modulo the box's half turn) of yaw_breakdown
OFFSET_BINS_DEG = ((0, 15), (15, 30), (30, 45), (45, 60), (60, 75), (75, 90))


def yaw_breakdown(episodes: list[EvalEpisode], train_yaw_deg: tuple[float, float]) -> dict:
    """Success by what EquiDiff's symmetry covers, from each episode's block yaw offset to the training
    range's centre (modulo 180 deg: the box's half turn):

    * ``mod90``: ``within`` where the offset lies within the range's half-width of a multiple of 90 deg
      (C4, exact on the voxel grid, maps the block into the training range), ``outside`` the rest;
    * ``mod45``: the same about multiples of 45 deg (C8's other elements, only approximate on the grid);
    * ``by_offset_deg``: |offset| in 15-degree bins.

    Each entry: ``{"episodes", "solved"}``. The scene's other parts (block position, bowl, the arm's
    start) are not rotated with the block, so a covered yaw is not the same scene as a trained one."""
    lo, hi = train_yaw_deg
    centre, half = (lo + hi) / 2, (hi - lo) / 2

    def tally(keep) -> dict:
        chosen = [e for e in episodes if keep(e)]
        return {"episodes": len(chosen), "solved": sum(e.success for e in chosen)}

    def offset(e: EvalEpisode) -> float:
        return abs((e.block_yaw_deg - centre + 90.0) % 180.0 - 90.0)

    result = {}
    for label, period in (("mod90", 90.0), ("mod45", 45.0)):
        result[label] = {
            "within": tally(lambda e, p=period: _distance_to_multiple(offset(e), p) <= half),
            "outside": tally(lambda e, p=period: _distance_to_multiple(offset(e), p) > half),
        }
    result["by_offset_deg"] = {
        f"{a}-{b}": tally(lambda e, a=a, b=b: a <= offset(e) < b or (b == 90 and offset(e) == 90))
        for a, b in OFFSET_BINS_DEG
    }
    return result
