"""`equidiff bench train`: training throughput (samples/s) on the CPU and on CUDA, same run.

Each device runs the real ``training.train`` loop with its defaults there (CPU: fp32, DataLoader;
CUDA: bf16 autocast, the whole set resident on the GPU) on synthetic observations (random
coloured voxels, gripper states near the workspace centre: the cost does not depend on their
content), with the preset's rotation augmentation, and times ``--steps`` optimiser steps after
``--warmup`` untimed ones (``benchmarks.measure_training``). Prints one JSON line: ``preset``,
``policy``, ``params``, then per device (``cpu``, ``cuda``) ``device`` (the CPU's name and
instruction sets or the GPU's name), ``batch_size``, ``precision``, ``data``, ``steps``,
``sec_per_step``, ``samples_per_s`` and ``data_wait_share`` (the loop's wait for its next batch
over the step time; on CUDA also ``gpu_busy_pct`` from NVML and ``peak_memory_gb``);
``"cuda": null`` with ``cuda_note`` when there is no GPU. ``--runs bf16,fp32,bf16:loader``
measures several precision / data-source settings per device: ``cpu_runs`` / ``cuda_runs`` list
them all, ``cpu`` / ``cuda`` is the first.
"""

from __future__ import annotations

import json
import os
import sys


def add_arguments(parser) -> None:
    parser.add_argument("--preset", default="compact", help="paper | compact | tiny")
    parser.add_argument("--policy", default="equidiff", choices=["equidiff", "baseline"])
    parser.add_argument(
        "--device", default="auto", choices=["auto", "cpu", "cuda"], help="auto: the CPU, then CUDA when there is one"
    )
    parser.add_argument("--batch-size", type=int, default=8, help="CPU batch size")
    parser.add_argument("--cuda-batch-size", type=int, default=64, help="CUDA batch size")
    parser.add_argument("--steps", type=int, default=4, help="timed optimiser steps per device")
    parser.add_argument("--warmup", type=int, default=2, help="untimed steps first (allocator, escnn, cuDNN)")
    parser.add_argument("--samples", type=int, default=64, help="synthetic training samples (held in memory)")
    parser.add_argument(
        "--cpu-precision",
        choices=["fp32", "bf16"],
        default="fp32",
        help="fp32 (training's CPU default) or bf16 autocast (fast only with AVX512-BF16/AMX)",
    )
    parser.add_argument(
        "--runs",
        default=None,
        help="comma-separated PRECISION[:DATA] settings measured on each device, e.g. bf16,fp32,bf16:loader "
        "(PRECISION auto | fp32 | bf16, DATA auto | device | loader); default: --cpu-precision on the CPU, auto on CUDA",
    )
    parser.add_argument("--threads", type=int, default=0, help="torch intra-op threads on the CPU (0: torch default)")
    parser.add_argument("--no-cpu", action="store_true", help="measure CUDA only (as --device cuda)")


def run(args) -> int:
    import torch

    from equidiff_core.benchmarks import SyntheticTrainingSet, fresh_policy, measure_training, parse_training_runs
    from equidiff_core.config import Workspace
    from equidiff_core.policies import count_parameters
    from equidiff_core.presets import get_preset

    if args.steps < 1 or args.warmup < 1:
        raise SystemExit("equidiff bench train: --steps and --warmup must be >= 1")
    try:
        runs = parse_training_runs(args.runs) if args.runs else None
    except ValueError as err:
        print(f"equidiff bench train: {err}", file=sys.stderr)
        return 2
    cuda = torch.cuda.is_available()
    if args.device == "cuda" and not cuda:
        print("equidiff bench train: --device cuda but CUDA is not available", file=sys.stderr)
        return 2
    if args.threads:
        torch.set_num_threads(args.threads)
    devices = {
        "cpu": args.device in ("auto", "cpu") and not args.no_cpu,
        "cuda": cuda and args.device in ("auto", "cuda"),
    }
    batch_sizes = {"cpu": args.batch_size, "cuda": args.cuda_batch_size}
    default_runs = {"cpu": [(args.cpu_precision, "auto")], "cuda": [("auto", "auto")]}
    preset, ws = get_preset(args.preset), Workspace()
    data = SyntheticTrainingSet(preset, ws, max(args.samples, *(batch_sizes[d] for d, on in devices.items() if on)))
    policy = fresh_policy(args.policy, preset, ws)  # trained by every run in turn: the timing does not care
    result = {
        "bench": "train",
        "preset": preset.name,
        "policy": args.policy,
        "params": count_parameters(policy.model),
        "rotation_aug": preset.rotation_aug,
        "samples": len(data),
        "load_avg_1min": round(os.getloadavg()[0], 2),  # a shared machine's load shows in CPU figures
    }
    for device, on in devices.items():
        if not on:
            continue
        measured = []
        for precision, source in runs or default_runs[device]:
            try:
                measured.append(
                    measure_training(
                        policy, data, device, batch_sizes[device], args.steps, args.warmup, precision, source
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
            "not asked for (--device cpu)" if args.device == "cpu" else "CUDA not available: not measured"
        )
    if "samples_per_s" in (result.get("cpu") or {}) and "samples_per_s" in (result["cuda"] or {}):
        result["cuda_vs_cpu"] = round(result["cuda"]["samples_per_s"] / result["cpu"]["samples_per_s"], 1)
    print(json.dumps(result), flush=True)
    return 0
