"""What ``equidiff bench policy`` and ``equidiff bench train`` print: the timings of ``benches.timing`` (inference
modes, training steps) and ``benches.cost`` assembled into one JSON line each (their help texts list the keys)."""

from __future__ import annotations

import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from equidiff_core.benches.cost import policy_cost
from equidiff_core.benches.timing import (
    InferenceMode,
    SyntheticTrainingSet,
    best_mode,
    device_name,
    fresh_policy,
    measure_training,
    measure_training_variants,
    parse_training_runs,
    synchronizer,
    time_inference_mode,
    time_inference_modes,
    time_relu_orders,
    timed_ms,
)
from equidiff_core.config import ConfigError, Workspace
from equidiff_core.inference import CheckpointError, check_device, export_policy, load_inference_policy
from equidiff_core.models.equivariance import random_observation
from equidiff_core.policies import count_parameters
from equidiff_core.presets import get_preset


def run_policy_bench(args) -> int:
    """``equidiff bench policy`` for its parsed arguments: one JSON line; the exit status."""
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(
        "cuda"
        if args.device == "auto" and torch.cuda.is_available()
        else ("cpu" if args.device == "auto" else args.device)
    )
    try:
        check_device(str(device))
        modes = (
            [InferenceMode.parse(m) for m in args.modes.split(",")]
            if args.modes
            else [InferenceMode(args.precision, _execution(args), args.graph)]
        )
    except ValueError as err:
        print(f"equidiff bench policy: {err}", file=sys.stderr)
        return 2
    if any(m.graph for m in modes) and device.type != "cuda" and not args.modes:
        print("equidiff bench policy: --graph needs --device cuda", file=sys.stderr)
        return 2

    with tempfile.TemporaryDirectory(prefix="bench_policy_") as tmp:
        if args.checkpoint:
            try:  # validates the file and its config before anything is timed
                plain = load_inference_policy(args.checkpoint)
            except CheckpointError as err:
                print(f"equidiff bench policy: {err}", file=sys.stderr)
                return 2
            path, policy_name, eager = Path(args.checkpoint), plain.name, None
        else:
            policy_name = args.policy
            eager = fresh_policy(policy_name, get_preset(args.preset), Workspace()).eval().to(device)
            path = export_policy(eager, Path(tmp) / "policy.pt")
        if args.modes:
            per_mode = time_inference_modes(path, device, modes, args.iters, args.rtc)
        else:  # one mode: its errors are the command's
            per_mode = {modes[0].name: time_inference_mode(path, device, modes[0], args.iters, args.rtc)[0]}
        first = next((name for name, r in per_mode.items() if "ddim16_median_ms" in r), None)
        if first is None:
            print(f"equidiff bench policy: no mode ran: {json.dumps(per_mode)}", file=sys.stderr)
            return 1
        # the same file with the old encoder order, timed alike in this run
        relu_orders = (
            time_relu_orders(path, device, InferenceMode.parse(first), args.iters) if args.compare_relu_order else {}
        )
    # escnn's trainable count; an exported file only holds the expanded (larger) plain weights
    params = count_parameters(eager.model if eager is not None else plain.net)
    result = {
        "preset": (eager if eager is not None else plain).preset.name,
        "policy": policy_name,
        "params": params,
        "params_kind": "trainable" if eager is not None else "exported",
        **per_mode[first],
        "eager_ddim16_median_ms": None,
        "device": device_name(device),
        "mode": first,
        "iters": args.iters,
        "torch": torch.__version__,
        **relu_orders,
    }
    if args.modes:
        result["modes"] = per_mode
        result["best_mode"] = best_mode(per_mode)
        result["best_ddim16_p99_ms"] = per_mode[result["best_mode"]]["ddim16_p99_ms"]
    if eager is not None and args.eager_iters > 0:
        vox, ee = random_observation(eager, batch=1, seed=0, fill=0.05)
        obs = {"voxels": vox.to(device), "ee": ee.to(device)}
        sync = synchronizer(device)
        eager.predict_action(obs)  # warm-up (escnn filter expansion, allocator)
        times = timed_ms(lambda: eager.predict_action(obs), args.eager_iters, sync)
        result["eager_ddim16_median_ms"] = round(float(np.median(times)), 2)
        result["speedup_vs_eager"] = round(result["eager_ddim16_median_ms"] / result["ddim16_median_ms"], 2)
    print(json.dumps(result), flush=True)
    return 0


def _execution(args) -> str:
    if args.compile:
        return "compiled"
    return "eager" if args.no_jit else "traced"


def run_train_bench(args) -> int:
    """``equidiff bench train`` for its parsed arguments: one JSON line; the exit status."""
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
