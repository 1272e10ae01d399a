"""episode.run_episode: the one sequence every episode loop runs (home -> reset -> settle -> record -> act -> keep)."""

from __future__ import annotations

import pytest

from equidiff_core.twin.episode import run_episode


class ScriptedWorld:
    """A world whose clock advances 0.2 s per actor step and whose success follows a script."""

    def __init__(self, success_at: list[bool] | None = None):
        self.t = 0.0
        self.success_at = success_at or []
        self.calls: list[str] = []
        self.closed: tuple | None = None

    def home(self):
        self.calls.append("home")

    def reset_scene(self, seed):
        self.calls.append(f"reset {seed}")

    def settle(self, seconds):
        self.calls.append(f"settle {seconds}")
        self.t += seconds

    def now_s(self):
        return self.t

    def success(self):
        i = round((self.t - 0.6) / 0.2)
        return self.success_at[i] if i < len(self.success_at) else False

    def start_recording(self):
        self.calls.append("record")
        return "/bags/ep"

    def stop_recording(self, keep, success, note):
        self.closed = (keep, success, note)


class StepActor:
    def __init__(self, world, stall_after: int | None = None, fail_after: int | None = None, judge_from: int = 0):
        self.world, self.steps, self.ended = world, 0, False
        self.stall_after, self.fail_after, self.judge_from = stall_after, fail_after, judge_from

    def begin(self):
        self.world.calls.append("begin")
        return self.world.t

    def advance(self):
        if self.fail_after is not None and self.steps >= self.fail_after:
            raise RuntimeError("policy_node died")
        self.steps += 1
        self.world.t += 0.2

    def judging(self):
        return self.steps >= self.judge_from

    def done(self):
        return False

    def stalled(self):
        return "voxel_node: no /voxels" if self.stall_after is not None and self.steps >= self.stall_after else ""

    def end(self):
        self.ended = True


def test_the_sequence_runs_in_order_and_success_must_hold_without_a_break():
    # success at steps 2-3, lapses, then holds from step 5 on: the hold restarts at the lapse
    world = ScriptedWorld([False, False, True, True, False, True, True, True, True, True])
    actor = StepActor(world)
    result = run_episode(world, actor, seed=7, max_duration_s=10.0, hold_s=0.6)
    assert world.calls == ["home", "reset 7", "settle 0.6", "record", "begin"]
    assert result.success and result.duration_s == pytest.approx(1.0)  # held from step 5 (1.0 s after the start)
    assert world.closed == (True, True, "seed=7") and result.bag == "/bags/ep" and actor.ended


def test_a_failure_runs_to_the_time_limit_and_is_kept_or_discarded_as_asked():
    world = ScriptedWorld()
    result = run_episode(world, StepActor(world), 3, max_duration_s=2.0, hold_s=0.4, note="scripted expert")
    assert not result.success and result.duration_s == pytest.approx(2.0)
    assert world.closed == (True, False, "seed=3 scripted expert")
    world = ScriptedWorld()
    result = run_episode(world, StepActor(world), 3, 2.0, 0.4, keep=lambda ok: ok)
    assert world.closed[0] is False and result.bag == ""


def test_a_stall_ends_the_episode_at_once_naming_the_stage_and_keeps_the_bag():
    world = ScriptedWorld([True] * 20)
    result = run_episode(world, StepActor(world, stall_after=2, judge_from=10), 1, 10.0, 0.2)
    assert result.stalled == "voxel_node: no /voxels" and not result.success
    assert world.closed == (True, False, "seed=1 stalled: voxel_node: no /voxels")


def test_success_before_the_actor_judges_does_not_count():
    world = ScriptedWorld([True] * 30)
    result = run_episode(world, StepActor(world, judge_from=5), 2, 10.0, 0.4)
    assert result.success and result.duration_s == pytest.approx(1.0)


def test_an_error_while_acting_keeps_the_bag_marked_interrupted_and_propagates():
    world = ScriptedWorld()
    actor = StepActor(world, fail_after=3)
    with pytest.raises(RuntimeError, match="policy_node died"):
        run_episode(world, actor, 5, 10.0, 0.4)
    assert world.closed == (True, False, "seed=5 interrupted") and actor.ended
