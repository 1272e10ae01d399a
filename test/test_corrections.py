"""Corrected roll-outs as data: who drove each frame (data.segments), what `dataset stats` counts, how the
samples are weighed, and `equidiff train --init-from` fine-tuning a run on them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers_data import SyntheticEpisode, write_synthetic_episode

from equidiff_core.data.dataset import DemoDataset, dataset_stats, load_episode_arrays
from equidiff_core.data.episode_arrays import DatasetConfig, write_packed
from equidiff_core.data.recording import RecordingConfig
from equidiff_core.data.segments import GATE_PAUSE_PREFIX, FrameSource, SourceWeights
from equidiff_core.wire.rosmsg import NS_PER_S
from equidiff_ros.cli import main as cli

CFG = RecordingConfig(min_free_gib=0.0)
EP = SyntheticEpisode(duration_s=6.0, image_size=None)  # 30 observations at 5 Hz
# the policy runs, its gate holds the arm at 2.5 s, the operator takes over at 3.5 s and drives to the end
ROLL_OUT = {
    "policy_states": (
        (0.0, "running"),
        (2.5, f"{GATE_PAUSE_PREFIX}: doubt 0.9 over 0.5"),
        (3.5, "paused teleop"),
    ),
    "teleop_active": ((0.0, False), (3.5, True)),
}
DATA = DatasetConfig(horizon=4, n_obs_steps=1, n_action_steps=2)


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("corrections")
    return {
        "demo": write_synthetic_episode(folder / "demo_0000", EP, config=CFG),
        "rollout": write_synthetic_episode(folder / "rollout_0000", EP, config=CFG, **ROLL_OUT),
    }


def expected_sources(stamps_ns: np.ndarray) -> np.ndarray:
    t = (stamps_ns - EP.t0_ns) / NS_PER_S
    return np.where(t < 2.5, FrameSource.POLICY, np.where(t < 3.5, FrameSource.HOLD, FrameSource.OPERATOR))


def test_each_frame_knows_who_drove_it(bags):
    demo, rollout = (load_episode_arrays(bags[k], DATA) for k in ("demo", "rollout"))
    assert np.all(demo.sources == FrameSource.DEMO) and demo.gate_alarms == 0
    np.testing.assert_array_equal(rollout.sources, expected_sources(rollout.stamps_ns))
    assert rollout.gate_alarms == 1  # the teleop pause after it is no alarm


def test_packed_episodes_keep_the_sources_and_a_bad_source_is_refused(bags, tmp_path):
    from equidiff_core.data.episode_arrays import read_packed
    from equidiff_core.data.mcap_reader import BagError

    rollout = load_episode_arrays(bags["rollout"], DATA)
    again = read_packed(write_packed(rollout, tmp_path / "r.episode.npz", DATA), DATA)
    np.testing.assert_array_equal(again.sources, rollout.sources)
    assert again.gate_alarms == 1
    rollout.sources = rollout.sources.copy()
    rollout.sources[0] = 9
    with pytest.raises(BagError, match="frame source 9"):
        read_packed(write_packed(rollout, tmp_path / "bad.episode.npz", DATA), DATA)


def test_stats_count_corrections_policy_time_and_alarms(bags):
    stats = dataset_stats(bags.values(), DATA)
    by_name = {Path(row["path"]).name: row for row in stats["episodes"]}
    rollout = by_name["rollout_0000"]
    assert rollout["corrected"] and not by_name["demo_0000"]["corrected"]
    assert rollout["seconds_by_source"] == pytest.approx({"demo": 0.0, "policy": 2.6, "operator": 2.4, "hold": 1.0})
    assert by_name["demo_0000"]["seconds_by_source"]["demo"] == pytest.approx(6.0)
    total = stats["total"]
    assert total["episodes_with_corrections"] == 1 and total["gate_alarms"] == 1
    assert total["correction_s"] == pytest.approx(2.4) and total["policy_s"] == pytest.approx(2.6)


def test_samples_are_weighed_by_their_current_frame(bags):
    episodes = [load_episode_arrays(bags[k], DATA) for k in ("demo", "rollout")]
    plain = DemoDataset(episodes, DATA)
    # default: the policy's frames and the held ones are not sampled, corrections count as demonstrations
    current = [episodes[e].sources[start] for e, start in plain.index]
    assert set(current) == {FrameSource.DEMO, FrameSource.OPERATOR} and plain.weights is None
    assert "weight" not in plain[0]

    weighed = DemoDataset(episodes, DATA, SourceWeights(intervention=3.0, policy=0.5))
    current = np.array([episodes[e].sources[start] for e, start in weighed.index])
    expected = np.select([current == FrameSource.OPERATOR, current == FrameSource.POLICY], [3.0, 0.5], 1.0)
    np.testing.assert_array_equal(weighed.weights, expected)
    assert FrameSource.HOLD not in current
    assert float(weighed[int(np.argmax(current == FrameSource.OPERATOR))]["weight"]) == 3.0
    with pytest.raises(ValueError, match="intervention"):
        SourceWeights(intervention=-1.0)


def test_weighted_loss_counts_each_sample_by_its_weight():
    from equidiff_core.config import Workspace
    from equidiff_core.policy.diffusion import make_policy
    from equidiff_core.policy.normalizer import Normalizer
    from equidiff_core.policy.presets import get_preset

    policy = make_policy("baseline", get_preset("tiny"), Workspace())
    policy.set_normalizer(Normalizer.from_workspace(policy.workspace))
    batch = policy_batch(policy, 3)
    unweighted = policy.compute_loss(batch, generator=torch.Generator().manual_seed(0))
    ones = policy.compute_loss({**batch, "weight": torch.ones(3)}, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(ones, unweighted)
    zeros = policy.compute_loss({**batch, "weight": torch.zeros(3)}, generator=torch.Generator().manual_seed(0))
    assert float(zeros.detach()) == 0.0
    doubled = policy.compute_loss({**batch, "weight": 2 * torch.ones(3)}, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(doubled, 2 * unweighted)
    from equidiff_core.policy.diffusion import PolicyInputError

    with pytest.raises(PolicyInputError, match="weight"):
        policy.compute_loss({**batch, "weight": torch.tensor([1.0, float("nan"), 1.0])})


def policy_batch(policy, n: int) -> dict:
    p, R = policy.preset, policy.workspace.resolution
    gen = torch.Generator().manual_seed(1)
    ee = torch.tensor([0.45, 0.0, 0.2, 1, 0, 0, 0, -1, 0, 0.04]).repeat(n, p.n_obs_steps, 1)
    action = torch.tensor([0.45, 0.0, 0.2, 1, 0, 0, 0, -1, 0, 0.04]).repeat(n, p.horizon, 1)
    voxels = (torch.rand((n, p.n_obs_steps, 4, R, R, R), generator=gen) < 0.01).to(torch.uint8) * 255
    return {"voxels": voxels, "ee": ee, "action": action}


@pytest.mark.slow
def test_train_init_from_fine_tunes_the_starting_run(bags, tmp_path, capsys):
    common = ["--steps", "0", "--batch-size", "4", "--val-fraction", "0", "--device", "cpu", "--no-progress"]
    start = tmp_path / "start"
    assert cli(["train", str(bags["demo"]), "--out", str(start), "--preset", "tiny", *common]) == 0
    capsys.readouterr()
    tuned = tmp_path / "tuned"
    flags = ["--init-from", str(start / "last.ckpt"), "--intervention-weight", "2"]
    assert cli(["train", *map(str, bags.values()), "--out", str(tuned), *flags, *common]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    # zero steps from the start: the same weights, so the start's were loaded (not a fresh initialisation)
    from equidiff_core.policy.file import open_policy_file

    assert open_policy_file(tuned / "policy.pt").weights_sha256 == open_policy_file(start / "policy.pt").weights_sha256
    assert summary["samples_by_source"]["policy"] == 0 and summary["samples_by_source"]["operator"] > 0
    recipe = json.loads((tuned / "run.json").read_text())["recipe"]
    assert recipe["init_from"] == str(start / "last.ckpt") and recipe["preset"] == "tiny"
    assert recipe["source_weights"] == {"intervention": 2.0, "policy": 0.0}
    assert len(recipe["init_weights_sha256"]) == 64

    # the starting run brings its model: a flag asking for another is refused, and nothing is written
    refused = tmp_path / "refused"
    assert cli(["train", str(bags["demo"]), "--out", str(refused), *flags, "--preset", "compact", *common]) == 2
    assert "drop --preset" in capsys.readouterr().err and not refused.exists()


def test_dataset_stats_command_reports_the_corrections(bags, capsys):
    assert cli(["dataset", "stats", *map(str, bags.values()), "--horizon", "4", "--n-action-steps", "2"]) == 0
    out = capsys.readouterr().out
    assert "1 episodes with corrections (2.4 s of the operator's correction, 2.6 s of the policy); 1 gate alarms" in out
