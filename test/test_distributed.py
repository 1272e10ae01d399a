"""Training that scales past one process: the device-resident batch source, the
shared shard sampler, the torch.distributed helpers, and two gloo ranks trained with torchrun."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from equidiff_core.config import Workspace
from equidiff_core.data.dataset import DemoDataset
from equidiff_core.data.episode_arrays import DatasetConfig
from equidiff_core.data.synthetic import CubeDataset
from equidiff_core.policy.diffusion import make_policy
from equidiff_core.policy.presets import get_preset
from equidiff_core.training import distributed
from equidiff_core.training.batches import (
    BatchSourceError,
    DeviceBatchSource,
    estimate_nbytes,
    loader_batches,
    make_sampler,
)
from equidiff_core.training.config import TrainConfig, resolve_precision
from equidiff_core.training.loop import train

ROOT = Path(__file__).resolve().parents[1]
SAMPLE_BAG = ROOT / "bags" / "sample_pick_0000"


def _same_batch(a: dict, b: dict):
    assert a.keys() == b.keys()
    for k, value in a.items():
        assert value.dtype == b[k].dtype, k
        torch.testing.assert_close(value, b[k], rtol=0, atol=0, msg=k)


def test_device_source_of_episodes_holds_each_frame_once_and_gives_the_datasets_samples(tmp_path):
    ds = DemoDataset.from_bags([SAMPLE_BAG], DatasetConfig(n_obs_steps=2, cache_dir=str(tmp_path)))
    source = DeviceBatchSource.from_dataset(ds, "cpu")
    assert len(source) == len(ds) and source.frames.shape[0] == len(ds.episodes[0])  # frames shared by windows
    assert source.nbytes == estimate_nbytes(ds)
    idx = torch.tensor([0, 5, len(ds) - 1, 5])
    batch = source.batch(idx)
    expected = {k: torch.stack([ds[int(i)][k] for i in idx]) for k in ("voxels", "ee", "action")}
    _same_batch(batch, expected)
    assert batch["voxels"].shape == (4, 2, 4, 64, 64, 64) and batch["voxels"].any()


def test_device_source_yields_the_loaders_batches_and_ranks_draw_disjoint_shards():
    ds = CubeDataset(10, seed=0)
    source = DeviceBatchSource.from_dataset(ds, "cpu")
    loader = loader_batches(ds, make_sampler(ds, seed=3), batch_size=4)
    device = source.batches(make_sampler(ds, seed=3), batch_size=4)
    for _ in range(5):  # two full batches an epoch (drop-last), into the second and third epochs
        _same_batch(next(device), next(loader))

    def epoch_indices(rank: int) -> list[int]:
        # a source whose "ee" holds the sample index tells which samples a rank drew
        tagged = DeviceBatchSource(source.frames, source.obs_index, torch.arange(10.0)[:, None, None], source.action)
        batches = tagged.batches(make_sampler(ds, seed=3, rank=rank, world_size=2), batch_size=5)
        return [int(i) for i in next(batches)["ee"].flatten()]

    r0, r1 = epoch_indices(0), epoch_indices(1)
    assert not set(r0) & set(r1) and sorted(r0 + r1) == list(range(10))
    with pytest.raises(BatchSourceError, match="empty"):
        DeviceBatchSource.from_dataset(CubeDataset(0), "cpu")


def test_single_process_helpers_and_a_torchrun_environment_missing_variables(monkeypatch):
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    assert distributed.init_from_env("cpu") == distributed.DistInfo()
    assert distributed.all_reduce_mean([2.0, 4.0]) == [2.0, 4.0] and distributed.broadcast_object("x") == "x"
    assert distributed.all_gather_object(1) == [1]
    distributed.barrier()
    a, b = (make_policy("baseline", get_preset("tiny"), Workspace()) for _ in range(2))
    assert distributed.parameter_digest(a.model) != distributed.parameter_digest(b.model)
    b.model.load_state_dict(a.model.state_dict())
    assert distributed.parameter_digest(a.model) == distributed.parameter_digest(b.model)
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.delenv("MASTER_ADDR", raising=False)
    with pytest.raises(distributed.DistributedError, match="torchrun"):
        distributed.init_from_env("cpu")


def test_torchrun_with_one_process_joins_a_group_of_one(monkeypatch):
    """`torchrun --nproc-per-node 1` (how one GPU checks the N-GPU path) forms a real
    process group: collectives and DDP run as with N ranks, not the single-process shortcuts."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    for key, value in {"WORLD_SIZE": "1", "RANK": "0", "LOCAL_RANK": "0", "MASTER_ADDR": "127.0.0.1"}.items():
        monkeypatch.setenv(key, value)
    monkeypatch.setenv("MASTER_PORT", str(port))
    try:
        info = distributed.init_from_env("cpu")
        assert info == distributed.DistInfo(rank=0, world_size=1, local_rank=0, backend="gloo") and info.distributed
        assert torch.distributed.is_initialized()
        assert distributed.all_reduce_mean([3.0, 5.0]) == [3.0, 5.0] and distributed.all_gather_object("x") == ["x"]
        distributed.barrier()
    finally:
        distributed.shutdown()
    assert not distributed.info().distributed
    monkeypatch.delenv("MASTER_PORT")  # WORLD_SIZE 1 without torchrun's rendezvous: one process, no group
    assert distributed.init_from_env("cpu") == distributed.DistInfo() and not torch.distributed.is_initialized()


def test_training_from_the_device_source_and_in_bf16_on_the_cpu(tmp_path):
    ds = CubeDataset(4, seed=1)
    cfg = {"steps": 2, "batch_size": 2, "warmup_steps": 1, "eval_every": 0, "log_every": 1, "checkpoint_every": 0}
    result = train(
        make_policy("baseline", get_preset("tiny"), Workspace()),
        ds,
        None,
        TrainConfig(**cfg, data="device", precision="bf16"),
        tmp_path / "a",
    )
    assert (result.data, result.precision, result.world_size) == ("device", "bf16", 1)
    assert all(np.isfinite(h["loss"]) for h in result.history if "loss" in h)
    # "auto": bf16 on CUDA, fp32 on the CPU
    assert resolve_precision("auto", torch.device("cpu")) == "fp32"
    assert resolve_precision("auto", torch.device("cuda", 0)) == "bf16"
    with pytest.raises(ValueError, match="precision"):
        TrainConfig(precision="fp16")


@pytest.mark.slow
def test_two_gloo_ranks_train_in_sync_and_leave_a_normal_checkpoint(tmp_path):
    """torchrun, 2 CPU processes, 3 steps of EquiDiff/tiny on the sample bag with the data resident
    on the (CPU) device: both ranks end with the same parameters, rank 0 wrote a checkpoint that
    loads, predicts and resumes in a single process."""
    from equidiff_core.policy.inference import load_inference_policy
    from equidiff_core.training.loop import (
        load_policy_from_checkpoint,
        load_training_checkpoint,
    )
    from equidiff_ros.cli import main as cli

    out = tmp_path / "run"
    args = [
        "train",
        str(SAMPLE_BAG),
        "--out",
        str(out),
        "--preset",
        "tiny",
        "--steps",
        "3",
        "--batch-size",
        "2",
        "--warmup-steps",
        "1",
        "--eval-every",
        "3",
        "--eval-max-samples",
        "2",
        "--checkpoint-every",
        "0",
        "--val-fraction",
        "0",
        "--seed",
        "5",
        "--device",
        "cpu",
        "--data",
        "device",
        "--no-progress",
        "--cache-dir",
        str(tmp_path / "cache"),
    ]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--standalone",
            "--nproc-per-node",
            "2",
            "-m",
            "equidiff_ros.cli",
            *args,
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    summaries = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    assert len(summaries) == 1 and summaries[0]["steps"] == 3  # rank 0 alone reports

    history = json.loads((out / "history.json").read_text())
    sync = next(h for h in history if "param_digests" in h)
    assert sync["world_size"] == 2 and len(set(sync["param_digests"])) == 1
    restored = load_policy_from_checkpoint(out / "last.ckpt")
    assert distributed.parameter_digest(restored.model) == sync["param_digests"][0]
    recipe = json.loads((out / "run.json").read_text())["recipe"]
    assert (recipe["world_size"], recipe["data"], recipe["precision"]) == (2, "device", "fp32")

    sample = DemoDataset.from_bags([SAMPLE_BAG], DatasetConfig(cache_dir=str(tmp_path / "cache")))[0]
    pred = load_inference_policy(out / "policy.pt").predict(
        sample["voxels"][0].numpy(), sample["ee"][0].numpy(), seed=0
    )
    assert pred.shape == (16, 10) and np.all(np.isfinite(pred))

    # the data-parallel checkpoint resumes in one process like any other
    steps_at = args.index("--steps") + 1
    assert cli([*args[:steps_at], "4", *args[steps_at + 1 :], "--resume"]) == 0
    assert load_training_checkpoint(out / "last.ckpt")["step"] == 4
    steps = [h["step"] for h in json.loads((out / "history.json").read_text()) if "loss" in h]
    assert steps[0] == 1 and steps[-1] == 4


def test_bench_train_prints_one_json_line_naming_preset_batch_and_devices(capsys):
    from equidiff_ros.cli import main

    assert (
        main(
            [
                "bench",
                "train",
                "--preset",
                "tiny",
                "--policy",
                "baseline",
                "--batch-size",
                "2",
                "--steps",
                "1",
                "--warmup",
                "1",
                "--samples",
                "2",
            ]
        )
        == 0
    )
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1
    out = json.loads(lines[0])
    assert out["preset"] == "tiny" and out["params"] > 0
    cpu = out["cpu"]
    assert cpu["device"].startswith("cpu: ") and cpu["batch_size"] == 2 and cpu["precision"] == "fp32"
    assert cpu["samples_per_s"] > 0 and cpu["samples_per_s"] == pytest.approx(2 / cpu["sec_per_step"], rel=0.01)
    assert {"avx512", "native_bf16", "cores"} <= cpu.keys()
    assert 0 <= cpu["data_wait_share"] < 1  # the loop's wait for its next batch, over the step time
    if torch.cuda.is_available():
        assert out["cuda"]["precision"] == "bf16" and out["cuda"]["data"] == "device"
    else:
        assert out["cuda"] is None and "not available" in out["cuda_note"]


def test_bench_train_measures_each_precision_and_data_source_asked_for(capsys):
    from equidiff_ros.cli import main

    args = ["bench", "train", "--device", "cpu", "--preset", "tiny", "--policy", "baseline", "--batch-size", "2"]
    assert main([*args, "--steps", "1", "--warmup", "1", "--samples", "2", "--runs", "bf16,fp32:device"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    runs = out["cpu_runs"]
    assert [(r["precision"], r["data"]) for r in runs] == [("bf16", "loader"), ("fp32", "device")]
    assert out["cpu"] == runs[0] and out["cuda"] is None and "--device cpu" in out["cuda_note"]
    assert all(r["samples_per_s"] > 0 and 0 <= r["data_wait_share"] < 1 for r in runs)
    assert main([*args, "--runs", "fp16"]) == 2
    assert "PRECISION[:DATA]" in capsys.readouterr().err
    if not torch.cuda.is_available():
        assert main([*args, "--device", "cuda"]) == 2
        assert "CUDA is not available" in capsys.readouterr().err
