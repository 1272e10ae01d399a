"""`equidiff train` end to end on CPU from bags: checkpoint, export, plot, split, resume, determinism."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers_data import SyntheticEpisode, write_synthetic_episode

from equidiff_ros.cli import main as cli

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    from equidiff_core.data.recording import RecordingConfig

    folder = tmp_path_factory.mktemp("bags")
    cfg = RecordingConfig(min_free_gib=0.0)
    write_synthetic_episode(
        folder / "pick_0001", SyntheticEpisode(duration_s=4.0, cube_xy=(0.42, -0.05), yaw=-0.4), config=cfg
    )
    write_synthetic_episode(
        folder / "pick_0002", SyntheticEpisode(duration_s=4.0, cube_xy=(0.50, 0.06), yaw=0.8), config=cfg
    )
    return [str(ROOT / "bags" / "sample_pick_0000"), str(folder)]


def train(bags, out, *extra):
    return cli(
        [
            "train",
            *bags,
            "--out",
            str(out),
            "--preset",
            "tiny",
            "--policy",
            "equidiff",
            "--steps",
            "3",
            "--batch-size",
            "4",
            "--warmup-steps",
            "1",
            "--eval-every",
            "3",
            "--checkpoint-every",
            "2",
            "--eval-max-samples",
            "3",
            "--val-fraction",
            "0.34",
            "--seed",
            "5",
            "--device",
            "cpu",
            "--no-progress",
            *extra,
        ]
    )


def test_train_writes_a_loadable_policy_and_plot(bags, tmp_path, capsys):
    from equidiff_core.policy.inference import load_inference_policy

    out = tmp_path / "run"
    assert train(bags, out) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["train_episodes"] == 2 and summary["val_episodes"] == 1 and summary["skipped"] == 0
    for name in ("last.ckpt", "policy.pt", "history.json", "training.png", "split.json"):
        assert (out / name).is_file(), name
    assert (out / "training.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    split = json.loads((out / "split.json").read_text())
    assert not set(split["train"]) & set(split["val"])  # whole episodes held out
    history = json.loads((out / "history.json").read_text())
    evals = [h for h in history if "val_action_mse" in h]
    assert evals and evals[-1]["step"] == 3 and np.isfinite(evals[-1]["val_action_mse"])
    assert summary["val_action_mse"] == evals[-1]["val_action_mse"]
    policy = load_inference_policy(out / "policy.pt")
    assert policy.preset.rotation_aug == "continuous"  # the preset's own
    from equidiff_core.data.dataset import DemoDataset
    from equidiff_core.data.episode_arrays import DatasetConfig

    ds = DemoDataset.from_bags([bags[0]], DatasetConfig())
    sample = ds[0]
    pred = policy.predict(sample["voxels"][0].numpy(), sample["ee"][0].numpy(), seed=0)
    assert pred.shape == (16, 10) and np.all(np.isfinite(pred))

    # same seed, same data -> the same run
    again = tmp_path / "again"
    assert train(bags, again) == 0
    losses = lambda p: [h["loss"] for h in json.loads((p / "history.json").read_text()) if "loss" in h]
    assert losses(out) == losses(again)
    # --noise-repeats reaches the loss: four (noise, step) draws per observation give other losses
    repeats = tmp_path / "repeats"
    assert train(bags, repeats, "--noise-repeats", "4") == 0
    assert len(losses(repeats)) == len(losses(out)) and losses(repeats) != losses(out)
    assert train(bags, tmp_path / "none", "--noise-repeats", "0") == 2
    assert "noise_repeats must be >= 1" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()  # a run that never started leaves nothing to block the rerun

    # --force replaces a run only once the new one is complete: a failed one leaves it as it was
    before = _tree(repeats)
    assert train(bags, repeats, "--noise-repeats", "0", "--force") == 2
    assert _tree(repeats) == before
    capsys.readouterr()
    assert train(bags, repeats, "--force") == 0
    assert losses(repeats) == losses(again)
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["policy"] == str(repeats / "policy.pt")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again", "repeats", "run"]  # no temporary left

    # an existing run is never silently restarted; --resume continues it from its checkpoint and split
    before = _tree(out)
    assert train(bags, out) == 2
    assert "pass --resume to continue its run, --force to replace it" in capsys.readouterr().err
    assert _tree(out) == before
    assert (
        cli(
            [
                "train",
                *bags,
                "--out",
                str(out),
                "--preset",
                "tiny",
                "--steps",
                "5",
                "--batch-size",
                "4",
                "--warmup-steps",
                "1",
                "--eval-every",
                "5",
                "--checkpoint-every",
                "0",
                "--eval-max-samples",
                "2",
                "--val-fraction",
                "0.9",
                "--seed",
                "5",
                "--device",
                "cpu",
                "--no-progress",
                "--resume",
            ]
        )
        == 0
    )
    resumed = json.loads((out / "history.json").read_text())
    steps = [h["step"] for h in resumed if "loss" in h]
    assert steps[0] == 1 and steps[-1] == 5  # history kept, continued to step 5
    assert json.loads((out / "split.json").read_text()) == split  # resume keeps the held-out episodes

    # a time budget ends the run early, and it still exports and says so
    capsys.readouterr()
    assert train(bags, tmp_path / "budget", "--max-minutes", "0.0001", "--rotation-aug", "none") == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["steps"] == 1 and "time budget" in summary["stopped"]
    # --rotation-aug replaces the preset's and is saved with the policy; run.json keeps the recipe
    recipe = json.loads((tmp_path / "budget" / "run.json").read_text())["recipe"]
    assert recipe["device"] == "cpu" and recipe["batch_size"] == 4 and recipe["rotation_aug"] == "none"
    assert recipe["noise_repeats"] == 1 and recipe["ema"] is False
    assert recipe["schedule_steps"] == 3 and summary["steps"] == 1  # planned against trained
    assert load_inference_policy(tmp_path / "budget" / "policy.pt").preset.rotation_aug == "none"


def _tree(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_train_reports_missing_data(tmp_path, capsys):
    assert (
        cli(
            [
                "train",
                str(tmp_path / "nothing"),
                "--out",
                str(tmp_path / "run"),
                "--preset",
                "tiny",
                "--steps",
                "1",
                "--no-progress",
            ]
        )
        == 1
    )
    err = capsys.readouterr().err
    assert "no such bag" in err and "no usable episodes" in err
    assert not (tmp_path / "run").exists()  # nothing left that would refuse the rerun
