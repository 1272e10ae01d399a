"""The policy's doubt signals (policy.doubt), K samples from one encoder pass, the /policy/doubt message."""

from __future__ import annotations

import math

import numpy as np
import pytest

from equidiff_core.benches.doubt import auroc, auroc_ci95, chunk_signals, episode_scores
from equidiff_core.config import Workspace
from equidiff_core.policy.doubt import (
    ChunkDoubt,
    DoubtCalibration,
    DoubtGate,
    DoubtTracker,
    calibrate_doubt,
    chunk_disagreement,
    sample_spread,
)
from equidiff_core.wire.rosmsg import MessageError, MessageReason, doubt_from_msg, doubt_msg, rosbags_factory

DT = 200_000_000
F = rosbags_factory()


def chunk(steps: int = 16, start=(0.4, 0.0, 0.2), step=(0.01, 0.0, 0.0), width: float = 0.08) -> np.ndarray:
    """(steps, 10) actions moving ``step`` per step, identity rotation."""
    a = np.zeros((steps, 10))
    a[:, :3] = np.asarray(start) + np.arange(steps)[:, None] * np.asarray(step)
    a[:, 3], a[:, 7], a[:, 9] = 1.0, 1.0, width
    return a


def test_identical_samples_have_no_spread_and_offset_ones_half_their_offset():
    a = chunk()
    assert sample_spread(np.stack([a, a, a])) == pytest.approx(0.0, abs=1e-15)
    b = a.copy()
    b[:, 1] += 0.02  # 2 cm apart: each sample 1 cm from their mean
    assert sample_spread(np.stack([a, b])) == pytest.approx(0.01)
    with pytest.raises(ValueError, match="K >= 2"):
        sample_spread(a[None])
    with pytest.raises(ValueError, match="finite"):
        sample_spread(np.stack([a, np.full_like(a, np.nan)]))


def test_a_chunk_that_continues_the_previous_one_does_not_disagree_and_a_shifted_one_by_its_shift():
    previous = chunk()
    shift = 8  # the new chunk observed 8 steps later: the previous one's steps 8.. had not run yet
    same = chunk(start=previous[shift, :3])
    assert chunk_disagreement(previous, 0, same, shift * DT, DT) == pytest.approx(0.0, abs=1e-12)
    moved = same.copy()
    moved[:, 2] += 0.03
    assert chunk_disagreement(previous, 0, moved, shift * DT, DT) == pytest.approx(0.03)
    # only the overlap (previous steps 8..15 against new steps 0..7) counts: the rest of the new one is free
    moved[shift:, 2] += 1.0
    assert chunk_disagreement(previous, 0, moved, shift * DT, DT) == pytest.approx(0.03)
    assert chunk_disagreement(previous, 0, same, 16 * DT, DT) is None  # the previous one is used up
    # a stamp off the dt grid: the previous chunk interpolated between its steps (it moves 1 cm per step)
    half = chunk(start=previous[0, :3] + [0.005, 0, 0])
    assert chunk_disagreement(previous, 0, half, DT // 2, DT) == pytest.approx(0.0, abs=1e-12)
    assert chunk_disagreement(previous, 0, previous, DT // 2, DT) == pytest.approx(0.005)
    assert chunk_disagreement(previous, DT, same, 0, DT) is None  # older than the previous one


def test_the_tracker_compares_each_chunk_with_the_previous_one_until_reset():
    tracker = DoubtTracker(DT, "disagreement")
    first = tracker.update(0, chunk())
    assert math.isnan(first.disagreement_m) and math.isnan(first.spread_m) and math.isnan(first.value)
    moved = chunk(start=chunk()[8, :3] + [0, 0.01, 0])
    second = tracker.update(8 * DT, np.stack([moved, moved]))
    assert second.disagreement_m == pytest.approx(0.01) and second.spread_m == 0.0
    assert second.value == second.disagreement_m and second.stamp_ns == 8 * DT
    tracker.reset()
    assert math.isnan(tracker.update(16 * DT, moved).disagreement_m)
    assert DoubtTracker(DT, "spread").update(0, np.stack([moved, moved])).value == 0.0
    with pytest.raises(ValueError, match="signal"):
        DoubtTracker(DT, "entropy")


@pytest.mark.parametrize("signal", ["disagreement", "spread"])
def test_the_doubt_message_round_trips_and_its_decoder_refuses_what_it_cannot_mean(signal):
    doubt = ChunkDoubt(1_234_000_000_007, 0.012, 0.003, signal)
    back = doubt_from_msg(doubt_msg(F, doubt))
    assert back == doubt
    msg = doubt_msg(F, doubt)
    assert msg.header.frame_id == signal and msg.vector.x == doubt.value
    first = doubt_from_msg(doubt_msg(F, ChunkDoubt(5, math.nan, math.nan, signal)))  # nothing to compare yet
    assert first.stamp_ns == 5 and math.isnan(first.value)
    for field, value, reason in [
        ("frame", "entropy", MessageReason.FRAME),
        ("y", -0.01, MessageReason.RANGE),
        ("z", math.inf, MessageReason.NAN),
        ("x", 0.5, MessageReason.MALFORMED),  # not the named signal's value
    ]:
        bad = doubt_msg(F, doubt)
        if field == "frame":
            bad.header.frame_id = value
        else:
            setattr(bad.vector, field, value)
        with pytest.raises(MessageError) as err:
            doubt_from_msg(bad)
        assert err.value.reason == reason


def test_auroc_and_episode_scores():
    assert auroc([3, 4], [1, 2]) == 1.0
    assert auroc([1, 2], [3, 4]) == 0.0
    assert auroc([1, 2], [1, 2]) == 0.5
    assert auroc([], [1]) is None
    low, high = auroc_ci95([3, 4, 5], [1, 2, 3], resamples=200)
    assert low < auroc([3, 4, 5], [1, 2, 3]) < high == 1.0  # 8.5 of 9 pairs: the interval reaches 1
    low, high = auroc_ci95([1, 3, 5, 7], [2, 4, 6, 8], resamples=200)
    assert low < auroc([1, 3, 5, 7], [2, 4, 6, 8]) < high
    assert auroc_ci95([1], [2, 3]) is None
    chunks = [{"disagreement": math.nan, "spread_2": 0.01}, {"disagreement": 0.02, "spread_2": 0.03}]
    assert episode_scores(chunks) == {"disagreement": 0.02, "spread_2": 0.03}
    a = chunk()
    b = a.copy()
    b[:, 0] += 0.02
    signals = chunk_signals(0.5, np.stack([a, b, a, b]), (2, 4, 8))
    assert signals == {"disagreement": 0.5, "spread_2": pytest.approx(0.01), "spread_4": pytest.approx(0.01)}


@pytest.fixture(scope="module")
def tiny_policy(tmp_path_factory):
    from equidiff_core.policy.diffusion import make_policy
    from equidiff_core.policy.file import export_policy
    from equidiff_core.policy.normalizer import Normalizer
    from equidiff_core.policy.presets import get_preset

    ws = Workspace()
    policy = make_policy("baseline", get_preset("tiny"), ws)
    policy.set_normalizer(Normalizer.from_workspace(ws))
    return export_policy(policy, tmp_path_factory.mktemp("policy") / "policy.pt")


@pytest.mark.parametrize("jit", [False, pytest.param(True, marks=pytest.mark.slow)])  # tracing takes ~10 s
def test_k_samples_share_one_encoder_pass_and_the_first_is_the_plain_prediction(tiny_policy, jit):
    from equidiff_core.policy.inference import load_inference_policy

    policy = load_inference_policy(tiny_policy, precision="fp32", jit=jit)
    vox, ee = policy._blank_observation()
    vox[:, 10:14, 10:14, 0:3] = 255
    plain = policy.predict(vox, ee, seed=11)
    samples = policy.predict_samples(vox, ee, 4, seed=11)
    assert samples.shape == (4, policy.preset.horizon, 10)
    np.testing.assert_allclose(samples[0], plain, atol=1e-5)
    assert sample_spread(samples) > 0  # other noise, other samples
    np.testing.assert_array_equal(policy.predict_samples(vox, ee, 1, seed=11)[0], plain)
    guide = (plain, np.ones(policy.preset.horizon))  # fully guided: every sample is the target
    assert sample_spread(policy.predict_samples(vox, ee, 3, seed=2, guide=guide)) < 1e-4
    with pytest.raises(ValueError, match="samples"):
        policy.predict_samples(vox, ee, 0)


def test_the_gate_fires_above_the_demos_quantile_and_never_on_nothing_to_compare():
    calibration = DoubtCalibration("disagreement", 1, tuple(np.linspace(0.0, 0.1, 101)), 10)
    assert calibration.threshold(0.5) == pytest.approx(0.05) and calibration.threshold(1.0) == pytest.approx(0.1)
    gate = DoubtGate(calibration, 0.9, "disagreement", 1)
    assert gate.threshold_m == pytest.approx(0.09)
    assert gate.alarm(ChunkDoubt(0, 0.08, math.nan)) == ""
    assert gate.alarm(ChunkDoubt(0, math.nan, math.nan)) == ""  # the first chunk: nothing to compare
    assert (
        gate.alarm(ChunkDoubt(0, 0.1, math.nan)) == "doubt 100.0 mm (disagreement) above 90.0 mm, the q0.9 of its demos"
    )
    back = DoubtCalibration.from_dict(calibration.as_dict())  # stored to the micrometre
    assert back.values_m == pytest.approx(calibration.values_m, abs=1e-6) and back.signal == calibration.signal
    with pytest.raises(ValueError, match="calibrated on 'disagreement'"):
        DoubtGate(calibration, 0.9, "spread", 2)
    with pytest.raises(ValueError, match="spread was calibrated with 4 samples"):
        DoubtGate(DoubtCalibration("spread", 4, (0.01,), 1), 0.9, "spread", 2)
    with pytest.raises(ValueError, match="quantile"):
        calibration.threshold(0.0)
    for bad in [{"signal": "disagreement", "samples": 1, "episodes": 1, "values_m": []},
                {"signal": "disagreement", "samples": 1, "episodes": 1, "values_m": [-0.1]},
                {"signal": "spread", "samples": 1, "episodes": 1, "values_m": [0.1]},
                {"signal": "disagreement", "samples": 1}]:  # fmt: skip
        with pytest.raises(ValueError):
            DoubtCalibration.from_dict(bad)


class _Episode:
    """Just what calibrate_doubt reads of an EpisodeArrays: frames (grid, ee) at 5 Hz."""

    def __init__(self, frames: int, resolution: int):
        self.stamps_ns = np.arange(frames) * DT
        self.ee = np.tile(np.array([0.45, 0.0, 0.2, 1, 0, 0, 0, 1, 0, 0.08], np.float32), (frames, 1))
        self.resolution = resolution

    def __len__(self):
        return len(self.stamps_ns)

    def grid(self, i, resolution):
        assert resolution == self.resolution
        grid = np.zeros((4, resolution, resolution, resolution), np.uint8)
        grid[:, 20:24, 20:24, 0:3] = 255
        return grid


def test_the_calibration_is_the_signal_on_the_demos_frames_and_is_stored_with_the_policy(tiny_policy, tmp_path):
    from equidiff_core.policy.file import open_policy_file, with_doubt_calibration
    from equidiff_core.policy.inference import load_inference_policy
    from equidiff_core.runtime.output_files import OutputExistsError

    policy = load_inference_policy(tiny_policy, precision="fp32")
    assert policy.doubt_calibration is None  # a file without one (every file before the gate) still loads
    steps = policy.n_action_steps
    episodes = [_Episode(3 * steps + 1, policy.workspace.resolution), _Episode(2 * steps, policy.workspace.resolution)]
    calibration = calibrate_doubt(policy, episodes)
    # answered frames 0, n, 2n, 3n and 0, n: the first of each episode has nothing to compare with
    assert len(calibration.values_m) == 3 + 1 and calibration.episodes == 2
    out = with_doubt_calibration(tiny_policy, calibration.as_dict(), tmp_path / "gated.pt")
    gated = load_inference_policy(out, precision="fp32")
    assert gated.doubt_calibration.values_m == pytest.approx(calibration.values_m, abs=1e-6)
    assert open_policy_file(out).weights_sha256 == open_policy_file(tiny_policy).weights_sha256
    with pytest.raises(OutputExistsError):
        with_doubt_calibration(tiny_policy, calibration.as_dict(), out)


def test_check_doubt_measures_the_demos_and_stores_the_calibration_beside_the_weights(tiny_policy, tmp_path, capsys):
    import json
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from helpers_data import SyntheticEpisode, write_synthetic_episode

    from equidiff_core.policy.inference import load_inference_policy
    from equidiff_ros.cli import main

    bag = write_synthetic_episode(tmp_path / "demos" / "ep_0000", SyntheticEpisode(duration_s=4.0, image_size=None))
    out = tmp_path / "gated.pt"
    args = ["check", "doubt", str(tiny_policy), "--demos", str(bag.parent), "--write", str(out)]
    assert main(args) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["episodes"] == 1 and result["frames"] >= 1 and result["written"] == str(out)
    assert result["quantiles_m"]["q0.5"] <= result["quantiles_m"]["q0.99"] <= result["quantiles_m"]["q1"]
    calibration = load_inference_policy(out).doubt_calibration
    assert len(calibration.values_m) == result["frames"] and calibration.signal == result["signal"]
    assert main(args) != 0  # an existing output is refused without --force
    assert main([*args[:-2], "--write", str(tiny_policy)]) == 2  # the policy file itself: --force
    assert "--force" in capsys.readouterr().err
