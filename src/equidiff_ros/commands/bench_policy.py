"""`equidiff bench policy`: time the exported policy against eager escnn, same weights, same run.

Prints one JSON line with ``preset``, ``params``, ``encoder_ms``, ``step_ms`` (one denoising
step), ``ddim16_median_ms`` and ``ddim16_p99_ms`` (full predict(): encoder + DDIM-16 + decode)
for the exported plain-torch policy with the chosen switches, ``eager_ddim16_median_ms`` for the
training-time model (escnn for EquiDiff) in fp32 eager mode, and ``device``. Random weights by
default (timing does not depend on them); ``--checkpoint policy.pt`` times a trained file.
Targets on a 2-core CPU: compact <= 100 ms p99, paper <= 400 ms median.
"""

from __future__ import annotations

import json
import sys
import time


def add_arguments(parser) -> None:
    parser.add_argument("--preset", default="compact", help="paper | compact | tiny")
    parser.add_argument("--policy", default="equidiff", choices=["equidiff", "baseline"])
    parser.add_argument("--checkpoint", default=None, help="time this exported policy.pt instead of random weights")
    parser.add_argument("--device", default="auto", help="auto | cpu | cuda")
    parser.add_argument(
        "--precision",
        default="auto",
        choices=["auto", "fp32", "bf16"],
        help="auto: bf16 on CUDA and on CPUs with native bf16, else fp32",
    )
    parser.add_argument("--no-jit", action="store_true", help="skip torch.jit.trace of encoder and denoiser")
    parser.add_argument(
        "--compile",
        action="store_true",
        help="torch.compile the denoising step (~45 s the first time, then cached on disk)",
    )
    parser.add_argument(
        "--compare-relu-order",
        action="store_true",
        help="also time the same weights with each ReLU before its max-pool (the encoder order before; "
        "adds relu_before_pool: encoder_ms, ddim16_median_ms)",
    )
    parser.add_argument("--iters", type=int, default=30, help="timed DDIM-16 runs of the exported policy")
    parser.add_argument("--eager-iters", type=int, default=3, help="timed runs of the eager escnn model")
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch intra-op threads (default 1: on a shared 2-core machine more threads oversubscribe; 0: torch default)",
    )


def _device_name(device) -> str:
    import torch

    if device.type == "cuda":
        return f"cuda: {torch.cuda.get_device_name(device)}"
    from equidiff_core.machine import cpu_model

    return f"cpu: {cpu_model()}, {torch.get_num_threads()} threads"


def _timed(fn, iters, sync):
    times = []
    for _ in range(iters):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append((time.perf_counter() - t0) * 1000)
    return times


def run(args) -> int:
    import tempfile
    from pathlib import Path

    import numpy as np
    import torch

    from equidiff_core.config import Workspace
    from equidiff_core.inference import (
        CheckpointError,
        check_device,
        export_policy,
        load_inference_policy,
    )
    from equidiff_core.models.equivariance import random_observation
    from equidiff_core.normalizer import Normalizer
    from equidiff_core.policies import count_parameters, make_policy
    from equidiff_core.presets import get_preset

    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(
        "cuda"
        if args.device == "auto" and torch.cuda.is_available()
        else ("cpu" if args.device == "auto" else args.device)
    )
    try:
        check_device(str(device))
    except ValueError as err:
        print(f"equidiff bench policy: {err}", file=sys.stderr)
        return 2
    precision = args.precision
    if precision == "auto":
        from equidiff_core.machine import cpu_has_native_bf16

        precision = "bf16" if device.type == "cuda" or cpu_has_native_bf16() else "fp32"
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)

    ws = Workspace()
    torch.manual_seed(0)
    load = lambda path: load_inference_policy(
        path, device=str(device), precision=precision, jit=not args.no_jit, compile=args.compile
    )
    if args.checkpoint:
        try:  # one read: load_inference_policy validates the file and its config (CheckpointError)
            fast = load(args.checkpoint)
        except CheckpointError as err:
            print(f"equidiff bench policy: {err}", file=sys.stderr)
            return 2
        policy_name, eager = fast.name, None
    else:
        policy_name = args.policy
        eager = make_policy(policy_name, get_preset(args.preset), ws)
        eager.set_normalizer(Normalizer.from_workspace(ws))
        eager.eval().to(device)
        with tempfile.TemporaryDirectory(prefix="bench_policy_") as tmp:
            fast = load(export_policy(eager, Path(tmp) / "policy.pt"))
    params = count_parameters(eager.model) if eager is not None else count_parameters(fast.net)

    vox_t, ee_t = random_observation(_Probe(fast.preset, fast.workspace), batch=1, seed=0, fill=0.05)
    vox, ee = vox_t[0, 0].numpy(), ee_t[0, 0].numpy()
    fast.warmup(3)
    enc = _timed(lambda: fast.encode(vox, ee), max(5, args.iters // 3), sync)
    cond = fast.encode(vox, ee)
    x = torch.zeros(1, fast.preset.horizon, fast.codec.dim, device=device)
    t = torch.tensor([50], device=device)
    step = _timed(lambda: fast.denoise(x, t, cond), max(10, args.iters), sync)
    ddim = _timed(lambda: fast.predict(vox, ee, seed=0), args.iters, sync)

    result = {
        "preset": fast.preset.name,
        "policy": policy_name,
        "params": params,
        # escnn's trainable count; an exported file only holds the expanded (larger) plain weights
        "params_kind": "trainable" if eager is not None else "exported",
        "encoder_ms": round(float(np.median(enc)), 2),
        "step_ms": round(float(np.median(step)), 2),
        "ddim16_median_ms": round(float(np.median(ddim)), 2),
        "ddim16_p99_ms": round(float(np.percentile(ddim, 99)), 2),
        "eager_ddim16_median_ms": None,
        "device": _device_name(device),
        "precision": precision,
        "jit": not args.no_jit,
        "compiled": fast.compiled,
        "iters": args.iters,
    }
    if args.compare_relu_order:  # the same file with the old encoder order, timed alike in this run
        from equidiff_core.models.plain import relu_before_pool_order

        with tempfile.TemporaryDirectory(prefix="bench_policy_") as tmp:
            path = args.checkpoint or export_policy(eager, Path(tmp) / "policy.pt")
            with relu_before_pool_order():
                old = load(path)
        old.warmup(3)
        old_enc = _timed(lambda: old.encode(vox, ee), max(5, args.iters // 3), sync)
        old_ddim = _timed(lambda: old.predict(vox, ee, seed=0), args.iters, sync)
        # and both orders alternately in this process's CPU time, which a loaded machine's waiting leaves out
        cpu = {"pool_before_relu": ([], []), "relu_before_pool": ([], [])}
        for _ in range(args.iters):
            for label, policy in (("pool_before_relu", fast), ("relu_before_pool", old)):
                encoder_times, ddim_times = cpu[label]
                t0 = time.process_time()
                policy.encode(vox, ee)
                sync()
                t1 = time.process_time()
                policy.predict(vox, ee, seed=0)
                sync()
                encoder_times.append((t1 - t0) * 1000)
                ddim_times.append((time.process_time() - t1) * 1000)
        result["relu_before_pool"] = {
            "encoder_ms": round(float(np.median(old_enc)), 2),
            "ddim16_median_ms": round(float(np.median(old_ddim)), 2),
        }
        result["relu_order_cpu_ms"] = {
            label: {"encoder": round(float(np.median(e)), 2), "ddim16": round(float(np.median(d)), 2)}
            for label, (e, d) in cpu.items()
        }
    if eager is not None and args.eager_iters > 0:
        obs = {"voxels": vox_t.to(device), "ee": ee_t.to(device)}
        eager.predict_action(obs)  # warm-up (escnn filter expansion, allocator)
        times = _timed(lambda: eager.predict_action(obs), args.eager_iters, sync)
        result["eager_ddim16_median_ms"] = round(float(np.median(times)), 2)
        result["speedup_vs_eager"] = round(result["eager_ddim16_median_ms"] / result["ddim16_median_ms"], 2)
    print(json.dumps(result), flush=True)
    return 0


class _Probe:
    """Just enough of a policy for equivariance.random_observation."""

    def __init__(self, preset, workspace):
        self.preset, self.workspace = preset, workspace
