"""`equidiff bench corrections`: the takeover triggers, a corrected roll-out's bag (who drove each frame), the
expert's plan from mid-episode, the resumable roll-outs and the bench's summary and plot."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from equidiff_core.benches.corrections import (
    demos_curve,
    episode_frames,
    gate_quality,
    plot_corrections,
    round_summary,
)
from equidiff_core.benches.rollouts import resumable_rollouts
from equidiff_core.data.bags import read_episode, read_meta
from equidiff_core.data.dataset import DatasetConfig, load_episode_arrays
from equidiff_core.data.segments import FrameSource, gate_alarms_ns
from equidiff_core.twin.config import TwinConfig
from equidiff_core.twin.corrections import (
    CorrectedEpisode,
    GateRule,
    LostRule,
    TakeoverView,
    first_trigger,
    plan_takeover,
    trigger_kind,
)
from equidiff_core.twin.evaluate import EvalEpisode
from equidiff_core.twin.expert import tcp_pose
from equidiff_core.wire.chunk import chunk_from_msg
from equidiff_core.wire.topics import TOPIC_COMMAND_CHUNK

CFG = TwinConfig()
# a policy on its way: early, nothing lifted yet, the TCP moving
GOING = TakeoverView(
    t_s=3.0,
    success_now=False,
    lifted_ever=False,
    block_rise_m=0.0,
    block_moved_m=0.005,
    block_in_bowl=False,
    tcp_travel_m=0.2,
)


@pytest.mark.parametrize(
    "change, kind",
    [
        ({}, ""),
        ({"block_moved_m": 0.06}, "lost/knocked"),
        ({"lifted_ever": True, "block_rise_m": 0.002, "block_moved_m": 0.08}, "lost/dropped"),
        ({"tcp_travel_m": 0.004}, "lost/stalled"),
        ({"t_s": 15.0}, "lost/no lift"),
        ({"t_s": 20.0, "lifted_ever": True, "block_rise_m": 0.08}, ""),  # lifted in time: still going
        ({"t_s": 25.0, "lifted_ever": True, "block_rise_m": 0.08}, "lost/too slow"),
        # a block lifted and set down inside the bowl is no drop, and nothing fires while the task succeeds
        ({"lifted_ever": True, "block_rise_m": 0.0, "block_in_bowl": True}, ""),
        ({"t_s": 29.0, "tcp_travel_m": 0.0, "block_moved_m": 0.2, "success_now": True}, ""),
    ],
)
def test_the_expert_judges_an_episode_lost_from_its_progress(change, kind):
    assert trigger_kind(LostRule()(replace(GOING, **change))) == kind


def test_the_gate_slot_fires_first_and_says_why():
    triggers = (GateRule(), LostRule())
    assert first_trigger(triggers, GOING) == ""
    stalled = replace(GOING, tcp_travel_m=0.0)
    assert trigger_kind(first_trigger(triggers, stalled)) == "lost/stalled"
    assert first_trigger(triggers, replace(stalled, gate_alarm="doubt 0.9 over 0.5")) == "gate: doubt 0.9 over 0.5"


def test_the_takeover_plan_starts_where_the_arm_is_and_never_moves_sideways_low():
    ex = CFG.expert
    tcp = tcp_pose([0.45, 0.05, 0.04], 0.3)  # low, beside the block
    block = tcp_pose([0.5, 0.0, 0.015], 0.0)
    bowl = tcp_pose([0.4, -0.15, 0.0], 0.0)
    plan = plan_takeover(tcp, 0.08, block, bowl, 0.03, ex, holding=False)
    first, rise = plan.keyframes[0], plan.keyframes[1]
    np.testing.assert_allclose(first.position, tcp[:3, 3])
    assert (
        rise.phase == "rise" and np.allclose(rise.position[:2], tcp[:2, 3]) and rise.position[2] >= ex.approach_height
    )
    assert [k.phase for k in plan.keyframes][-2:] == ["release", "retreat"]
    # holding a lifted block: straight on to the bowl, the gripper closed until the release
    held = plan_takeover(tcp_pose([0.5, 0.0, 0.12], 0.0), 0.03, block, bowl, 0.03, ex, holding=True)
    phases = [k.phase for k in held.keyframes]
    assert "approach" not in phases and phases[-2:] == ["release", "retreat"]
    assert all(k.width == 0.03 for k in held.keyframes[: phases.index("release")])
    np.testing.assert_allclose(held.keyframes[phases.index("lower")].position[:2], bowl[:2, 3])


class _FrozenPolicy:
    """An ``InferencePolicy`` that holds the arm where it is: the expert judges it stalled."""

    preset = SimpleNamespace(dt=0.2, n_action_steps=8, horizon=16, n_obs_steps=1)

    def predict(self, grid, ee, seed=0, guide=None):
        return np.repeat(ee[None], 16, axis=0)


@pytest.fixture(scope="module")
def recorder():
    from equidiff_core.config import default_config_dir, load_lab_config
    from equidiff_core.twin.demos import DirectRecorder

    rec = DirectRecorder(CFG, load_lab_config(default_config_dir() / "lab.yaml"), reuse_instant=True)
    yield rec
    rec.close()


@pytest.mark.sim
def test_the_recorded_roll_out_renders_each_instant_once(recorder):
    """The bag and the policy ask for the grid at the same instant: one render, one noise draw."""
    recorder.reset(5)
    first = recorder.voxel_grid(1)
    assert recorder.voxel_grid(2) is first
    recorder.sim.step(1)
    assert recorder.voxel_grid(3) is not first


@pytest.mark.sim
@pytest.mark.parametrize("gate", [False, True])
def test_a_corrected_episode_records_who_drove_each_frame(recorder, tmp_path, gate):
    """A policy that does not move, recorded in-process: the stall rule (or the gate slot) hands the arm to the
    expert at 0.6 s; the bag's frames before are the policy's, those after the operator's, as training reads
    them, and the bag holds the policy's chunks, then the expert's one-point targets."""
    from equidiff_core.twin.corrections import CorrectedRollout, CorrectionWorld, RecordedPolicy
    from equidiff_core.twin.episode import run_episode
    from equidiff_core.twin.evaluate import answer_sizing, control_config

    world = CorrectionWorld(recorder, tmp_path, "corrected", epoch_ns=10**18, record_images=False)
    policy = _FrozenPolicy()
    execute, publish = answer_sizing(policy.preset, 0.1)
    actor = RecordedPolicy(world, policy, 3, control_config(), 30.0, 0.1, execute, publish, False)
    alarm = (lambda: "doubt 0.9 over 0.5" if world.ms >= 400 else "") if gate else None
    rollout = CorrectedRollout(world, actor, (GateRule(), LostRule(stall_s=0.6)), stall_s=0.6, gate_alarm=alarm)
    result = run_episode(world, rollout, 3, 1.6, CFG.success.hold_s, settle_s=0.0)
    takeover = 0.4 if gate else 0.6
    assert trigger_kind(rollout.trigger) == ("gate" if gate else "lost/stalled")
    assert rollout.takeover_s == pytest.approx(takeover)
    bag = Path(result.bag)
    assert "takeover at" in read_meta(bag).notes
    arrays = load_episode_arrays(bag, DatasetConfig(horizon=4, n_obs_steps=1, n_action_steps=2))
    t = (arrays.stamps_ns - arrays.stamps_ns[0]) / 1e9
    expected = np.where(t < takeover - 1e-6, FrameSource.POLICY, FrameSource.OPERATOR)
    np.testing.assert_array_equal(arrays.sources, expected)
    assert episode_frames(bag) == {
        "demo": 0,
        "policy": int((expected == FrameSource.POLICY).sum()),
        "operator": int((expected == FrameSource.OPERATOR).sum()),
        "hold": 0,
    }
    episode = read_episode(bag)
    assert len(gate_alarms_ns(episode)) == int(gate)
    lengths = [len(chunk_from_msg(m)) for m in episode[TOPIC_COMMAND_CHUNK].messages]
    assert lengths[0] == publish > 1 and lengths[-1] == 1  # the policy's chunks, then the expert's targets


def _episode(seed, success, trigger="", takeover_s=None):
    return CorrectedEpisode(seed, success, trigger, takeover_s, 30.0, 3.0, True, False, f"/bags/{seed}")


def test_round_summary_and_gate_fields():
    episodes = [
        _episode(1, True),
        _episode(2, True, "lost/no lift: the block not lifted after 15 s", 15.0),
        _episode(3, False, "lost/stalled: the TCP moved 3 mm in 5 s", 7.0),
    ]
    frames = [
        {"demo": 0, "policy": 50, "operator": 0, "hold": 0},
        {"demo": 0, "policy": 75, "operator": 60, "hold": 0},
        {"demo": 0, "policy": 35, "operator": 70, "hold": 1},
    ]
    s = round_summary(episodes, frames)
    assert s["policy_success"]["successes"] == 1 and s["takeovers"] == 2
    assert s["takeover_success"]["successes"] == 1 and s["success_with_takeovers"]["successes"] == 2
    assert s["triggers"] == {"lost/no lift": 1, "lost/stalled": 1} and s["median_takeover_s"] == 11.0
    assert s["frames"] == {"demo": 0, "policy": 160, "operator": 130, "hold": 1}
    gate = gate_quality(episodes)
    assert gate["auroc"] is None and gate["false_alarms_per_success"] is None and gate["reason"]


def test_gate_quality_from_the_doubt_the_round_logged():
    def measured(seed, success, trigger, takeover_s, doubt_m, alarms, first_alarm_s):
        return replace(_episode(seed, success, trigger, takeover_s), max_doubt_m=doubt_m, alarms=alarms,
                       first_alarm_s=first_alarm_s)  # fmt: skip

    episodes = [
        measured(1, True, "", None, 0.02, 0, None),  # solved, quiet
        measured(2, True, "", None, 0.09, 2, 4.0),  # solved, but the gate cried twice
        measured(3, True, "lost/no lift", 15.0, 0.10, 1, 6.0),  # the gate saw it 9 s before the expert
        measured(4, False, "lost/dropped", 5.0, 0.08, 1, 7.0),  # the gate was late: the block was down
        measured(5, True, "lost/knocked", 8.0, 0.03, 0, None),  # missed
    ]
    gate = gate_quality(episodes)
    # failures' largest doubt (0.10, 0.08, 0.03) against the successes' (0.02, 0.09): 4 of 6 pairs ordered
    assert gate["auroc"] == pytest.approx(4 / 6) and gate["episodes"] == 5 and gate["reason"] is None
    assert gate["failures_flagged_recoverable"]["successes"] == 1 and gate["failures_flagged_recoverable"]["n"] == 3
    assert gate["false_alarms_per_success"] == 1.0  # 0 + 2 alarms over the 2 roll-outs the policy solved
    watched = [replace(e, alarms=None, first_alarm_s=None) for e in episodes]
    assert gate_quality(watched)["false_alarms_per_success"] is None and "quantile" in gate_quality(watched)["reason"]


def test_the_plot_draws_the_points_and_bench_demos_curve(tmp_path):
    result = tmp_path / "result.json"
    result.write_text(
        json.dumps(
            {
                "success": {"equidiff": {"10": 0.56, "20": 0.88, "40": None}},
                "success_ci95": {"equidiff": {"10": [0.42, 0.69], "20": [0.76, 0.94], "40": None}},
            }
        )
    )
    curve = demos_curve(result, {10: 800, 20: 1600, 40: 3200})
    assert sorted(curve) == [10, 20] and curve[20] == {"frames": 1600, "rate": 0.88, "ci95": [0.76, 0.94]}
    points = {
        "start": {"name": "equidiff_10", "frames": 800, "rate": 0.56, "ci95": [0.42, 0.69]},
        "corrected": {"name": "corrected", "frames": 1100, "rate": 0.8, "ci95": [0.67, 0.89]},
        "reference": {"name": "equidiff_20", "frames": 1600, "rate": 0.88, "ci95": [0.76, 0.94]},
    }
    path = plot_corrections(points, curve, tmp_path / "plot.png", "a note")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 10_000
    plot_corrections(points, None, path)  # the bench's own file: redrawn


def test_roll_outs_resume_scene_by_scene(tmp_path):
    cache = tmp_path / "run" / "rollouts.json"
    settings = {"seeds": [5, 6, 7], "max_duration_s": 30.0, "latency_s": 0.1, "policy_digest": "abc"}
    calls = []

    def roll_one(seed):
        calls.append(seed)
        if seed == 7 and len(calls) == 3:
            raise KeyboardInterrupt  # interrupted on the last scene
        return EvalEpisode(seed, seed % 2 == 1, 30.0, 19, 3.0, True, False, 0.2, 0.01)

    with pytest.raises(KeyboardInterrupt):
        resumable_rollouts(cache, settings, roll_one, lambda s: None)
    done = resumable_rollouts(cache, settings, roll_one, lambda s: None)
    assert calls == [5, 6, 7, 7] and [e.seed for e in done] == [5, 6, 7]
    assert [e.success for e in done] == [True, False, True]
    assert resumable_rollouts(cache, settings, roll_one, lambda s: None) == done and len(calls) == 4
    # other settings: nothing reused
    resumable_rollouts(cache, {**settings, "policy_digest": "def"}, roll_one, lambda s: None)
    assert len(calls) == 7


def test_a_roll_outs_doubt_log_keeps_the_largest_and_the_gates_alarms():
    from equidiff_core.policy.doubt import ChunkDoubt, DoubtCalibration, DoubtGate
    from equidiff_core.twin.corrections import DoubtLog

    gate = DoubtGate(DoubtCalibration("disagreement", 1, (0.01, 0.02, 0.05), 1), 1.0, "disagreement", 1)
    log = DoubtLog(gate)
    for t_s, value in ((0.0, float("nan")), (1.6, 0.03), (3.2, 0.07), (4.8, 0.06), (6.4, 0.04)):
        log.add(0, ChunkDoubt(int(t_s * 1e9), value, float("nan")), None)
    assert log.max_m == 0.07 and log.alarms == 2  # 0.07 and 0.06 are over the demos' largest, 0.05
    assert log.first_alarm_ns == int(3.2e9) and log.first_alarm.startswith("doubt 70.0 mm")
    watching = DoubtLog(None)
    watching.add(0, ChunkDoubt(0, 0.5, float("nan")), None)
    assert watching.max_m == 0.5 and watching.alarms == 0 and not watching.first_alarm
