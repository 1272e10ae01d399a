"""The GPU check checked on the CPU: every part of scripts/gpu_check.sh parses with the CLI it will
run, so that no typo reaches the few GPU minutes; and the pieces it is built from."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from equidiff_core.benches.timing import InferenceMode, best_mode, parse_training_runs

ROOT = Path(__file__).resolve().parents[1]
SAMPLE_BAG = ROOT / "bags" / "sample_pick_0000"


def _gpu_check_module():
    spec = importlib.util.spec_from_file_location("gpu_check", ROOT / "scripts" / "gpu_check.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("gpu_check", module)  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_inference_modes_and_training_runs_parse_or_say_what_is_expected():
    assert InferenceMode.parse("bf16-traced-graph") == InferenceMode("bf16", "traced", True)
    assert InferenceMode.parse("fp32-eager").name == "fp32-eager"
    for bad in ("bf16", "bf16-graph", "fp16-traced", "bf16-traced-graph-x"):
        with pytest.raises(ValueError, match="PRECISION-EXECUTION"):
            InferenceMode.parse(bad)
    assert parse_training_runs("bf16,fp32:loader") == [("bf16", "auto"), ("fp32", "loader")]
    with pytest.raises(ValueError, match=r"PRECISION\[:DATA\]"):
        parse_training_runs("bf16:disk")
    results = {"a": {"ddim16_p99_ms": 9.0}, "b": {"error": "x"}, "c": {"ddim16_p99_ms": 4.5}}
    assert best_mode(results) == "c" and best_mode({"b": {"error": "x"}}) is None


def test_summary_names_the_best_mode_goals_and_what_failed():
    gpu_check = _gpu_check_module()
    paper = {"ddim16_p99_ms": 12.0, "ddim16_median_ms": 9.0, "rtc_vs_plain": 1.1, "max_abs_diff_vs_ungraphed": 0.0}
    results = {
        "rehearsal": False,
        "parts": {
            "policy_paper": {
                "status": "ok",
                "result": {
                    "preset": "paper",
                    "modes": {
                        "bf16-traced": {"ddim16_p99_ms": 60.0, "ddim16_median_ms": 50.0},
                        "bf16-traced-graph": paper,
                    },
                },
            },
            "policy_compact": {"status": "error", "error": "exit 1"},
            "train_bench_paper_equidiff": {
                "status": "ok",
                "result": {
                    "preset": "paper",
                    "policy": "equidiff",
                    "cuda": {"precision": "bf16", "data": "device", "samples_per_s": 100.0, "gpu_busy_pct": 95.0},
                },
            },
        },
    }
    summary = gpu_check.summarize(results)
    assert summary["paper_ddim16_p99_ms"] == 12.0 and summary["paper_best_mode"] == "bf16-traced-graph"
    assert summary["paper_p99_goal_met"] is True and summary["paper_rtc_vs_plain"] == 1.1
    assert summary["compact_ddim16_p99_ms"] is None and summary["parts_failed"] == ["policy_compact"]
    assert summary["train_samples_per_s"] == {"paper/equidiff/bf16/device": 100.0}
    assert summary["train_gpu_busy_pct"] == {"paper/equidiff/bf16/device": 95.0}
    assert summary["graph_max_abs_diff"] == 0.0


def test_size_counts_what_a_device_call_would_send():
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "gpu_check.py"), "size", "--carry", "src"],
        capture_output=True,
        text=True,
    )
    out = json.loads(proc.stdout)
    assert proc.returncode == (0 if out["fits"] else 3)
    assert out["limit_mib"] == 64 and out["carry_mib"]["src"] > 0.5
    assert out["total_mib"] == pytest.approx(out["tree_mib"] + out["carry_mib"]["src"], abs=0.02)
    assert "src" in out["largest"]


def test_every_part_of_the_plan_parses_with_the_cli_it_will_run(tmp_path):
    """`gpu_check.sh --dry-run`: the GPU plan's commands as the CLI parses them, through the script a
    device call runs; the CPU rehearsal's plan (`--device cpu --tiny`) through the same function in this
    process. The full rehearsal (minutes) is a documented command, docs/model.md."""
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "PYTHON": sys.executable}
    proc = subprocess.run(
        ["bash", str(ROOT / "scripts" / "gpu_check.sh"), "--dry-run", "--device", "cuda"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    parts = json.loads(proc.stdout)["parts"]
    assert {"policy_paper", "policy_compact", "ddp", "training"} <= parts.keys() and set(parts.values()) == {""}
    gpu_check = _gpu_check_module()
    rehearsal = gpu_check.Check(
        SimpleNamespace(device="cpu", tiny=True, budget_s=None, work=str(tmp_path), json=None, packed=None)
    )
    parts = gpu_check.parse_plan(rehearsal)
    assert {"policy_paper", "ddp", "training"} <= parts.keys() and set(parts.values()) == {""}
    assert "policy_compact" not in parts  # the rehearsal's two presets are both tiny


def test_a_mistyped_option_is_named_before_anything_runs(monkeypatch, tmp_path):
    gpu_check = _gpu_check_module()
    check = gpu_check.Check(
        SimpleNamespace(device="cpu", tiny=True, budget_s=None, work=str(tmp_path), json=None, packed=None)
    )
    typo = gpu_check.Part("train_bench_typo", check.cli("bench", "train", "--cuda-bach-size", "8"), 1, 1)
    monkeypatch.setattr(gpu_check, "plan", lambda _check: [typo])
    assert gpu_check.parse_plan(check) == {
        "train_bench_typo": "equidiff: error: unrecognized arguments: --cuda-bach-size 8"
    }
