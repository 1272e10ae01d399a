"""`equidiff bench train`: training throughput (samples/s) on the CPU and on CUDA, same run.

Each device runs the real ``training.train`` loop with its defaults there (CPU: fp32, DataLoader;
CUDA: bf16 autocast, the whole set resident on the GPU) on synthetic observations (random
coloured voxels, gripper states near the workspace centre: the cost does not depend on their
content), with the preset's rotation augmentation, and times ``--steps`` optimiser steps after
``--warmup`` untimed ones (``benches.timing.measure_training``). Prints one JSON line: ``preset``,
``policy``, ``params``, ``cost`` (parameters and FLOPs per sample: encoder, denoising step, DDIM-16,
training step; ``benches.cost``), then per device (``cpu``, ``cuda``) ``device`` (the CPU's name and
instruction sets or the GPU's name), ``batch_size``, ``precision``, ``data``, ``steps``,
``sec_per_step``, ``samples_per_s`` and ``data_wait_share`` (the loop's wait for its next batch
over the step time; on the CPU also ``cpu_sec_per_step``, the process's CPU seconds; on CUDA
``gpu_busy_pct`` from NVML and ``peak_memory_gb``); ``"cuda": null`` with ``cuda_note`` when there
is no GPU. ``--runs bf16,fp32,bf16:loader`` measures several precision / data-source settings per
device: ``cpu_runs`` / ``cuda_runs`` list them all, ``cpu`` / ``cuda`` is the first.
``--variants A B ...`` (CPU) times training-step variants in alternating rounds of one run instead of
``cpu``: ``cpu_variants`` with each one's ``sec_per_step`` and ``vs_first``, the first variant being
the reference (``benches.timing.CPU_VARIANTS``).
"""

from __future__ import annotations

import json
import os
import sys

from equidiff_core.benches.timing import CPU_VARIANTS


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
    parser.add_argument(
        "--rotation-aug",
        default=None,
        help="none | c4 | c8 | continuous (default: the preset's; the benches train with none)",
    )
    parser.add_argument("--noise-repeats", type=int, default=1, help="(noise, step) draws per encoder pass")
    parser.add_argument(
        "--variants",
        nargs="+",
        choices=tuple(CPU_VARIANTS),
        default=None,
        metavar="NAME",
        help="CPU only: time these training-step variants in the same run, in alternating rounds, the first "
        f"as the reference ({', '.join(CPU_VARIANTS)})",
    )
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds of --variants")
    parser.add_argument("--no-cpu", action="store_true", help="measure CUDA only (as --device cuda)")


def run(args) -> int:
    import torch

    from equidiff_core.benches.cost import policy_cost
    from equidiff_core.benches.timing import (
        SyntheticTrainingSet,
        fresh_policy,
        measure_training,
        measure_training_variants,
        parse_training_runs,
    )
    from equidiff_core.config import ConfigError, Workspace
    from equidiff_core.presets import get_preset

    if args.steps < 1 or args.warmup < 1 or args.noise_repeats < 1:
        raise SystemExit("equidiff bench train: --steps, --warmup and --noise-repeats must be >= 1")
    try:
        runs = parse_training_runs(args.runs) if args.runs else None
        preset = get_preset(args.preset, **({"rotation_aug": args.rotation_aug} if args.rotation_aug else {}))
    except (ValueError, ConfigError) as err:
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
    ws = Workspace()
    batches = [batch_sizes[d] for d, on in devices.items() if on] + ([args.batch_size] if args.variants else [])
    data = SyntheticTrainingSet(preset, ws, max([args.samples, *batches]))
    cost = policy_cost(fresh_policy(args.policy, preset, ws), batch=2, noise_repeats=args.noise_repeats)
    policy = fresh_policy(args.policy, preset, ws)  # trained by every run in turn: the timing does not care
    result = {
        "bench": "train",
        "preset": preset.name,
        "policy": args.policy,
        "params": cost["params"],
        "cost": cost,
        "rotation_aug": preset.rotation_aug,
        "samples": len(data),
        "noise_repeats": args.noise_repeats,
        "load_avg_1min": round(os.getloadavg()[0], 2),  # a shared machine's load shows in CPU figures
    }
    if args.variants:  # instead of the CPU's plain measurement
        result["cpu_variants"] = measure_training_variants(
            args.policy,
            preset,
            ws,
            data,
            args.variants,
            args.batch_size,
            args.steps,
            args.warmup,
            args.rounds,
            args.noise_repeats,
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
                        args.steps,
                        args.warmup,
                        precision,
                        source,
                        args.noise_repeats,
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
