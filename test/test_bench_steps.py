"""`equidiff bench steps`: success against DDIM steps, timed and rolled out per sampler, resumed, plotted."""

from __future__ import annotations

import json

import pytest
import torch

from equidiff_core.benches import BenchError
from equidiff_core.benches import denoising_steps as bench
from equidiff_core.config import Workspace
from equidiff_core.policy.diffusion import make_policy
from equidiff_core.policy.file import CheckpointError, export_policy
from equidiff_core.policy.normalizer import Normalizer
from equidiff_core.policy.presets import get_preset
from equidiff_core.twin.evaluate import EvalEpisode
from equidiff_ros.cli import main


@pytest.fixture(scope="module")
def tiny_policy_file(tmp_path_factory):
    torch.manual_seed(0)
    policy = make_policy("equidiff", get_preset("tiny"), Workspace())
    policy.set_normalizer(Normalizer.from_workspace(Workspace()))
    return export_policy(policy.eval(), tmp_path_factory.mktemp("steps") / "policy.pt")


class _RollOuts:
    """Stands in for ``evaluate_policy``: outcomes from the sampler's step count (8 or more solve every scene
    but the first, fewer every other one), a chunk switch fed to the probe, the calls counted."""

    def __init__(self, fail_on_steps: int | None = None):
        self.calls: list[tuple[int, str]] = []
        self.fail_on_steps = fail_on_steps

    def __call__(self, policy, cfg, lab, seeds, max_duration, *, recorder, latency_s, probe, threads, log):
        assert threads == 1 and latency_s == 0.1 and max_duration == 3.0
        if policy.inference_steps == self.fail_on_steps:
            raise RuntimeError("interrupted")
        self.calls.append((policy.inference_steps, policy.timestep_spacing))
        many = policy.inference_steps >= 8
        return [
            EvalEpisode(s, (i > 0) if many else (i % 2 == 0), 3.0, 15, 0.0, failed_predictions=0 if many else 1)
            for i, s in enumerate(seeds)
        ]


class _NoRecorder:
    def __init__(self, *args):
        pass

    def close(self):
        pass


def _argv(checkpoint, out, *extra):
    return [
        "bench",
        "steps",
        "--checkpoint",
        str(checkpoint),
        "--episodes",
        "4",
        "--max-duration",
        "3",
        "--timing-calls",
        "1",
        "--out",
        str(out),
        *extra,
    ]


def test_bench_steps_rows_timing_paired_and_plot_then_resumes_without_rolling_out_again(
    tiny_policy_file, tmp_path, monkeypatch, capsys
):
    roll_outs = _RollOuts()
    monkeypatch.setattr(bench, "evaluate_policy", roll_outs)
    monkeypatch.setattr(bench, "DirectRecorder", _NoRecorder)
    out, plot = tmp_path / "work", tmp_path / "figures" / "steps.png"
    argv = _argv(tiny_policy_file, out, "--steps", "4", "16", "1", "--plot", str(plot))
    assert main(argv) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert len(lines) == 1
    result = json.loads(lines[0])
    rows = {row["sampler"]: row for row in result["rows"]}
    # the policy's own sampler first, then the asked counts in their order (trailing by default)
    assert list(rows) == ["ddim16_leading", "ddim4_trailing", "ddim16_trailing", "ddim1_trailing"]
    assert roll_outs.calls == [(16, "leading"), (4, "trailing"), (16, "trailing"), (1, "trailing")]
    base, four, one = rows["ddim16_leading"], rows["ddim4_trailing"], rows["ddim1_trailing"]
    assert base["baseline"] and base["paired_vs_baseline"] is None and base["successes"] == 3
    assert four["successes"] == 2 and four["episodes"] == 4 and four["success"] == 0.5
    assert four["success_ci95"][0] < 0.5 < four["success_ci95"][1]
    # scenes 0 and 2 solved at 4 steps, 1, 2 and 3 by the baseline: one scene each way that only one solved
    paired = four["paired_vs_baseline"]
    assert paired["n"] == 4 and paired["difference"] == -0.25 and (paired["a_only"], paired["b_only"]) == (1, 2)
    assert one["timesteps"] == [99] and four["timesteps"] == [99, 74, 49, 24] and base["timesteps"][0] == 90
    assert four["failed_predictions"] == 4 and base["failed_predictions"] == 0
    for row in rows.values():
        assert 0 < row["inference_median_ms"] <= row["inference_p99_ms"]
        assert row["chunking"]["chunk_switches"] == 0 and row["boundary_dv_p95_mps"] is None  # no commands fed
    assert result["timing"]["ddim1_trailing"]["calls"] == 1 and result["cpu"] and result["complete"]
    assert len(result["timing_load_average_1min"]) == 2
    assert result["seeds"] == [100000, 100003] and result["pending"] == []
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" == (out / bench.PLOT_NAME).read_bytes()[:8]
    assert json.loads((out / "result.json").read_text()) == result

    # the same call again rolls nothing out: every sampler's roll-outs are reused, the figures the same
    assert main([*argv, "--force"]) == 0
    again = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert len(roll_outs.calls) == 4
    assert [r["successes"] for r in again["rows"]] == [r["successes"] for r in result["rows"]]
    # a plot the user named is refused before anything runs, left as it is
    plot.write_bytes(b"someone's figure")
    monkeypatch.setattr(bench, "load_twin_config", lambda *a: pytest.fail("refused after work began"))
    assert main(argv) == 2
    assert "exists; not replacing it" in capsys.readouterr().err and plot.read_bytes() == b"someone's figure"


def test_an_interrupted_bench_steps_keeps_what_it_rolled_out_and_resumes_there(tiny_policy_file, tmp_path, monkeypatch):
    monkeypatch.setattr(bench, "DirectRecorder", _NoRecorder)
    settings = bench.StepsSettings(
        checkpoint=tiny_policy_file,
        steps=(4, 2),
        spacing="trailing",
        episodes=2,
        seed=100000,
        max_duration=3.0,
        latency_ms=100.0,
        timing_calls=1,
        out=tmp_path / "work",
        plot=None,
    )
    interrupted = _RollOuts(fail_on_steps=2)
    monkeypatch.setattr(bench, "evaluate_policy", interrupted)
    with pytest.raises(RuntimeError, match="interrupted"):
        bench.run_steps_bench(settings)
    partial = json.loads((tmp_path / "work" / "result.json").read_text())
    assert not partial["complete"] and partial["pending"] == ["ddim2_trailing"]
    assert [r["sampler"] for r in partial["rows"]] == ["ddim16_leading", "ddim4_trailing"]
    resumed = _RollOuts()
    monkeypatch.setattr(bench, "evaluate_policy", resumed)
    result = bench.run_steps_bench(settings)
    assert resumed.calls == [(2, "trailing")] and result["complete"] and len(result["rows"]) == 3
    # the policy's own spacing asked for: its own count is the baseline, rolled out once
    leading = bench.run_steps_bench(
        bench.StepsSettings(**{**settings.__dict__, "steps": (16, 4), "spacing": "leading", "out": tmp_path / "l"})
    )
    assert [r["sampler"] for r in leading["rows"]] == ["ddim16_leading", "ddim4_leading"]


def test_a_distilled_policy_is_compared_at_its_own_sampler_on_the_same_scenes(
    tiny_policy_file, tmp_path, monkeypatch, capsys
):
    roll_outs = _RollOuts()
    monkeypatch.setattr(bench, "evaluate_policy", roll_outs)
    monkeypatch.setattr(bench, "DirectRecorder", _NoRecorder)
    # the same weights written as a 4-step policy through its own timesteps, as `equidiff distill` writes its student
    torch.manual_seed(0)
    policy = make_policy("equidiff", get_preset("tiny"), Workspace())
    policy.set_normalizer(Normalizer.from_workspace(Workspace()))
    with pytest.raises(CheckpointError, match="steps 3 but 4 timesteps"):  # a file that would not load is not written
        export_policy(policy.eval(), tmp_path / "student.pt", sampler={"steps": 3, "timesteps": [90, 60, 12, 0]})
    assert not (tmp_path / "student.pt").exists()
    student = export_policy(policy.eval(), tmp_path / "student.pt", sampler={"steps": 4, "timesteps": [90, 60, 12, 0]})
    assert main(_argv(tiny_policy_file, tmp_path / "work", "--steps", "--compare", str(student))) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    base, other = result["rows"]
    assert base["sampler"] == "ddim16_leading" and base["policy"] == str(tiny_policy_file)
    assert other["sampler"] == "student__ddim4_t90-60-12-0" and other["policy"] == str(student)
    assert other["timesteps"] == [90, 60, 12, 0] and not other["baseline"]
    assert other["paired_vs_baseline"]["n"] == 4 and other["successes"] == 2
    assert roll_outs.calls == [(16, "leading"), (4, "leading")]
    assert (tmp_path / "work" / "student__ddim4_t90-60-12-0" / "rollouts.json").is_file()


def test_bench_steps_refuses_settings_it_cannot_run_with(tiny_policy_file, tmp_path, capsys):
    assert main(_argv(tiny_policy_file, tmp_path / "w", "--episodes", "0")) == 2
    assert "need --episodes >= 1" in capsys.readouterr().err
    assert main(_argv(tiny_policy_file, tmp_path / "w", "--steps", "0")) == 2
    assert "inference steps must be in 1..100, got 0" in capsys.readouterr().err
    assert main(_argv(tmp_path / "none.pt", tmp_path / "w")) == 2
    assert capsys.readouterr().err == f"equidiff bench steps: no policy file at {tmp_path / 'none.pt'}\n"
    assert main(_argv(tiny_policy_file, tmp_path / "w", "--steps", "--compare", str(tmp_path / "other.pt"))) == 2
    assert capsys.readouterr().err == f"equidiff bench steps: no policy file at {tmp_path / 'other.pt'}\n"
    assert main(_argv(tiny_policy_file, tmp_path / "w", "--steps")) == 2
    assert "a step count or a --compare file" in capsys.readouterr().err
    with pytest.raises(BenchError, match="latency"):
        bench.run_steps_bench(
            bench.StepsSettings(tiny_policy_file, (4,), "trailing", 1, 0, 3.0, -1.0, 1, tmp_path / "w", None)
        )


@pytest.mark.slow
@pytest.mark.sim
def test_bench_steps_rolls_the_shipped_policy_out_in_the_twin(tmp_path, capsys):
    """The real roll-outs (the shipped checkpoint, one short episode, one step against its own 16): the
    chunk-boundary probe and the skipped answers reach the row."""
    assert (
        main(
            ["bench", "steps", "--episodes", "1", "--max-duration", "3", "--timing-calls", "1"]
            + ["--steps", "2", "--out", str(tmp_path / "w")]
        )
        == 0
    )
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    base, two = result["rows"]
    assert (base["steps"], two["steps"]) == (16, 2) and result["preset"] == "compact"
    assert base["chunking"]["chunk_switches"] >= 1 and base["boundary_dv_p95_mps"] >= 0
    assert two["episodes"] == 1 and two["failed_predictions"] >= 0
    assert base["inference_vs_baseline"] == 1.0 and two["inference_median_ms"] > 0
