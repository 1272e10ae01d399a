"""`equidiff bench policy`: time the exported policy against eager escnn, same weights, same run.

Prints one JSON line with ``preset``, ``params``, ``encoder_ms``, ``step_ms`` (one denoising
step), ``ddim16_median_ms`` and ``ddim16_p99_ms`` (full predict(): encoder + DDIM-16 + decode)
for the exported plain-torch policy with the chosen switches, ``eager_ddim16_median_ms`` for the
training-time model (escnn for EquiDiff) in fp32 eager mode, and ``device``. Random weights by
default (timing does not depend on them); ``--checkpoint policy.pt`` times a trained file.
Targets on a 2-core CPU: compact <= 100 ms p99, paper <= 400 ms median.

``--modes bf16-traced,bf16-traced-graph,fp32-traced`` times several ways of running the same
export in one run (``benches.timing.InferenceMode``): the top-level figures are the first measured
mode's, ``modes`` holds each one's (or its error), ``best_mode`` / ``best_ddim16_p99_ms`` the
smallest p99. ``--rtc`` adds RTC-guided sampling (``rtc_median_ms``, ``rtc_vs_plain``).
``--compare-relu-order`` adds the same export with the encoder's old order, each ReLU before its
max-pool (``relu_before_pool``; ``relu_order_cpu_ms``: both orders alternately in CPU time).
"""

from __future__ import annotations

import json
import sys


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
        "--graph", action="store_true", help="CUDA only: replay encoder + DDIM-16 as one captured CUDA graph"
    )
    parser.add_argument(
        "--modes",
        default=None,
        help="comma-separated PRECISION-EXECUTION[-graph] modes timed in one run, e.g. "
        "bf16-traced,bf16-traced-graph,fp32-traced (EXECUTION: eager | traced | compiled); overrides the switches above",
    )
    parser.add_argument("--rtc", action="store_true", help="also time RTC-guided sampling against plain DDIM")
    parser.add_argument(
        "--compare-relu-order",
        action="store_true",
        help="also time the same weights with each ReLU before its max-pool (the encoder order before), in the "
        "first measured mode (adds relu_before_pool: encoder_ms, ddim16_median_ms; relu_order_cpu_ms)",
    )
    parser.add_argument("--iters", type=int, default=30, help="timed DDIM-16 runs of the exported policy")
    parser.add_argument("--eager-iters", type=int, default=3, help="timed runs of the eager escnn model")
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch intra-op threads (default 1: on a shared 2-core machine more threads oversubscribe; 0: torch default)",
    )


def run(args) -> int:
    import tempfile
    from pathlib import Path

    import numpy as np
    import torch

    from equidiff_core.benches.timing import (
        InferenceMode,
        best_mode,
        device_name,
        fresh_policy,
        synchronizer,
        time_inference_mode,
        time_inference_modes,
        time_relu_orders,
        timed_ms,
    )
    from equidiff_core.config import Workspace
    from equidiff_core.inference import CheckpointError, check_device, export_policy, load_inference_policy
    from equidiff_core.models.equivariance import random_observation
    from equidiff_core.policies import count_parameters
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
