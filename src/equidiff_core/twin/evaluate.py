"""Closed-loop evaluation of a policy in the twin, in-process on the sim clock.

Used by ``equidiff twin evaluate``, ``bench generalization`` and ``bench chunking``: the same
scene, cameras (rendered from the sim state), voxeliser and inference code as the live stack,
but stepped synchronously, so the result does not depend on how fast this machine is. Each
episode is ``twin.episode.run_episode`` (the sequence ``twin run`` and ``twin collect`` run) in a
``demos.DirectWorld`` that records nothing, with ``direct_execution.DirectPolicy`` acting.

Chunks execute exactly as the live stack executes them on simulated time (policy_node +
franka_node, docs/evaluation_scheme.md): an observation is due every ``dt`` (the preset's,
0.2 s: the cameras' frame rate); the policy answers one every ``execute_steps`` of them (0:
``n_action_steps``, policy_node's default). The answer to the observation at t_k (its first
k + ceil(L/dt) + 1 actions, enough to last until the next answer arrives, as policy_node sizes
them; step i stamped t_k + i*dt by ``wire.chunk.chunk_from_actions`` as policy_node does) reaches
franka_node at t_k + ``latency_s`` (the twin's latency budget L);
until then the previous chunk keeps running. franka_node's own ``control.Controller``
(configured by ``config/control.yaml``, ticked at its ``control_hz`` on the sim clock) then
does what it does in the lab: the jump and staleness checks, dropping the steps already due
and replacing the rest of the trajectory from the current setpoint, the watchdog, the
workspace clip and speed limits, the gripper deadband. Its streamed target reaches the sim's
arm at ``COMMAND_HZ``. The policy samples each scene's observations with ``wire.chunk.SamplingSeeds``,
as policy_node does in the live twin. What still differs from the live twin is the arm itself:
DirectSim's IK and joint PD instead of franky's Cartesian impedance tracker in franky-sim;
``replay_chunks`` replays a live run's chunks on this arm to measure what that changes.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
import torch

from ..config import LabConfig
from ..policy.chunk_sizing import ChunkSizing
from ..wire.chunk import DEFAULT_EXECUTE_STEPS, DEFAULT_RTC, DEFAULT_TRANSPORT_S, AnswerSchedule
from ..wire.rosmsg import position_from_msg
from ..wire.topics import TOPIC_COMMAND_CHUNK, TOPIC_EE_POSE
from .config import TwinConfig
from .direct_execution import (
    DirectPolicy,
    RecordedChunks,
)
from .episode import run_episode

# policy_node's default torch_threads. A fixed count also keeps each seed's outcome the same from
# run to run: 1 and 2 threads round differently and ended one scene differently (docs/evaluation_scheme.md).
ROLLOUT_THREADS = 1


@contextlib.contextmanager
def torch_threads(threads: int | None):
    """torch's intra-op threads set to ``threads`` inside the block (None: left as they are)."""
    before = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


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
    failed_predictions: int = 0  # answers with no valid chunk, skipped as policy_node skips them


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
    threads: int | None = ROLLOUT_THREADS,
    doubt_samples: int = 1,
    on_doubt=None,
) -> list[EvalEpisode]:
    """Roll ``policy`` (an ``policy.inference.InferencePolicy``) out from each seed's scene; returns per-episode results.

    Each answered observation's chunk takes effect ``latency_s`` after it (default 0.1 s, the
    twin's default budget); the policy answers every ``execute_steps``-th observation (0: every
    ``n_action_steps``-th, policy_node's default) and publishes ``publish_steps`` steps of each
    chunk (None, the default: enough to bridge ``latency_s``, as policy_node given that latency, which
    the live twin passes it, with ``execute_steps`` 0 lowered as policy_node lowers it when L is too
    long for n_action_steps; 0: ``n_action_steps``); with ``rtc`` (default policy_node's) each chunk is
    denoised towards the previous one (``wire.chunk.RealTimeChunking``, its delay from ``latency_s``); see the
    module doc. The policy's sampling seeds are ``wire.chunk.SamplingSeeds``' for the episode's seed. ``probe``
    (e.g. ``twin.chunking.ChunkingProbe``) sees each episode's chunks as franka_node's
    Controller receives them and its every command. Inference runs on ``threads`` torch threads (None:
    the process's setting); ``doubt_samples`` and ``on_doubt``: ``DirectPolicy``'s (the doubt of each
    chunk, ``policy.doubt``); each scene's cameras draw their depth noise from its seed
    (``DirectRecorder.reset``), so with a fixed thread count a seed's episode does not depend on the
    episodes rolled out before it."""
    from .demos import DirectRecorder, DirectWorld

    execute_steps, publish_steps = answer_sizing(policy.preset, latency_s, execute_steps, publish_steps)
    control = control_config()
    rec = recorder or DirectRecorder(cfg, lab)
    world = DirectWorld(rec)  # records nothing
    results = []
    with contextlib.ExitStack() as cleanup:
        if recorder is None:
            cleanup.callback(rec.close)
        cleanup.enter_context(torch_threads(threads))
        for seed in seeds:
            actor = DirectPolicy(
                world,
                policy,
                seed,
                control,
                max_duration_s,
                latency_s,
                execute_steps,
                publish_steps,
                rtc,
                probe,
                doubt_samples,
                on_doubt,
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
                    actor.failed_predictions,
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
                    f"; {actor.failed_predictions} predictions skipped (no valid chunk)"
                    if actor.failed_predictions
                    else "",
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
    return results


def answer_sizing(
    preset, latency_s: float, execute_steps: int = DEFAULT_EXECUTE_STEPS, publish_steps: int | None = None
) -> tuple[int, int]:
    """(execute_steps, publish_steps) as ``evaluate_policy`` documents them (None: policy_node's own sizing for
    ``latency_s``); ValueError for a latency or step count policy_node would refuse."""
    if not (math.isfinite(latency_s) and latency_s >= 0):
        raise ValueError(f"latency_s must be finite and >= 0, got {latency_s}")
    if publish_steps is None:  # policy_node's own sizing, given L as its latency_s parameter
        sizing = ChunkSizing(preset, 0, execute_steps, latency_s, DEFAULT_TRANSPORT_S)
        sizing.follow_latency()
        return sizing.answers.steps, sizing.publish_steps()
    execute_steps = AnswerSchedule(execute_steps, int(preset.n_action_steps), 1).steps  # checked up front
    available = preset.horizon - preset.n_obs_steps + 1  # the predicted steps from the observation on
    if publish_steps and not 1 <= publish_steps <= available:
        raise ValueError(f"publish_steps must be within 1..{available}, got {publish_steps}")
    return execute_steps, int(publish_steps) or int(preset.n_action_steps)


def control_config():
    """franka_node's control configuration (config/control.yaml): the scheduler and gripper deadband."""
    from ..config import default_config_dir
    from ..control import load_control_config

    return load_control_config(default_config_dir() / "control.yaml")


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
    from ..data.bags import read_episode
    from ..data.mcap_reader import BagError
    from ..wire.chunk import ChunkError, chunk_from_msg
    from .demos import DirectRecorder, DirectWorld

    control = control_config()
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
