"""The live twin's episodes (``twin.episode.run_episode`` over ROS): the world and who acts in it.

* ``LiveTwin``, the ``twin.episode.EpisodeWorld``: the supervisor homes the arm, resets the scene,
  reads success from /twin/state and drives recorder_node;
* the ``twin.episode.Actor``s: ``GatedPolicy`` (policy_node through the supervisor's gate) and
  ``LiveExpert`` (the scripted expert through the teleop path);
* ``run_policy_episode``: one episode of the main job.
"""

from __future__ import annotations

import time

import numpy as np

from equidiff_core.twin.episode import run_episode
from equidiff_core.twin.expert import object_poses_from_state, plan_pick_place
from equidiff_core.twin.run_summary import EpisodeRecord
from equidiff_core.twin.scene import ScenePoses, scene_record
from equidiff_core.wire.rosmsg import NS_PER_S
from equidiff_ros.twin.stack import TwinStack
from equidiff_ros.twin.supervisor import SupervisorError


class LiveTwin:
    """The live twin stack as a ``twin.episode.EpisodeWorld``: the supervisor homes the arm, resets
    the scene, reads success from /twin/state and drives recorder_node."""

    def __init__(self, stack: TwinStack):
        self.stack, self.sup = stack, stack.sup
        self.scene: ScenePoses | None = None

    def home(self) -> None:
        self.stack.home()

    def reset_scene(self, seed: int) -> None:
        self.scene = ScenePoses.from_dict(self.sup.reset_scene(seed, check=self.stack.check))  # recorded with the bag

    def settle(self, seconds: float) -> None:
        self.sup.sim_sleep(seconds, self.stack.check)

    def now_s(self) -> float:
        return self.sup.now_ns() / NS_PER_S

    def success(self) -> bool:
        return bool(self.sup.twin().get("success"))

    def start_recording(self) -> str:
        status = self.sup.recorder(f"start {self.stack.task}", "recording", check=self.stack.check)
        return status.split(" ", 1)[1] if " " in status else ""

    def stop_recording(self, keep: bool, success: bool, note: str) -> None:
        scene = scene_record(self.stack.cfg.scene, self.scene) if self.scene is not None else {}
        words = " ".join(f"extra.{key}={value}" for key, value in scene.items())
        command = f"stop {'success' if success else 'failure'} {words} {note}" if keep else "discard"
        self.sup.recorder(command, "idle", check=self.stack.check)


class GatedPolicy:
    """policy_node as a ``twin.episode.Actor``: its chunks reach the robot while the gate is open.

    The episode's duration counts from the first chunk; a stall twin_node reports (a stage that
    did not deliver within its stall timeout, simulated time) ends the episode at once."""

    def __init__(self, stack: TwinStack, seed: int | None = None, poll_s: float = 0.05):
        self.stack, self.sup, self.seed, self.poll_s = stack, stack.sup, seed, poll_s
        self.stalls0 = 0
        self.arrivals: list[float] = []
        self.dropped: list[str] = []
        self.end_to_end_ms: list[float] = []
        self.inference_ms: list[float] = []

    def begin(self) -> float:
        sup = self.sup
        self.stalls0 = sup.twin().get("stalls", 0)
        sup.open_gate(self.seed)
        gate_t = sup.now_ns() / NS_PER_S
        sup.wait_for(
            lambda: sup.chunk_arrivals or sup.twin().get("stalls", 0) > self.stalls0,
            60.0 + self.stack.stall_timeout_s,
            "the first policy chunk",
            self.stack.check,
        )
        return sup.chunk_arrivals[0] if sup.chunk_arrivals else gate_t

    def advance(self) -> None:
        time.sleep(self.poll_s)

    def judging(self) -> bool:
        return True

    def done(self) -> bool:
        return False

    def stalled(self) -> str:
        self.stack.check()
        self.sup.check_clock()
        state = self.sup.twin()
        return state.get("last_stall", "a stage of the pipeline") if state.get("stalls", 0) > self.stalls0 else ""

    def end(self) -> None:
        passed = self.sup.close_gate()
        self.arrivals, self.dropped = passed.arrivals, passed.dropped
        self.end_to_end_ms, self.inference_ms = passed.end_to_end_ms, passed.inference_ms
        self.sup.send_target(*self.sup.current())  # hold where it is while the recorder closes


class LiveExpert:
    """The scripted expert as a ``twin.episode.Actor`` through the teleop path: one-point chunks at
    ``hz`` (20 Hz), as teleop_node sends them.

    The plan's clock advances only while the arm keeps up (TCP within ``max_lag_m`` of the
    target, like teleop's ``max_lead_m``), so a twin slower than real time (a loaded CPU) gets
    the same motion, just later. Success counts once the plan is done; ``extra_s`` after it the
    expert gives up. An arm that never catches up (blocked, in a reflex) raises
    SupervisorError after ``timeout_s`` (default: 30 s + 10x the plan)."""

    def __init__(
        self,
        stack: TwinStack,
        hz: float | None = None,
        max_lag_m: float = 0.03,
        extra_s: float = 4.0,
        timeout_s: float | None = None,
    ):
        self.stack, self.sup, self.cfg = stack, stack.sup, stack.cfg
        self.hz = hz or self.cfg.expert.command_hz
        self.max_lag_m, self.extra_s, self.timeout_s = max_lag_m, extra_s, timeout_s
        self.plan = None
        self.t_plan = 0.0

    def begin(self) -> float:
        sup, cfg = self.sup, self.cfg
        block, bowl = object_poses_from_state(sup.twin())
        start, width = sup.current()
        self.plan = plan_pick_place(start, width, block, bowl, cfg.scene.block_size[2], cfg.expert)
        self.t_plan, self.last = 0.0, sup.now_ns() / NS_PER_S
        limit = self.timeout_s if self.timeout_s is not None else 30.0 + 10.0 * self.plan.duration  # node clock
        self.deadline = self.last + limit / sup.time_scale()
        return self.last

    def advance(self) -> None:
        sup, plan = self.sup, self.plan
        now = sup.now_ns() / NS_PER_S
        if now > self.deadline:
            lag_mm = 1000 * np.linalg.norm(sup.current()[0][:3, 3] - plan.target_at(self.t_plan)[0][:3, 3])
            raise SupervisorError(
                f"the scripted expert's {plan.duration:.0f} s plan did not finish in time: "
                f"plan clock at {self.t_plan:.1f} s, TCP {lag_mm:.0f} mm from its target"
            )
        dt, self.last = now - self.last, now
        pose, width = plan.target_at(self.t_plan)
        keeping_up = np.linalg.norm(sup.current()[0][:3, 3] - pose[:3, 3]) < self.max_lag_m
        # the plan's clock waits for a lagging arm, except after the plan (its final target holds)
        if keeping_up or self.t_plan >= plan.duration:
            self.t_plan += dt * sup.time_scale()
        sup.send_target(pose, width)
        time.sleep(1.0 / self.hz)  # wall pacing of the stream; the plan runs on the node's clock

    def judging(self) -> bool:
        return self.t_plan >= self.plan.duration

    def done(self) -> bool:
        return self.t_plan >= self.plan.duration + self.extra_s

    def stalled(self) -> str:
        self.stack.check()
        self.sup.check_clock()
        return ""

    def end(self) -> None:
        pass  # the plan's last target holds the arm


def run_policy_episode(stack: TwinStack, seed: int, max_duration_s: float) -> EpisodeRecord:
    """One episode of the main job (``twin.episode.run_episode`` with policy_node acting through the
    gate); durations on the node clock (simulated time by default).

    An episode in which twin_node reports a stall (a camera or the policy did not deliver within
    its stall timeout) ends at once as ``stalled``, naming the stage; its bag is kept."""

    policy = GatedPolicy(stack, seed)
    result = run_episode(LiveTwin(stack), policy, seed, max_duration_s, stack.cfg.success.hold_s)
    return EpisodeRecord(
        seed=seed,
        success=result.success,
        duration_s=result.duration_s,
        chunks=len(policy.arrivals),
        dropped_cycles=len(policy.dropped),  # observations due an answer that got none
        bag=result.bag,
        end_to_end_ms=policy.end_to_end_ms,
        inference_ms=policy.inference_ms,
        stalled=result.stalled,
    )
