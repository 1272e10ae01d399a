"""Few-step distillation (`equidiff distill`, training.distill): the student's sampler, the DDIM step it is
trained through, a tiny teacher distilled end to end, and the student selected by its policy file alone."""

from __future__ import annotations

import json
import math

import pytest
import torch
from helpers_data import SyntheticEpisode, write_synthetic_episode

from equidiff_core.config import Workspace
from equidiff_core.data.dataset import DemoDataset, load_episodes
from equidiff_core.data.episode_arrays import DatasetConfig
from equidiff_core.data.recording import RecordingConfig
from equidiff_core.models import equivariance
from equidiff_core.models.sampling import (
    ListedDDIMScheduler,
    ddim_step_between,
    make_inference_scheduler,
    sampler_timesteps,
    uniform_timesteps,
)
from equidiff_core.policy.file import open_policy_file
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.policy.presets import get_preset
from equidiff_core.training.distill import student_sampler
from equidiff_core.twin.config import load_twin_config
from equidiff_core.twin.shipped import SHIPPED_CHECKPOINT
from equidiff_ros.cli import main as cli

FP32_EXACT = 1e-5  # as test_equivariance: a C4-exact network leaves only float rounding


def test_uniform_timesteps_end_on_the_clean_sample():
    assert uniform_timesteps(100, 4, 90) == [90, 65, 40, 15]
    assert uniform_timesteps(100, 2, 90) == [90, 40] and uniform_timesteps(100, 1, 99) == [99]
    assert uniform_timesteps(100, 4, 75) == [75, 50, 25, 0]
    with pytest.raises(ValueError, match="must start in 75..99"):
        uniform_timesteps(100, 4, 70)  # its last step would land at t = 20, not on the clean sample
    with pytest.raises(ValueError, match="steps must be in 1..100"):
        uniform_timesteps(100, 0, 90)


def test_a_listed_sampler_steps_to_the_next_listed_timestep_as_ddim_step_between():
    preset = get_preset("tiny")
    sched = make_inference_scheduler(preset, timesteps=(90, 60, 12, 0))
    assert isinstance(sched, ListedDDIMScheduler) and [int(t) for t in sched.timesteps] == [90, 60, 12, 0]
    alphas = sched.alphas_cumprod
    generator = torch.Generator().manual_seed(0)
    x = torch.randn(3, 16, 14, generator=generator)
    for t, after in zip([90, 60, 12, 0], [60, 12, 0, None]):
        eps = torch.randn(x.shape, generator=generator)
        ours = ddim_step_between(x, eps, alphas[t], alphas[after] if after is not None else torch.tensor(1.0))
        theirs = sched.step(eps, torch.tensor(t), x).prev_sample
        torch.testing.assert_close(ours, theirs, rtol=0, atol=0)
        x = theirs
    for bad in ((90, 90, 12), (90, 100), (), (12, 60)):
        with pytest.raises(ValueError, match="timesteps must"):
            make_inference_scheduler(preset, timesteps=bad)
    with pytest.raises(ValueError, match="4 inference steps but 2 timesteps"):
        make_inference_scheduler(preset, 4, timesteps=(90, 40))


def test_a_listed_sampler_is_diffusers_own_where_that_applies():
    # evenly spaced timesteps are the ones diffusers' DDIM step assumes: both samplers then take the same steps
    preset = get_preset("tiny")
    listed = make_inference_scheduler(preset, timesteps=(99, 74, 49, 24))
    own = make_inference_scheduler(preset, 4, "trailing")
    assert [int(t) for t in own.timesteps] == [99, 74, 49, 24]
    generator = torch.Generator().manual_seed(1)
    x = y = torch.randn(2, 16, 14, generator=generator)
    for t in own.timesteps:
        eps = torch.randn(x.shape, generator=generator)
        x, y = listed.step(eps, t, x).prev_sample, own.step(eps, t, y).prev_sample
        torch.testing.assert_close(x, y, rtol=1e-6, atol=1e-6)


def test_an_older_files_first_timestep_reads_as_its_evenly_spaced_timesteps():
    assert sampler_timesteps({"steps": 4, "first_timestep": 90}, 100) == (90, 65, 40, 15)
    assert sampler_timesteps({"steps": 2, "timesteps": [90, 12]}, 100) == (90, 12)
    assert sampler_timesteps({"steps": 16, "timestep_spacing": "leading"}, 100) is None
    with pytest.raises(ValueError, match="steps 3 but 2 timesteps"):
        sampler_timesteps({"steps": 3, "timesteps": [90, 12]}, 100)


def test_each_student_step_is_a_stretch_of_the_teachers_own_trajectory():
    teacher = [int(t) for t in make_inference_scheduler(get_preset("compact")).timesteps]  # 90, 84, ..., 0
    sampler = student_sampler((90, 60, 12, 0), teacher, 100)
    assert sampler.timesteps == (90, 60, 12, 0)
    assert sampler.teacher_paths == (
        (90, 84, 78, 72, 66, 60),
        (60, 54, 48, 42, 36, 30, 24, 18, 12),
        (12, 6, 0),
        (0, -1),  # -1: the clean sample; the teacher's own last step
    )
    # every teacher step is in exactly one student step's path
    assert [t for path in sampler.teacher_paths for t in path[:-1]] == teacher
    # a student timestep off the teacher's grid is still an end of its paths
    off = student_sampler((80, 25), teacher, 100)
    assert off.teacher_paths == ((80, 78, 72, 66, 60, 54, 48, 42, 36, 30, 25), (25, 24, 18, 12, 6, 0, -1))
    with pytest.raises(ValueError, match="timesteps must"):
        student_sampler((60, 90), teacher, 100)


def test_the_shipped_four_step_policy_is_the_shipped_weights_through_its_own_timesteps():
    four = load_inference_policy(SHIPPED_CHECKPOINT.with_name("policy_ddim4.pt"))
    assert four.explicit_timesteps == (90, 60, 12, 0) and four.inference_steps == 4
    assert four.timesteps == [90, 60, 12, 0]
    assert four.weights_sha256 == load_inference_policy(SHIPPED_CHECKPOINT).weights_sha256 != "unhashed"


@pytest.fixture(scope="module")
def tiny_teacher(tmp_path_factory):
    """A tiny EquiDiff run (a few steps on one synthetic demo) and that demo."""
    folder = tmp_path_factory.mktemp("distill")
    demo = write_synthetic_episode(
        folder / "demo_0000", SyntheticEpisode(duration_s=4.0, image_size=None), config=RecordingConfig(min_free_gib=0)
    )
    run = folder / "teacher"
    flags = ["--preset", "tiny", "--steps", "5", "--batch-size", "4", "--val-fraction", "0", "--device", "cpu"]
    assert cli(["train", str(demo), "--out", str(run), *flags, "--no-progress"]) == 0
    return run / "last.ckpt", demo


@pytest.mark.slow
def test_distill_trains_an_equivariant_student_that_its_file_selects(tiny_teacher, tmp_path, capsys):
    teacher, demo = tiny_teacher
    capsys.readouterr()
    student = tmp_path / "student.pt"
    argv = ["distill", str(teacher), "--demos", str(demo), "--out", str(student), "--timesteps", "90", "36"]
    assert cli([*argv, "--train-steps", "150", "--batch-size", "16", "--lr", "1e-3", "--crops", "2"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["inputs"] == 2 * summary["frames"]  # the centred crop and a random one per frame
    assert summary["timesteps"] == [90, 36] and summary["sampler"] == {"steps": 2, "timesteps": [90, 36]}
    assert summary["teacher_paths"][0][0] == 90 and summary["teacher_paths"][-1][-1] == -1
    assert summary["train_steps"] == 150 and summary["frames"] > 0 and summary["recipe"]["crops"] == 2
    # the student learned the teacher's path: on the same held-out batch its one step lands nearer two of his
    assert summary["check_loss_after"] < 0.8 * summary["check_loss_before"]

    # the file alone selects the student's sampler; asking for steps overrides it
    policy = load_inference_policy(student)
    assert policy.inference_steps == 2 and policy.timesteps == [90, 36]
    assert policy.explicit_timesteps == (90, 36)
    assert load_inference_policy(student, inference_steps=8).explicit_timesteps is None
    other = load_inference_policy(student, timesteps=(90, 60, 12, 0))  # another sampler, asked for by its timesteps
    assert other.inference_steps == 4 and other.timesteps == [90, 60, 12, 0]
    assert open_policy_file(student).config["sampler"] == {"steps": 2, "timesteps": [90, 36]}

    # `bench policy` times what the file selects, and says so
    timing = ["bench", "policy", "--checkpoint", str(student), "--device", "cpu", "--precision", "fp32"]
    assert cli([*timing, "--no-jit", "--iters", "1", "--eager-iters", "0"]) == 0
    timed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert timed["inference_steps"] == 2 and timed["timesteps"] == [90, 36] and timed["ddim16_median_ms"] > 0

    # the student stays C4-equivariant through its own sampler (its weights are escnn's, re-exported)
    scene = load_twin_config().scene
    voxels, ee = equivariance.twin_scenes(policy.preset, Workspace(), count=1, seed=3, scene=scene)
    report = equivariance.measure(equivariance.ExportedModel(policy), voxels, ee, angles_deg=(90, 180, 270))
    assert report["sampling"]["c4_max_rel_err"] <= FP32_EXACT and math.isfinite(report["sampling"]["c4_max_rel_err"])

    # an existing output is refused before any work, and left as it is
    before = student.read_bytes()
    assert cli([*argv, "--train-steps", "1"]) == 2
    assert "exists" in capsys.readouterr().err and student.read_bytes() == before
    assert cli([*argv, "--train-steps", "-1", "--force"]) == 2
    assert "--train-steps must be >= 0" in capsys.readouterr().err and student.read_bytes() == before
    bad = tmp_path / "bad.pt"  # timesteps that do not decrease: refused, nothing written
    assert cli(["distill", str(teacher), "--demos", str(demo), "--out", str(bad), "--timesteps", "60", "90"]) == 2
    assert "timesteps must decrease strictly" in capsys.readouterr().err and not bad.exists()

    # no training at all: the teacher's weights at the student's sampler, the baseline a distillation must beat
    undistilled = tmp_path / "undistilled.pt"
    untrained = ["distill", str(teacher), "--demos", str(demo), "--out", str(undistilled), "--timesteps", "90", "36"]
    assert cli([*untrained, "--train-steps", "0", "--crops", "2"]) == 0
    plain = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert plain["train_steps"] == 0 and plain["final_loss"] is None
    assert plain["check_loss_after"] == plain["check_loss_before"]
    assert plain["check_loss_before"] == summary["check_loss_before"]


def test_a_roll_out_teaches_at_every_frame_the_policy_or_the_operator_drove(tiny_teacher, tmp_path, capsys):
    # Training's default leaves the policy's own frames out (HG-DAgger); the teacher answers at every frame,
    # so distilling from a roll-out (the policy until 2 s, then the operator) uses as many as a demo of its length.
    teacher, demo = tiny_teacher
    rollout = write_synthetic_episode(
        tmp_path / "rollout_0000",
        SyntheticEpisode(duration_s=4.0, image_size=None),
        config=RecordingConfig(min_free_gib=0),
        policy_states=((0.0, "running"), (2.0, "paused teleop")),
        teleop_active=((0.0, False), (2.0, True)),
    )
    frames = {}
    for name, bag in (("demo", demo), ("rollout", rollout)):
        capsys.readouterr()
        argv = [
            "distill",
            str(teacher),
            "--demos",
            str(bag),
            "--out",
            str(tmp_path / f"{name}.pt"),
            "--timesteps",
            "90",
        ]
        assert cli([*argv, "--train-steps", "0"]) == 0
        frames[name] = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["frames"]
    assert frames["rollout"] == frames["demo"] > 0
    weighted = DemoDataset(load_episodes([rollout], DatasetConfig())[0], DatasetConfig())  # training's default
    assert 0 < len(weighted) < frames["rollout"]


def test_sampler_gap_script_finds_no_gap_for_the_policys_own_timesteps_and_one_for_four_steps(tiny_teacher):
    # scripts/sampler_gap.py is the command behind docs/denoising_steps.md's choice of timesteps
    import os
    import subprocess
    import sys
    from pathlib import Path

    teacher, demo = tiny_teacher
    root = Path(__file__).resolve().parents[1]
    own = ",".join(str(t) for t in range(90, -1, -6))  # the preset's DDIM-16 "leading": the reference itself
    result = subprocess.run(
        [sys.executable, str(root / "scripts/sampler_gap.py"), str(teacher.parent / "policy.pt"), "--demos", str(demo)]
        + ["--frames", "3", "--noises", "2", "--schedules", own, "90,65,40,15"],
        capture_output=True,
        text=True,
        timeout=300,
        env=dict(os.environ, PYTHONPATH=str(root / "src")),
    )
    assert result.returncode == 0, result.stderr[-2000:]
    rows = {len(r["timesteps"]): r for r in map(json.loads, result.stdout.strip().splitlines())}
    assert rows[16]["position_gap_mm"] < 0.01 and rows[16]["width_gap_mm"] < 0.01  # float rounding at most
    assert rows[4]["position_gap_mm"] > 0.01 and rows[4]["frames"] == 3 and rows[4]["executed_steps"] > 0


@pytest.mark.slow
@pytest.mark.sim
def test_record_rollouts_records_a_policys_twin_episodes_and_refuses_an_existing_folder(tmp_path):
    # scripts/record_rollouts.py: the roll-outs `equidiff distill --demos` takes beside the demos
    import os
    import subprocess
    import sys
    from pathlib import Path

    from equidiff_core.data.bags import read_episode
    from equidiff_core.twin.config import TwinConfig
    from equidiff_core.twin.standin import make_standin_policy

    root = Path(__file__).resolve().parents[1]
    policy = make_standin_policy(tmp_path / "standin.pt", Workspace(), preset="tiny", cfg=TwinConfig())
    out = tmp_path / "round"
    argv = [sys.executable, str(root / "scripts/record_rollouts.py"), str(policy), str(out), "--seed", "7"]
    env = dict(os.environ, PYTHONPATH=str(root / "src"), OMP_NUM_THREADS="1")
    done = subprocess.run([*argv, "--episodes", "1", "--max-duration", "2"], capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    (episode,) = json.loads((tmp_path / "round.json").read_text())
    assert episode["seed"] == 7 and episode["duration_s"] <= 2.5
    assert read_episode(Path(episode["bag"])).meta is not None  # a bag our own reader accepts
    again = subprocess.run([*argv, "--episodes", "1"], capture_output=True, text=True, env=env)
    assert again.returncode == 2 and "exists" in again.stderr
