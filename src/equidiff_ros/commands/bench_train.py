"""`equidiff bench train`: training throughput (samples/s) on the CPU and on CUDA, same run.

Each device runs the real ``training.train`` loop with its defaults there (CPU: fp32, DataLoader;
CUDA: bf16 autocast, the whole set resident on the GPU) on synthetic observations (random
coloured voxels, gripper states near the workspace centre: the cost does not depend on their
content), with the preset's rotation augmentation, and times ``--steps`` optimiser steps after
``--warmup`` untimed ones. Prints one JSON line: ``preset``, ``policy``, ``params``, ``cost`` (parameters
and FLOPs per sample: encoder, denoising step, DDIM-16, training step; ``benches.cost``), then per
device (``cpu``, ``cuda``) ``device`` (the CPU's name and instruction sets or the GPU's name),
``batch_size``, ``precision``, ``data``, ``steps``, ``sec_per_step`` and ``samples_per_s``;
``"cuda": null`` with ``cuda_note`` when there is no GPU. ``--variants A B ...`` (CPU) times training-step
variants in alternating rounds of one run instead: ``cpu_variants`` with each one's ``sec_per_step`` and
``vs_first``, the first variant being the reference (``CPU_VARIANTS``).
"""

from __future__ import annotations

import contextlib
import json
import os
import time


def add_arguments(parser) -> None:
    parser.add_argument("--preset", default="compact", help="paper | compact | tiny")
    parser.add_argument("--policy", default="equidiff", choices=["equidiff", "baseline"])
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
    parser.add_argument("--no-cpu", action="store_true", help="measure CUDA only")


# What a CPU training step can be made of, for --variants: each the training's CPU default but for one thing.
CPU_VARIANTS = {
    "default": "fp32, the encoder's max-pools before their ReLUs (training's CPU default)",
    "relu_before_pool": "each ReLU before the max-pool after it, the order before (the 56^3 ReLU and its backward)",
    "bf16": "bf16 autocast (the CPU's AVX512-BF16 / AMX, if any)",
    "channels_last": "the voxel input in channels_last_3d memory format (the baseline's default already)",
    "contiguous_input": "the voxel input in the contiguous (N, C, D, H, W) format (the baseline's before)",
    "one_noise_draw": "1 (noise, step) draw per encoder pass instead of --noise-repeats",
    "eight_noise_draws": "8 (noise, step) draws per encoder pass instead of --noise-repeats",
}
VARIANT_NOISE_REPEATS = {"one_noise_draw": 1, "eight_noise_draws": 8}


def _apply_variant(policy, variant: str) -> str:
    """Shape ``policy`` as ``variant`` needs (``relu_before_pool`` is built so, see ``measure``); returns the
    training precision for it."""
    import torch

    encoder = policy.model.encoder
    if variant in ("channels_last", "contiguous_input"):
        layout = torch.channels_last_3d if variant == "channels_last" else torch.contiguous_format

        def to_layout(module, inputs):
            x = inputs[0]
            if isinstance(x, torch.Tensor):
                return (x.contiguous(memory_format=layout),)
            return (type(x)(x.tensor.contiguous(memory_format=layout), x.type),)  # escnn

        encoder.register_forward_pre_hook(to_layout)
    return "bf16" if variant == "bf16" else "fp32"


class _SyntheticSet:
    """Random observations with actions around the gripper state (map-style dataset)."""

    def __init__(self, preset, workspace, n: int, seed: int = 0):
        import torch

        from equidiff_core.models.equivariance import random_observation

        from .bench_policy import _Probe

        probe = _Probe(preset, workspace)
        parts = [random_observation(probe, batch=min(8, n - a), seed=seed + a, fill=0.05) for a in range(0, n, 8)]
        self.voxels = torch.cat([v for v, _ in parts])
        self.ee = torch.cat([e for _, e in parts])
        gen = torch.Generator().manual_seed(seed)
        self.action = self.ee[:, -1:].repeat(1, preset.horizon, 1)
        self.action[..., :3] += 0.02 * torch.randn((n, preset.horizon, 3), generator=gen).cumsum(1)

    def __len__(self):
        return len(self.voxels)

    def __getitem__(self, i):
        return {"voxels": self.voxels[i], "ee": self.ee[i], "action": self.action[i]}


class _StepClock:
    def __init__(self, sync):
        self.sync, self.times, self.cpu_times = sync, {}, {}

    def on_step(self, step, metrics):
        self.sync()
        self.times[step] = time.perf_counter()
        # the process's CPU time: on a loaded machine it still measures the work, not the waiting
        self.cpu_times[step] = time.process_time()


def measure(
    preset,
    policy_name: str,
    workspace,
    data,
    device: str,
    batch_size: int,
    steps: int,
    warmup: int,
    precision: str = "auto",
    noise_repeats: int = 1,
    variant: str = "default",
) -> dict:
    import tempfile

    import torch

    from equidiff_core.models.plain import relu_before_pool_order
    from equidiff_core.normalizer import Normalizer
    from equidiff_core.policies import make_policy
    from equidiff_core.training import TrainConfig, train

    from .bench_policy import _device_name

    torch.manual_seed(0)
    with relu_before_pool_order() if variant == "relu_before_pool" else contextlib.nullcontext():
        policy = make_policy(policy_name, preset, workspace)
    policy.set_normalizer(Normalizer.from_workspace(workspace))
    if variant != "default":
        precision = _apply_variant(policy, variant)
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    clock = _StepClock(sync)
    cfg = TrainConfig(
        steps=warmup + steps,
        batch_size=batch_size,
        warmup_steps=1,
        device=device,
        eval_every=0,
        checkpoint_every=0,
        log_every=1,
        precision=precision,
        noise_repeats=noise_repeats,
    )
    with tempfile.TemporaryDirectory(prefix="bench_train_") as tmp:
        result = train(policy, data, None, cfg, tmp, callbacks=[clock])
    seconds = clock.times[warmup + steps] - clock.times[warmup]
    out = {
        "device": _device_name(torch.device(device)),
        "batch_size": batch_size,
        "precision": result.precision,
        "data": result.data,
        "steps": steps,
        "sec_per_step": float(f"{seconds / steps:.4g}"),
        "samples_per_s": float(f"{batch_size * steps / seconds:.4g}"),
    }
    if device == "cpu":
        cpu_seconds = clock.cpu_times[warmup + steps] - clock.cpu_times[warmup]
        out["cpu_sec_per_step"] = float(f"{cpu_seconds / steps:.4g}")
        from equidiff_core.machine import cpu_description

        d = cpu_description()
        out.update(cores=d["cores"], avx512=d["avx512"], native_bf16=d["bf16"])
    return out


def run(args) -> int:
    import torch

    from equidiff_core.config import Workspace
    from equidiff_core.policies import count_parameters, make_policy
    from equidiff_core.presets import get_preset

    if args.steps < 1 or args.warmup < 1:
        raise SystemExit("equidiff bench train: --steps and --warmup must be >= 1")
    if args.threads:
        torch.set_num_threads(args.threads)
    preset, ws = (
        get_preset(args.preset, **({"rotation_aug": args.rotation_aug} if args.rotation_aug else {})),
        Workspace(),
    )
    cuda = torch.cuda.is_available()
    batch_sizes = ([] if args.no_cpu else [args.batch_size]) + ([args.cuda_batch_size] if cuda else [])
    data = _SyntheticSet(preset, ws, max([args.samples, *batch_sizes]))
    result = {
        "bench": "train",
        "preset": preset.name,
        "policy": args.policy,
        "params": count_parameters(make_policy(args.policy, preset, ws).model),
        "cost": _cost(preset, args, ws),
        "rotation_aug": preset.rotation_aug,
        "samples": len(data),
        "noise_repeats": args.noise_repeats,
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }  # a shared machine's load shows in CPU figures
    if args.variants:
        result["cpu_variants"] = measure_variants(preset, args, ws, data)
    elif not args.no_cpu:
        result["cpu"] = measure(
            preset,
            args.policy,
            ws,
            data,
            "cpu",
            args.batch_size,
            args.steps,
            args.warmup,
            args.cpu_precision,
            args.noise_repeats,
        )
    if cuda:
        result["cuda"] = measure(
            preset,
            args.policy,
            ws,
            data,
            "cuda",
            args.cuda_batch_size,
            args.steps,
            args.warmup,
            "auto",
            args.noise_repeats,
        )
    else:
        result["cuda"] = None
        result["cuda_note"] = "CUDA not available: not measured"
    if "cpu" in result and result["cuda"] is not None:
        result["cuda_vs_cpu"] = round(result["cuda"]["samples_per_s"] / result["cpu"]["samples_per_s"], 1)
    print(json.dumps(result), flush=True)
    return 0


def measure_variants(preset, args, workspace, data) -> dict:
    """Each of ``args.variants`` timed on the CPU in ``args.rounds`` alternating rounds (a shared machine's
    load then weighs on all alike): the CPU, and per variant the median round's ``sec_per_step`` and
    ``samples_per_s``, every round's ``sec_per_step`` and ``vs_first`` (the first variant's median over
    this one's: above 1 is faster)."""
    import statistics

    rounds = {name: [] for name in args.variants}
    cpu_rounds = {name: [] for name in args.variants}
    m = {}
    for _ in range(max(1, args.rounds)):
        for name in args.variants:
            m = measure(
                preset,
                args.policy,
                workspace,
                data,
                "cpu",
                args.batch_size,
                args.steps,
                args.warmup,
                noise_repeats=VARIANT_NOISE_REPEATS.get(name, args.noise_repeats),
                variant=name,
            )
            rounds[name].append(m["sec_per_step"])
            cpu_rounds[name].append(m["cpu_sec_per_step"])
    first = statistics.median(rounds[args.variants[0]])
    cpu_first = statistics.median(cpu_rounds[args.variants[0]])
    out = {}
    for name, secs in rounds.items():
        med = statistics.median(secs)
        out[name] = {
            "sec_per_step": float(f"{med:.4g}"),
            "samples_per_s": float(f"{args.batch_size / med:.4g}"),
            "rounds": secs,
            "vs_first": round(first / med, 3),
            # CPU seconds of this process per step (one torch thread: the work itself, whatever the load)
            "cpu_sec_per_step": float(f"{statistics.median(cpu_rounds[name]):.4g}"),
            "cpu_rounds": cpu_rounds[name],
            "cpu_vs_first": round(cpu_first / statistics.median(cpu_rounds[name]), 3),
            "what": CPU_VARIANTS[name],
        }
    machine = {k: m[k] for k in ("device", "cores", "avx512", "native_bf16") if k in m}
    return {**machine, "batch_size": args.batch_size, "steps": args.steps, "variants": out}


def _cost(preset, args, workspace) -> dict:
    """Parameters and FLOPs per sample (``benches.cost.policy_cost``) of a freshly built ``args.policy``."""
    import torch

    from equidiff_core.benches.cost import policy_cost
    from equidiff_core.normalizer import Normalizer
    from equidiff_core.policies import make_policy

    torch.manual_seed(0)
    policy = make_policy(args.policy, preset, workspace)
    policy.set_normalizer(Normalizer.from_workspace(workspace))
    return policy_cost(policy, batch=2, noise_repeats=args.noise_repeats)
