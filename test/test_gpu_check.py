"""The GPU check (issue 28) rehearsed on the CPU: every part of scripts/gpu_check.sh runs with tiny
sizes, so that no typo reaches the few GPU minutes; and the pieces it is built from."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

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


@pytest.mark.slow
@pytest.mark.timeout(1500)  # ~8 processes, each importing torch and escnn: minutes when the 2 cores are shared
def test_cpu_rehearsal_runs_every_part_and_its_trained_checkpoint_loads_on_the_cpu(tmp_path):
    """`scripts/gpu_check.sh --device cpu --tiny`: the GPU check's commands end to end (graph modes
    skipped), one JSON file, the returned files where $OUT would be, and they verify on the CPU."""
    from equidiff_core.dataset import pack_episodes

    packed, out, result = tmp_path / "packed", tmp_path / "out", tmp_path / "gpu_check.json"
    assert len(pack_episodes([SAMPLE_BAG], packed)[0]) == 1  # what gpu_prepare.sh carries
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    proc = subprocess.run(
        ["bash", str(ROOT / "scripts" / "gpu_check.sh"), "--device", "cpu", "--tiny"]
        + ["--work", str(tmp_path / "work"), "--json", str(result), "--packed", str(packed)],
        env={**env, "OUT": str(out), "PYTHON": sys.executable},
        capture_output=True,
        text=True,
        timeout=1200,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    check = json.loads(result.read_text())
    assert json.loads((out / "gpu_check.json").read_text()) == check
    assert check["rehearsal"] and check["gpu"] is None and check["parts_failed"] == []
    assert set(check["parts_ok"]) == {
        "policy_paper",
        "ddp",
        "train_bench_tiny_equidiff",
        "training",
        "train_bench_tiny_baseline",
    }
    modes = check["parts"]["policy_paper"]["result"]["modes"]
    assert modes["bf16-traced-graph"] == {"skipped": "CUDA graphs need a CUDA device"}
    assert check["paper_ddim16_p99_ms"] == min(m["ddim16_p99_ms"] for m in modes.values() if "ddim16_p99_ms" in m)
    assert check["paper_rtc_vs_plain"] > 0 and check["paper_p99_goal_met"] is None  # no goal for a rehearsal
    assert (check["ddp_backend"], check["ddp_result_loads"]) == ("gloo", True)
    assert check["parts"]["ddp"]["check"]["world_size"] == 1
    training = check["parts"]["training"]
    assert training["check"]["loads_on_cpu"] and training["check"]["too_big_to_return"] == []
    assert training["steps"] == 8 and training["loss_first"] > 0 and training["loss_last"] > 0
    runs = check["train_samples_per_s"]
    assert {"tiny/equidiff/bf16/loader", "tiny/equidiff/fp32/device", "tiny/baseline/fp32/loader"} <= runs.keys()
    returned = {p.name for p in out.iterdir()}
    assert {"gpu_check.json", "gpu_check.log", "train_policy.pt", "train_last.ckpt"} <= returned
    assert len(returned) <= 8  # what $OUT gives back at most

    # what a later session runs on the files a GPU run returned (`scripts/gpu_check.py verify DIR`)
    verified = _gpu_check_module().verify(out)
    assert verified == {k: v for k, v in training["check"].items() if k != "too_big_to_return"}
