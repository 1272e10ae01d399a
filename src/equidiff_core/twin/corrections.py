"""Corrected roll-outs in-process: the policy acts, and when a takeover trigger fires the scripted expert takes the
arm to the end of the episode, planning from where the arm and the block are, as an operator with a SpaceMouse
would (``equidiff bench corrections``, docs/corrections.md).

Every episode is recorded (``demos.DirectWorld``: the training topics) together with the two latched topics a
lab bag holds while a policy runs: ``/policy/state`` (``running``, then ``paused teleop takeover``, or ``paused
asks for help ...`` when the policy's doubt gate fired) and ``/teleop/active`` (false, then true from the
takeover on). So ``data.segments`` labels the policy's frames and the operator's, and ``equidiff train
--init-from`` fine-tunes on them like on a lab day's bags.

A takeover trigger is a callable ``TakeoverView -> str`` (why it fires; '' while it does not), checked at each
observation instant while the policy drives; the first that fires names the takeover. ``LostRule`` is the
expert judging the episode lost; ``GateRule`` is the slot for the policy's doubt gate, fed by a callable that
says whether the gate holds the arm.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ..config import LabConfig
from ..data.segments import GATE_PAUSE_PREFIX, RUNNING
from ..policy.doubt import ChunkDoubt, DoubtGate
from ..wire.chunk import DEFAULT_RTC, PoseChunk, chunk_to_msg
from ..wire.topics import RECORDED_TOPICS, TOPIC_COMMAND_CHUNK, TOPIC_POLICY_STATE, TOPIC_TELEOP_ACTIVE
from .config import ExpertConfig, TwinConfig
from .demos import DirectExpert, DirectRecorder, DirectWorld
from .direct_execution import LIFT_M, DirectPolicy
from .episode import run_episode
from .expert import ExpertPlan, Keyframe, plan_pick_place, tcp_yaw
from .scene import BLOCK, BOWL, body_pose

TAKEOVER_PAUSE = "paused teleop takeover"  # /policy/state while the operator (here the expert) has the arm
OPERATOR = "scripted expert (takeovers)"


@dataclass(frozen=True)
class TakeoverView:
    """What a takeover trigger sees at an observation instant while the policy drives."""

    t_s: float  # since the policy started
    success_now: bool  # the scene's success test passes now (no trigger fires then)
    lifted_ever: bool  # the block has been LIFT_M above its start at some point
    block_rise_m: float  # the block's height above its start now
    block_moved_m: float  # how far the block's centre moved horizontally from its start
    block_in_bowl: bool  # the block's centre lies inside the bowl's rim (horizontally)
    tcp_travel_m: float  # the TCP's path length over the rule's last stall window (inf before one has passed)
    gate_alarm: str = ""  # why the policy's doubt gate holds the arm ('' when it does not or has none)


@dataclass(frozen=True)
class LostRule:
    """The expert judges the episode lost (checked in this order; none fires while the task succeeds):

    * ``knocked``: the block moved more than ``knocked_m`` horizontally without having been lifted (pushed away);
    * ``dropped``: it was lifted and is back on the table outside the bowl;
    * ``stalled``: the TCP moved less than ``stall_m`` over the last ``stall_s``;
    * ``no lift``: the block is not lifted ``lift_by_s`` after the start;
    * ``too slow``: the task is not done ``give_up_s`` after the start.

    Each returns ``lost/<kind>: why`` ('' while the episode looks recoverable); ``trigger_kind`` reads the kind."""

    lift_by_s: float = 15.0
    give_up_s: float = 25.0
    knocked_m: float = 0.04
    drop_height_m: float = 0.01
    stall_s: float = 5.0
    stall_m: float = 0.01

    def __call__(self, v: TakeoverView) -> str:
        if v.success_now:
            return ""
        if not v.lifted_ever and v.block_moved_m > self.knocked_m:
            return f"lost/knocked: the block {v.block_moved_m * 1000:.0f} mm from its start, never lifted"
        if v.lifted_ever and v.block_rise_m < self.drop_height_m and not v.block_in_bowl:
            return "lost/dropped: lifted, then back on the table outside the bowl"
        if v.tcp_travel_m < self.stall_m:
            return f"lost/stalled: the TCP moved {v.tcp_travel_m * 1000:.0f} mm in {self.stall_s:g} s"
        if not v.lifted_ever and v.t_s >= self.lift_by_s:
            return f"lost/no lift: the block not lifted after {self.lift_by_s:g} s"
        if v.t_s >= self.give_up_s:
            return f"lost/too slow: not done after {self.give_up_s:g} s"
        return ""


@dataclass(frozen=True)
class GateRule:
    """The policy's doubt gate held the arm and asked for help: fires with the gate's reason."""

    def __call__(self, v: TakeoverView) -> str:
        return f"gate: {v.gate_alarm}" if v.gate_alarm else ""


def trigger_kind(reason: str) -> str:
    """``lost/knocked``, ``gate``, ...: the part of a trigger's reason before its colon."""
    return reason.split(":", 1)[0]


def first_trigger(triggers: Sequence[Callable[[TakeoverView], str]], view: TakeoverView) -> str:
    """The reason of the first trigger that fires ('' if none)."""
    for trigger in triggers:
        reason = trigger(view)
        if reason:
            return reason
    return ""


class TakeoverWatch:
    """Builds ``TakeoverView`` from the sim (block, bowl, TCP) at each observation instant."""

    def __init__(self, sim, cfg: TwinConfig, stall_s: float):
        self.sim, self.cfg, self.stall_s = sim, cfg, stall_s
        block = self._position(BLOCK)
        self.block0, self.t0 = block, sim.time
        self.lifted_ever = False
        self.tcp: deque[tuple[float, np.ndarray]] = deque([(sim.time, sim.tcp_pose()[:3, 3].copy())])

    def _position(self, body: str) -> np.ndarray:
        return body_pose(self.sim.model, self.sim.data, body)[:3, 3].copy()

    def view(self, gate_alarm: str = "") -> TakeoverView:
        sim, now = self.sim, self.sim.time
        block, bowl, tcp = self._position(BLOCK), self._position(BOWL), sim.tcp_pose()[:3, 3].copy()
        rise = float(block[2] - self.block0[2])
        self.lifted_ever |= rise > LIFT_M
        self.tcp.append((now, tcp))
        while len(self.tcp) > 1 and self.tcp[1][0] <= now - self.stall_s:
            self.tcp.popleft()  # keep one sample at or before the window's start
        if now - self.tcp[0][0] >= self.stall_s - 1e-9:
            points = np.array([p for _, p in self.tcp])
            travel = float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())
        else:
            travel = float("inf")
        return TakeoverView(
            t_s=now - self.t0,
            success_now=bool(sim.success()["success"]),
            lifted_ever=self.lifted_ever,
            block_rise_m=rise,
            block_moved_m=float(np.hypot(*(block[:2] - self.block0[:2]))),
            block_in_bowl=bool(np.hypot(*(block[:2] - bowl[:2])) < self.cfg.scene.bowl_inner_radius),
            tcp_travel_m=travel,
            gate_alarm=gate_alarm,
        )


def plan_takeover(
    tcp: np.ndarray,
    width: float,
    block: np.ndarray,
    bowl: np.ndarray,
    block_height: float,
    cfg: ExpertConfig,
    holding: bool,
) -> ExpertPlan:
    """The expert's plan from wherever the policy left the arm: up to a safe height first (a sideways move
    low down would push the block), then, ``holding`` a lifted block, over the bowl and release; otherwise
    the gripper opens on the way up (whatever it held drops where it is) and the expert picks the block
    from where it lies (``plan_pick_place``)."""
    yaw, start = tcp_yaw(tcp), tcp[:3, 3].copy()
    frames = [Keyframe(0.0, start, yaw, width, "takeover")]

    def go(position, width, phase, speed, yaw=yaw):
        last = frames[-1]
        position = np.asarray(position, dtype=float)
        dist = float(np.linalg.norm(position - last.position))
        dyaw = abs(yaw - last.yaw)
        dt = max(dist / speed * np.pi / 2, dyaw / cfg.yaw_speed * np.pi / 2, 0.2)
        frames.append(Keyframe(last.t + dt, position, yaw, width, phase))

    if holding:
        go([*start[:2], max(start[2], cfg.lift_height)], width, "lift", cfg.slow_speed * 2)
        go([*bowl[:2, 3], cfg.lift_height], width, "transfer", cfg.speed)
        go([*bowl[:2, 3], cfg.place_height], width, "lower", cfg.slow_speed * 2)
        last = frames[-1]
        frames.append(replace(last, t=last.t + cfg.settle_s, phase="settle"))
        frames.append(
            replace(last, t=last.t + cfg.settle_s + cfg.gripper_wait_s, width=cfg.open_width, phase="release")
        )
        go([*bowl[:2, 3], cfg.lift_height], cfg.open_width, "retreat", cfg.speed)
        return ExpertPlan(frames)
    raised = max(start[2], cfg.approach_height)
    go([*start[:2], raised], cfg.open_width, "rise", cfg.slow_speed * 2)
    up = tcp.copy()
    up[2, 3] = raised
    pick = plan_pick_place(up, cfg.open_width, block, bowl, block_height, cfg)
    offset = frames[-1].t
    frames += [replace(k, t=k.t + offset) for k in pick.keyframes[1:]]
    return ExpertPlan(frames)


class TakeoverExpert(DirectExpert):
    """The scripted expert taking over mid-episode: ``plan_takeover`` from the sim's current state
    (``block_z0``: the block's height at the episode's start, to tell a lifted block)."""

    def __init__(self, world: DirectWorld, block_z0: float, extra_s: float = 3.0):
        super().__init__(world, extra_s)
        self.block_z0, self.holding = float(block_z0), False

    def begin(self) -> float:
        sim, cfg = self.world.sim, self.world.rec.cfg
        block = body_pose(sim.model, sim.data, BLOCK)
        tcp = sim.tcp_pose()
        width = sim.gripper_width()
        # a block in the closed hand above the table: carry it on
        holding = (
            width < 0.5 * (cfg.expert.open_width + cfg.expert.close_width) + 0.005
            and float(np.hypot(*(tcp[:2, 3] - block[:2, 3]))) < 0.03
            and block[2, 3] - self.block_z0 > LIFT_M
        )
        self.holding = bool(holding)
        self.plan = plan_takeover(
            tcp, width, block, body_pose(sim.model, sim.data, BOWL), cfg.scene.block_size[2], cfg.expert, holding
        )
        self.t0 = sim.time
        return self.t0


class CorrectionWorld(DirectWorld):
    """A recording ``DirectWorld`` that also records the latched ``/policy/state`` and ``/teleop/active``, and
    adds the takeover to the bag's notes."""

    extra_note = ""

    def start_recording(self) -> str:
        path = super().start_recording()
        for topic in (TOPIC_POLICY_STATE, TOPIC_TELEOP_ACTIVE):
            self.writer.add_topic(topic, RECORDED_TOPICS[topic], transient_local=True)
        self.extra_note = ""
        return path

    def latch(self, policy_state: str, teleop_active: bool) -> None:
        """Both latched topics now (the recorder logs a latched message when it changes)."""
        f, t_ns = self.rec.factory, self.stamp_ns()
        self.writer.write(TOPIC_POLICY_STATE, f.make("std_msgs/msg/String", data=policy_state), t_ns)
        self.writer.write(TOPIC_TELEOP_ACTIVE, f.make("std_msgs/msg/Bool", data=bool(teleop_active)), t_ns)

    def stop_recording(self, keep: bool, success: bool, note: str) -> None:
        super().stop_recording(keep, success, " ".join(w for w in (note, self.extra_note) if w))


class RecordedPolicy(DirectPolicy):
    """``DirectPolicy`` whose sim time passes through its ``CorrectionWorld`` one ms at a time (so the bag gets
    every state, grid and command), its chunks recorded on /franka/command_chunk as policy_node publishes them."""

    def step_sim(self, ms: int) -> None:
        for _ in range(ms):
            self.world.step()

    def observe(self, stamp_ns: int) -> None:
        super().observe(stamp_ns)
        chunk = self.pending[-1][1]
        epoch = self.world.stamp_ns() - stamp_ns  # the bag's stamps: the world's epoch + the episode's time
        moved = PoseChunk(chunk.stamp_ns + epoch, chunk.times_ns + epoch, chunk.poses, chunk.widths)
        msg = chunk_to_msg(moved, self.world.rec.factory, self.world.lab.base_frame)
        self.world.writer.write(TOPIC_COMMAND_CHUNK, msg, self.world.stamp_ns())


class CorrectedRollout:
    """A ``twin.episode.Actor``: ``policy`` (an Actor stepping ``world``) drives until a trigger fires at an
    observation instant, then ``TakeoverExpert`` drives to its plan's end (+ ``extra_s``)."""

    def __init__(
        self,
        world: CorrectionWorld,
        policy,
        triggers: Sequence[Callable[[TakeoverView], str]],
        stall_s: float = LostRule.stall_s,
        gate_alarm: Callable[[], str] | None = None,
        extra_s: float = 3.0,
    ):
        self.world, self.policy, self.triggers, self.stall_s = world, policy, tuple(triggers), stall_s
        self.gate_alarm, self.extra_s = gate_alarm, extra_s
        self.expert: TakeoverExpert | None = None
        self.trigger, self.takeover_s = "", None

    def begin(self) -> float:
        self.t0 = self.policy.begin()
        self.watch = TakeoverWatch(self.world.sim, self.world.rec.cfg, self.stall_s)
        self.world.latch(RUNNING, False)
        return self.t0

    def advance(self) -> None:
        if self.expert is not None:
            self.expert.advance()
            return
        self.policy.advance()
        if self.policy.done():
            return
        view = self.watch.view(self.gate_alarm() if self.gate_alarm is not None else "")
        reason = first_trigger(self.triggers, view)
        if reason:
            self.take_over(reason, view.gate_alarm if reason.startswith("gate:") else "")

    def take_over(self, reason: str, gate_alarm: str = "") -> None:
        """The operator (the expert) takes the arm now."""
        self.trigger, self.takeover_s = reason, round(self.world.sim.time - self.t0, 3)
        if gate_alarm:  # the gate paused the policy first, then the operator took over
            self.world.latch(f"{GATE_PAUSE_PREFIX}: {gate_alarm}", False)
        self.world.latch(TAKEOVER_PAUSE, True)
        self.world.extra_note = f"takeover at {self.takeover_s:.1f} s ({reason})"
        self.policy.end()
        self.expert = TakeoverExpert(self.world, self.watch.block0[2], self.extra_s)
        self.expert.begin()

    def judging(self) -> bool:
        return self.policy.judging() if self.expert is None else self.expert.judging()

    def done(self) -> bool:
        return self.policy.done() if self.expert is None else self.expert.done()

    def stalled(self) -> str:
        return ""

    def end(self) -> None:
        if self.expert is None:
            self.policy.end()


@dataclass(frozen=True)
class CorrectedEpisode:
    seed: int
    success: bool  # the episode's, whoever finished it
    trigger: str  # why the expert took over ('' if it did not)
    takeover_s: float | None  # when, from the policy's start
    duration_s: float  # sim seconds recorded after the start
    block_yaw_deg: float
    reached: bool  # how far the policy got before any takeover (twin.direct_execution.EpisodeProgress)
    lifted: bool
    bag: str
    # the policy's doubt (policy.doubt, the default signal) over its own chunks: the largest, and with a gate
    # the chunks over its threshold and when the first came (from the policy's start); None: not measured
    max_doubt_m: float | None = None
    alarms: int | None = None
    first_alarm_s: float | None = None

    @property
    def policy_success(self) -> bool:
        """Solved by the policy alone."""
        return self.success and not self.trigger


def corrected_rollouts(
    policy,
    cfg: TwinConfig,
    lab: LabConfig,
    seeds: Iterable[int],
    out: Path,
    rule: LostRule = LostRule(),
    max_duration_s: float = 30.0,
    latency_s: float = 0.1,
    gate: DoubtGate | None = None,
    gate_takes_over: bool = False,
    on_episode: Callable[[CorrectedEpisode], None] = lambda e: None,
    log: Callable[[str], None] = print,
    task: str = "twin_block_in_bowl",
) -> list[CorrectedEpisode]:
    """Roll ``policy`` (an ``InferencePolicy``) out from each seed's scene with takeovers (``GateRule`` first,
    then ``rule``), every episode recorded under ``out`` and kept; ``on_episode`` sees each as it ends.
    Timing and answering are ``evaluate.evaluate_policy``'s (its defaults); inference runs on one thread.
    Each chunk's doubt is measured as policy_node measures it; ``gate`` counts the alarms it would raise,
    and with ``gate_takes_over`` its first alarm hands the arm to the expert, as the doubt gate does live."""
    from .evaluate import ROLLOUT_THREADS, answer_sizing, control_config, torch_threads

    execute_steps, publish_steps = answer_sizing(policy.preset, latency_s)
    control = control_config()
    rec = DirectRecorder(cfg, lab, reuse_instant=True)
    world = CorrectionWorld(rec, out, task, operator=OPERATOR, record_images=False)
    results = []
    try:
        with torch_threads(ROLLOUT_THREADS):
            for seed in seeds:
                t_wall = time.monotonic()
                world.epoch_ns = time.time_ns()
                doubts = DoubtLog(gate)
                actor = RecordedPolicy(
                    world,
                    policy,
                    seed,
                    control,
                    max_duration_s,
                    latency_s,
                    execute_steps,
                    publish_steps,
                    DEFAULT_RTC,
                    on_doubt=doubts.add,
                )
                alarm = (lambda doubts=doubts: doubts.first_alarm) if gate_takes_over else None
                rollout = CorrectedRollout(world, actor, (GateRule(), rule), rule.stall_s, alarm)
                episode = run_episode(world, rollout, seed, float("inf"), cfg.success.hold_s, settle_s=0.0)
                row = CorrectedEpisode(
                    seed,
                    episode.success,
                    rollout.trigger,
                    rollout.takeover_s,
                    round(world.now_s() - rollout.t0, 2),
                    round(float(np.degrees(world.scene.block_yaw)), 1),
                    actor.progress.reached,
                    actor.progress.lifted,
                    episode.bag,
                    doubts.max_m,
                    None if gate is None else doubts.alarms,
                    None if doubts.first_alarm_ns is None else round(doubts.first_alarm_ns / 1e9, 2),
                )
                results.append(row)
                on_episode(row)
                log(
                    f"[corrections] seed {seed}: {'success' if row.success else 'failure'}, "
                    + (f"takeover at {row.takeover_s:.1f} s ({row.trigger})" if row.trigger else "no takeover")
                    + f", {row.duration_s:.1f} s sim in {time.monotonic() - t_wall:.0f} s; {Path(row.bag).name}"
                )
    finally:
        rec.close()
    return results


class DoubtLog:
    """One roll-out's chunk doubts (``DirectPolicy``'s ``on_doubt``): the largest, and ``gate``'s alarms."""

    def __init__(self, gate: DoubtGate | None):
        self.gate, self.max_m, self.alarms = gate, None, 0
        self.first_alarm, self.first_alarm_ns = "", None

    def add(self, seed: int, doubt: ChunkDoubt, samples) -> None:  # stamps count from the policy's start
        if math.isfinite(doubt.value):
            self.max_m = doubt.value if self.max_m is None else max(self.max_m, doubt.value)
        why = self.gate.alarm(doubt) if self.gate is not None else ""
        if why:
            self.alarms += 1
            if not self.first_alarm:
                self.first_alarm, self.first_alarm_ns = why, doubt.stamp_ns


def episode_dict(episode: CorrectedEpisode) -> dict:
    return asdict(episode)
