"""What ``equidiff bench policy`` and ``equidiff bench train`` print: the timings of ``benches.timing`` (inference
modes, training steps) and ``benches.cost`` assembled into one JSON line each (their help texts list the keys).
Each takes its settings and returns its JSON line as a dict, or raises ``BenchError``."""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from equidiff_core.benches import BenchError
from equidiff_core.benches.cost import encoder_flops, policy_cost
from equidiff_core.benches.timing import (
    InferenceMode,
    SyntheticTrainingSet,
    best_mode,
    device_name,
    fresh_policy,
    gemm_gflop_s,
    measure_training,
    measure_training_variants,
    parse_training_runs,
    synchronizer,
    time_encoder_kernels,
    time_inference_mode,
    time_inference_modes,
    time_relu_orders,
    timed_ms,
)
from equidiff_core.config import ConfigError, Workspace
from equidiff_core.data.dataset import DemoDataset, load_episodes
from equidiff_core.data.episode_arrays import DatasetConfig
from equidiff_core.models.equivariance import random_observation
from equidiff_core.models.sampling import make_inference_scheduler
from equidiff_core.policy.diffusion import count_parameters
from equidiff_core.policy.file import CheckpointError, build_plain_network, check_device, export_policy
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.policy.presets import get_preset


@dataclass(frozen=True)
class PolicyBenchSettings:
    """``equidiff bench policy``'s settings: its flags, same names (the command's help says more)."""

    preset: str  # the random-weight policy's preset (ignored with ``checkpoint``)
    policy: str  # equidiff or baseline (ignored with ``checkpoint``)
    checkpoint: str | None  # time this exported policy.pt instead of random weights
    device: str  # auto, cpu or cuda
    precision: str  # the one mode's precision (without ``modes``)
    execution: str  # the one mode's execution: traced, eager (--no-jit) or compiled (--compile)
    graph: bool  # the one mode as one captured CUDA graph
    modes: str | None  # comma-separated InferenceMode names, timed in one run (None: the one mode above)
    rtc: bool  # also time RTC-guided sampling
    compare_relu_order: bool  # also time the same file with the old encoder order
    compare_encoder: bool  # also time the same file with the fp32 CPU encoder's old kernels, alternately
    iters: int  # timed DDIM-16 runs of the exported policy
    eager_iters: int  # timed runs of the eager escnn model (0: none)
    threads: int  # torch intra-op threads (0: as chosen at start)
    doubt_samples: tuple[int, ...] = ()  # also time K samples per observation (the spread's cost), each K


def run_policy_bench(settings: PolicyBenchSettings) -> dict:
    """The timings: the bench's JSON line. BenchError: exit status 2 for settings or a checkpoint it cannot
    time, 1 when no mode ran."""
    if settings.threads:
        torch.set_num_threads(settings.threads)
    device = torch.device(
        "cuda"
        if settings.device == "auto" and torch.cuda.is_available()
        else ("cpu" if settings.device == "auto" else settings.device)
    )
    try:
        check_device(str(device))
        modes = (
            [InferenceMode.parse(m) for m in settings.modes.split(",")]
            if settings.modes
            else [InferenceMode(settings.precision, settings.execution, settings.graph)]
        )
    except ValueError as err:
        raise BenchError(str(err), 2) from err
    if any(k < 2 for k in settings.doubt_samples):
        raise BenchError(f"--doubt-samples must each be >= 2, got {list(settings.doubt_samples)}", 2)
    if any(m.graph for m in modes) and device.type != "cuda" and not settings.modes:
        raise BenchError("--graph needs --device cuda", 2)

    with tempfile.TemporaryDirectory(prefix="bench_policy_") as tmp:
        if settings.checkpoint:
            try:  # validates the file and its config before anything is timed
                plain = load_inference_policy(settings.checkpoint)
            except CheckpointError as err:
                raise BenchError(str(err), 2) from err
            path, policy_name, eager = Path(settings.checkpoint), plain.name, None
        else:
            policy_name = settings.policy
            eager = fresh_policy(policy_name, get_preset(settings.preset), Workspace()).eval().to(device)
            path = export_policy(eager, Path(tmp) / "policy.pt")
        if settings.modes:
            per_mode = time_inference_modes(path, device, modes, settings.iters, settings.rtc, settings.doubt_samples)
        else:  # one mode: its errors are the command's
            per_mode = {
                modes[0].name: time_inference_mode(
                    path, device, modes[0], settings.iters, settings.rtc, settings.doubt_samples
                )[0]
            }
        first = next((name for name, r in per_mode.items() if "ddim16_median_ms" in r), None)
        if first is None:
            raise BenchError(f"no mode ran: {json.dumps(per_mode)}")
        # the same file with the old encoder order, timed alike in this run
        relu_orders = (
            time_relu_orders(path, device, InferenceMode.parse(first), settings.iters)
            if settings.compare_relu_order
            else {}
        )
        kernels = (
            time_encoder_kernels(path, device, InferenceMode.parse(first), settings.iters)
            if settings.compare_encoder
            else None
        )
    # escnn's trainable count; an exported file only holds the expanded (larger) plain weights
    params = count_parameters(eager.model if eager is not None else plain.net)
    preset = (eager if eager is not None else plain).preset
    # the sampler every predict() above ran: the preset's DDIM-16, or a policy file's own (a distilled one's)
    scheduler = plain.scheduler if eager is None else make_inference_scheduler(preset)
    # the encoder's FLOP rate against the same device's fp32 GEMM, measured now with the same threads
    encoder_gflop = encoder_flops(build_plain_network(policy_name, preset), preset) / 1e9
    gemm = gemm_gflop_s(device)

    def rates(figures: dict) -> dict:
        out = {}
        for clock, gemm_key in (("", "gemm_gflop_s"), ("_cpu", "gemm_cpu_gflop_s")):
            if f"encoder{clock}_ms" in figures and gemm_key in gemm:
                rate = encoder_gflop / (figures[f"encoder{clock}_ms"] / 1000)
                out[f"encoder{clock}_gflop_s"] = round(rate, 1)
                out[f"encoder_gemm{clock}_ratio"] = round(rate / gemm[gemm_key], 3)
        return out

    result = {
        "preset": preset.name,
        "policy": policy_name,
        "params": params,
        "params_kind": "trainable" if eager is not None else "exported",
        "inference_steps": len(scheduler.timesteps),
        "timesteps": [int(t) for t in scheduler.timesteps],
        **per_mode[first],
        "eager_ddim16_median_ms": None,
        "device": device_name(device),
        "mode": first,
        "iters": settings.iters,
        "torch": torch.__version__,
        "encoder_gflop": round(encoder_gflop, 3),
        **rates(per_mode[first]),
        **gemm,
        "load_avg_1min": round(os.getloadavg()[0], 2),  # a shared machine's load shows in CPU figures
        **relu_orders,
    }
    if kernels is not None:
        for figures in kernels.values():
            figures.update(rates(figures))
        result["encoder_kernels"] = kernels
        result["encoder_speedup_vs_native"] = round(
            kernels["native"]["encoder_ms"] / kernels["onednn"]["encoder_ms"], 2
        )
    if settings.modes:
        result["modes"] = per_mode
        result["best_mode"] = best_mode(per_mode)
        result["best_ddim16_p99_ms"] = per_mode[result["best_mode"]]["ddim16_p99_ms"]
    if eager is not None and settings.eager_iters > 0:
        vox, ee = random_observation(eager, batch=1, seed=0, fill=0.05)
        obs = {"voxels": vox.to(device), "ee": ee.to(device)}
        sync = synchronizer(device)
        eager.predict_action(obs)  # warm-up (escnn filter expansion, allocator)
        times = timed_ms(lambda: eager.predict_action(obs), settings.eager_iters, sync)
        result["eager_ddim16_median_ms"] = round(float(np.median(times)), 2)
        result["speedup_vs_eager"] = round(result["eager_ddim16_median_ms"] / result["ddim16_median_ms"], 2)
    return result


@dataclass(frozen=True)
class TrainBenchSettings:
    """``equidiff bench train``'s settings: its flags, same names (the command's help says more)."""

    preset: str
    policy: str  # equidiff or baseline
    device: str  # auto (the CPU, then CUDA when there is one), cpu or cuda
    batch_size: int  # the CPU's batch size
    cuda_batch_size: int
    steps: int  # timed optimiser steps per device
    warmup: int  # untimed steps first
    samples: int  # synthetic training samples, held in memory
    cpu_precision: str  # the CPU's precision (without ``runs``)
    runs: str | None  # PRECISION[:DATA],... measured on each device (None: one run each)
    threads: int  # torch intra-op threads (0: as chosen at start)
    rotation_aug: str | None  # None: the preset's
    noise_repeats: int  # (noise, step) draws per encoder pass
    variants: tuple[str, ...] | None  # CPU variants timed instead of the CPU's plain measurement
    rounds: int  # alternating rounds of the variants
    cpu: bool  # measure the CPU (``--no-cpu``: False, CUDA only)
    observations: str = "twin"  # the synthetic set's voxels (``timing.SyntheticTrainingSet``): twin | noise
    demos: tuple[str, ...] = ()  # recorded episodes (bags or folders) to train on instead of the synthetic set


def recorded_training_set(paths, preset, workspace, batch_size: int) -> DemoDataset:
    """The training samples of the recorded episodes at ``paths`` (bags or folders of them): what a lab's own
    frames cost a step, arm and clutter included. Only the grids' resolution is checked against the preset's; a
    bag that does not decode stops the bench (BenchError, exit status 2) rather than shrinking the set."""
    config = DatasetConfig.from_preset(preset, resolution=workspace.resolution)
    episodes, skipped = load_episodes(paths, config)
    if skipped or not episodes:
        reasons = "; ".join(reason for _, reason in skipped[:3]) or f"no episodes in {', '.join(map(str, paths))}"
        raise BenchError(f"--demos: {reasons}", 2)
    data = DemoDataset(episodes, config)
    if len(data) < batch_size:
        raise BenchError(f"--demos: {len(data)} training samples, fewer than a batch of {batch_size}", 2)
    return data


def run_train_bench(settings: TrainBenchSettings) -> dict:
    """The training throughput: the bench's JSON line. BenchError: exit status 2 for a preset, run list or
    device it cannot measure, 1 for step counts out of range."""
    if settings.steps < 1 or settings.warmup < 1 or settings.noise_repeats < 1:
        raise BenchError("--steps, --warmup and --noise-repeats must be >= 1")
    try:
        runs = parse_training_runs(settings.runs) if settings.runs else None
        preset = get_preset(
            settings.preset, **({"rotation_aug": settings.rotation_aug} if settings.rotation_aug else {})
        )
    except (ValueError, ConfigError) as err:
        raise BenchError(str(err), 2) from err
    cuda = torch.cuda.is_available()
    if settings.device == "cuda" and not cuda:
        raise BenchError("--device cuda but CUDA is not available", 2)
    if settings.threads:
        torch.set_num_threads(settings.threads)
    devices = {
        "cpu": settings.device in ("auto", "cpu") and settings.cpu,
        "cuda": cuda and settings.device in ("auto", "cuda"),
    }
    batch_sizes = {"cpu": settings.batch_size, "cuda": settings.cuda_batch_size}
    default_runs = {"cpu": [(settings.cpu_precision, "auto")], "cuda": [("auto", "auto")]}
    ws = Workspace()
    batches = [batch_sizes[d] for d, on in devices.items() if on] + ([settings.batch_size] if settings.variants else [])
    if settings.demos:
        data = recorded_training_set(settings.demos, preset, ws, max(batches))
    else:
        try:
            data = SyntheticTrainingSet(
                preset, ws, max([settings.samples, *batches]), observations=settings.observations
            )
        except ValueError as err:
            raise BenchError(str(err), 2) from err
    cost = policy_cost(fresh_policy(settings.policy, preset, ws), batch=2, noise_repeats=settings.noise_repeats)
    policy = fresh_policy(settings.policy, preset, ws)  # trained by every run in turn: the timing does not care
    result = {
        "bench": "train",
        "preset": preset.name,
        "policy": settings.policy,
        "params": cost["params"],
        "cost": cost,
        "rotation_aug": preset.rotation_aug,
        "samples": len(data),
        "noise_repeats": settings.noise_repeats,
        "observations": "demos" if settings.demos else settings.observations,
        **({"demo_episodes": len(data.episodes)} if settings.demos else {}),
        "load_avg_1min": round(os.getloadavg()[0], 2),  # a shared machine's load shows in CPU figures
    }
    if settings.variants:  # instead of the CPU's plain measurement
        result["cpu_variants"] = measure_training_variants(
            settings.policy,
            preset,
            ws,
            data,
            list(settings.variants),
            settings.batch_size,
            settings.steps,
            settings.warmup,
            settings.rounds,
            settings.noise_repeats,
        )
        devices["cpu"] = False
    for device, on in devices.items():
        if not on:
            continue
        measured = []
        for precision, source in runs or default_runs[device]:
            try:
                measured.append(
                    measure_training(
                        policy,
                        data,
                        device,
                        batch_sizes[device],
                        settings.steps,
                        settings.warmup,
                        precision,
                        source,
                        settings.noise_repeats,
                    )
                )
            except (RuntimeError, MemoryError) as err:  # e.g. CUDA out of memory in fp32: the other runs still count
                if not runs:
                    raise
                measured.append({"precision": precision, "data": source, "error": f"{type(err).__name__}: {err}"[:300]})
                if device == "cuda":
                    torch.cuda.empty_cache()
        result[device] = measured[0]
        if runs:
            result[f"{device}_runs"] = measured
    if not devices["cuda"]:
        result["cuda"] = None
        result["cuda_note"] = (
            "not asked for (--device cpu)" if settings.device == "cpu" else "CUDA not available: not measured"
        )
    if "samples_per_s" in (result.get("cpu") or {}) and "samples_per_s" in (result["cuda"] or {}):
        result["cuda_vs_cpu"] = round(result["cuda"]["samples_per_s"] / result["cpu"]["samples_per_s"], 1)
    return result
