"""The measurements behind ``equidiff bench policy`` and ``equidiff bench train``, on the CPU or CUDA.

Inference: an exported policy is loaded once per *mode* (``InferenceMode``: precision, eager /
traced / compiled, with or without a CUDA graph) and timed on one observation: the encoder, one
denoising step, the whole DDIM-16 ``predict`` (median and p99, host wall clock after the device
finished: what the control loop waits for), and optionally RTC-guided ``predict`` against plain
DDIM. A graph mode also reports how far its actions lie from the same mode without the graph
(same seed): on CUDA the graph must compute the same function. ``time_relu_orders`` times the same
export with the encoder's old order (each ReLU before its max-pool) beside the current one, and
``time_encoder_kernels`` with the fp32 CPU encoder's old kernels (``encoder_kernels="native"``),
alternately. ``gemm_gflop_s``: the device's fp32 1024² matrix product, the yardstick for the
encoder's FLOP rate.

Training: the real ``training.loop.train`` loop on synthetic observations (``SyntheticTrainingSet``: how many
voxels they occupy, and how spread, is what changes the cost, through ``models.sparse_stage``), timed over
``steps`` optimiser steps after ``warmup`` untimed ones, with the time the loop waited for its next
batch (``data_s``, training's per-step metric) as a share of the step time. The loss is read back
every step (``loss.item()``), so the device's queue is empty while the host fetches a batch: that wait
is time the GPU idles. On CUDA, NVML's utilisation (the share of
time a kernel was running) is sampled over the timed steps when ``pynvml`` is installed. On the CPU
the process's CPU seconds per step stand beside the wall seconds: on a loaded machine they still
measure the work, not the waiting. ``measure_training_variants`` times CPU training-step variants
(``CPU_VARIANTS``) in alternating rounds of one run, so that a shared machine's load weighs on all alike.
"""

from __future__ import annotations

import contextlib
import functools
import statistics
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..geometry import slice_resampled_rotation
from ..models.equivariance import random_observation, twin_scenes
from ..models.plain import relu_before_pool_order
from ..models.sparse_stage import dense_first_stage
from ..policy.diffusion import make_policy
from ..policy.doubt import DEFAULT_SAMPLES, DEFAULT_SIGNAL, DoubtTracker
from ..policy.inference import ENCODER_KERNELS, load_inference_policy
from ..policy.normalizer import Normalizer
from ..runtime.machine import PRECISIONS, cpu_description, cpu_model
from ..training.config import DATA_SOURCES, TrainConfig
from ..training.loop import previous_optimizer_step, train
from ..twin.config import load_twin_config
from ..wire.chunk import RealTimeChunking

MODE_EXECUTIONS = ("eager", "traced", "compiled")


@dataclass(frozen=True)
class InferenceMode:
    """How an exported policy runs: ``precision-execution[-graph]``, e.g. ``bf16-traced-graph``."""

    precision: str = "auto"
    execution: str = "traced"  # eager | traced (jit.trace + freeze) | compiled (traced + torch.compile)
    graph: bool = False  # CUDA graph replay of the whole sampling

    @property
    def name(self) -> str:
        return f"{self.precision}-{self.execution}" + ("-graph" if self.graph else "")

    @classmethod
    def parse(cls, text: str) -> InferenceMode:
        parts = text.strip().split("-")
        graph = parts[-1] == "graph"
        if graph:
            parts = parts[:-1]
        if len(parts) != 2 or parts[0] not in PRECISIONS or parts[1] not in MODE_EXECUTIONS:
            raise ValueError(
                f"inference mode {text!r}: expected PRECISION-EXECUTION[-graph] with PRECISION in "
                f"{PRECISIONS} and EXECUTION in {MODE_EXECUTIONS}, e.g. bf16-traced-graph"
            )
        return cls(parts[0], parts[1], graph)

    def load(self, path: str | Path, device: torch.device, encoder_kernels: str = "onednn"):
        return load_inference_policy(
            path,
            device=str(device),
            precision=self.precision,
            jit=self.execution != "eager",
            compile=self.execution == "compiled",
            cuda_graph=self.graph,
            encoder_kernels=encoder_kernels,
        )


def device_name(device: torch.device | str) -> str:
    device = torch.device(device)
    if device.type == "cuda":
        return f"cuda: {torch.cuda.get_device_name(device)}"
    return f"cpu: {cpu_model()}, {torch.get_num_threads()} threads"


def synchronizer(device: torch.device | str):
    """What makes a host clock read after the device's work: CUDA's synchronize, nothing on the CPU."""
    return torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)


def timed_ms(fn, iters: int, sync) -> list[float]:
    times = []
    for _ in range(iters):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append((time.perf_counter() - t0) * 1000)
    return times


def _ms(value: float) -> float:
    return round(float(value), 3)


class ObservationProbe:
    """Just enough of a policy for ``models.equivariance.random_observation``."""

    def __init__(self, preset, workspace):
        self.preset, self.workspace = preset, workspace


def probe_observation(preset, workspace, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """One random observation (voxels (4, R, R, R) uint8, ee (10,)) as the policy node passes it."""
    vox, ee = random_observation(ObservationProbe(preset, workspace), batch=1, seed=seed, fill=0.05)
    return vox[0, 0].numpy(), ee[0, 0].numpy()


def rtc_guide(policy, voxels: np.ndarray, ee: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A real-time-chunking guide as the policy node builds one: the previous chunk (predicted for
    this observation two periods ago), latency one period."""
    previous = policy.predict(voxels, ee, seed=1)
    dt_ns = round(policy.dt * 1e9)
    rtc = RealTimeChunking(RealTimeChunking.delay_for(policy.dt, policy.dt), dt_ns, max_gap_m=10.0)
    rtc.remember(0, previous)
    return rtc.guide(2 * dt_ns)


def time_doubt(policy, voxels: np.ndarray, ee: np.ndarray, iters: int, sample_counts, sync) -> dict:
    """What the doubt signal (``policy.doubt``) adds to DDIM-16: the default signal's ``doubt_ms`` and
    ``doubt_vs_ddim16_percent``, and with ``sample_counts`` the extra ms (and percent) of K samples
    through the U-Net in one encoder pass (``spread_extra_ms``), all timed in alternating rounds with
    plain DDIM-16 so that a shared machine's load weighs on each alike."""
    tracker = DoubtTracker(round(policy.dt * 1e9), DEFAULT_SIGNAL)
    counts = sorted({int(k) for k in sample_counts} | ({DEFAULT_SAMPLES} - {1}))
    plain, update, drawn = [], [], {k: [] for k in counts}
    previous = policy.predict(voxels, ee, seed=1)
    tracker.update(0, previous)
    stamp = policy.preset.n_action_steps * tracker.dt_ns  # the next answer's stamp: half the chunk overlaps
    for k in counts:
        policy.predict_samples(voxels, ee, k, seed=0)  # a traced policy traces each batch size once
    for _ in range(iters):
        plain += timed_ms(lambda: policy.predict(voxels, ee, seed=0), 1, sync)
        update += timed_ms(lambda: tracker.update(stamp, previous[None]), 1, sync)
        for k in counts:
            drawn[k] += timed_ms(lambda k=k: policy.predict_samples(voxels, ee, k, seed=0), 1, sync)
    base = float(np.median(plain))
    extra = {k: float(np.median(v)) - base for k, v in drawn.items()}
    doubt = float(np.median(update)) + (extra[DEFAULT_SAMPLES] if DEFAULT_SAMPLES > 1 else 0.0)
    figures = {
        "doubt_signal": DEFAULT_SIGNAL,
        "doubt_samples": DEFAULT_SAMPLES,
        "doubt_ms": _ms(doubt),
        "doubt_vs_ddim16_percent": round(100 * doubt / base, 2),
        "doubt_ddim16_median_ms": _ms(base),
    }
    if sample_counts:
        figures["spread_extra_ms"] = {str(k): _ms(extra[k]) for k in sorted(sample_counts)}
        figures["spread_vs_ddim16_percent"] = {str(k): round(100 * extra[k] / base, 1) for k in sorted(sample_counts)}
    return figures


def time_inference_mode(
    path: str | Path,
    device: torch.device,
    mode: InferenceMode,
    iters: int,
    rtc: bool = False,
    doubt_samples: tuple[int, ...] = (),
) -> tuple[dict, dict]:
    """(figures, actions) of one mode; actions: ``plain`` and ``guided`` (seeded) for comparisons."""
    sync = synchronizer(device)
    t0 = time.perf_counter()
    policy = mode.load(path, device)
    vox, ee = probe_observation(policy.preset, policy.workspace)
    policy.warmup(3)
    sync()
    load_s = time.perf_counter() - t0
    enc = timed_ms(lambda: policy.encode(vox, ee), max(5, iters // 3), sync)
    cond = policy.encode(vox, ee)
    x = torch.zeros(1, policy.preset.horizon, policy.codec.dim, device=device)
    t = torch.tensor([50], device=device)
    step = timed_ms(lambda: policy.denoise(x, t, cond), max(10, iters), sync)
    ddim = timed_ms(lambda: policy.predict(vox, ee, seed=0), iters, sync)
    guide = rtc_guide(policy, vox, ee)
    figures = {
        "precision": policy.precision,
        "jit": policy.jit,
        "compiled": policy.compiled,
        "graph": policy.graphed,
        "load_s": round(load_s, 2),
        "encoder_ms": _ms(np.median(enc)),
        "step_ms": _ms(np.median(step)),
        "ddim16_median_ms": _ms(np.median(ddim)),
        "ddim16_p99_ms": _ms(np.percentile(ddim, 99)),
    }
    if rtc:
        guided = timed_ms(lambda: policy.predict(vox, ee, seed=0, guide=guide), iters, sync)
        figures["rtc_median_ms"] = _ms(np.median(guided))
        figures["rtc_p99_ms"] = _ms(np.percentile(guided, 99))
        figures["rtc_vs_plain"] = round(float(np.median(guided) / np.median(ddim)), 3)
    figures.update(time_doubt(policy, vox, ee, iters, doubt_samples, sync))
    actions = {
        "plain": policy.predict(vox, ee, seed=0),
        "guided": policy.predict(vox, ee, seed=0, guide=guide),
    }
    return figures, actions


def time_inference_modes(
    path: str | Path,
    device: torch.device,
    modes: list[InferenceMode],
    iters: int,
    rtc: bool = False,
    doubt_samples: tuple[int, ...] = (),
) -> dict[str, dict]:
    """Each mode's figures, or ``{"error": ...}`` / ``{"skipped": ...}``: one failing mode (a graph that
    will not capture, a compiler missing) leaves the others measured. Graph modes add
    ``max_abs_diff_vs_ungraphed`` (plain) and ``rtc_max_abs_diff_vs_ungraphed`` (guided)."""
    results: dict[str, dict] = {}
    actions: dict[str, dict] = {}
    for mode in modes:
        if mode.graph and torch.device(device).type != "cuda":
            results[mode.name] = {"skipped": "CUDA graphs need a CUDA device"}
            continue
        try:
            results[mode.name], actions[mode.name] = time_inference_mode(path, device, mode, iters, rtc, doubt_samples)
            if mode.graph:
                plain = InferenceMode(mode.precision, mode.execution, graph=False)
                if plain.name not in actions:
                    actions[plain.name] = time_inference_mode(path, device, plain, 1)[1]
                for kind, key in (("plain", "max_abs_diff_vs_ungraphed"), ("guided", "rtc_max_abs_diff_vs_ungraphed")):
                    diff = np.abs(actions[mode.name][kind] - actions[plain.name][kind]).max()
                    results[mode.name][key] = float(f"{diff:.3g}")
        except Exception as err:  # noqa: BLE001 - recorded per mode; the other modes still run
            results[mode.name] = {"error": f"{type(err).__name__}: {(str(err).splitlines() or [''])[0]}"}
        if torch.device(device).type == "cuda":
            torch.cuda.empty_cache()
    return results


def time_relu_orders(path: str | Path, device: torch.device, mode: InferenceMode, iters: int) -> dict:
    """The same export loaded twice in ``mode``, the encoder's current order (max-pool before ReLU) and the
    old one (``models.plain.relu_before_pool_order``): ``relu_before_pool`` (the old order's encoder and
    DDIM-16 median wall ms) and ``relu_order_cpu_ms`` (both orders timed alternately in this process's CPU
    time, which a loaded machine's waiting leaves out)."""
    sync = synchronizer(device)
    current = mode.load(path, device)
    with relu_before_pool_order():
        old = mode.load(path, device)
    vox, ee = probe_observation(current.preset, current.workspace)
    current.warmup(3)
    old.warmup(3)
    old_enc = timed_ms(lambda: old.encode(vox, ee), max(5, iters // 3), sync)
    old_ddim = timed_ms(lambda: old.predict(vox, ee, seed=0), iters, sync)
    both = time_alternately({"pool_before_relu": current, "relu_before_pool": old}, vox, ee, iters, sync)
    return {
        "relu_before_pool": {"encoder_ms": _ms(np.median(old_enc)), "ddim16_median_ms": _ms(np.median(old_ddim))},
        "relu_order_cpu_ms": {
            label: {"encoder": r["encoder_cpu_ms"], "ddim16": r["ddim16_cpu_ms"]} for label, r in both.items()
        },
    }


def time_alternately(policies: dict, vox: np.ndarray, ee: np.ndarray, iters: int, sync) -> dict[str, dict]:
    """Each policy's encoder and DDIM-16 ``predict``, one call of each policy in turn per round (a shared
    machine's load then weighs on all alike): medians of the wall clock (``encoder_ms``,
    ``ddim16_median_ms``) and of this process's CPU time (``encoder_cpu_ms``, ``ddim16_cpu_ms``)."""
    times: dict[str, dict[str, list[float]]] = {label: {} for label in policies}
    for _ in range(iters):
        for label, policy in policies.items():
            for key, call in (
                ("encoder", functools.partial(policy.encode, vox, ee)),
                ("ddim16", functools.partial(policy.predict, vox, ee, seed=0)),
            ):
                w0, c0 = time.perf_counter(), time.process_time()
                call()
                sync()
                times[label].setdefault(key, []).append((time.perf_counter() - w0) * 1000)
                times[label].setdefault(f"{key}_cpu", []).append((time.process_time() - c0) * 1000)
    names = {
        "encoder": "encoder_ms",
        "ddim16": "ddim16_median_ms",
        "encoder_cpu": "encoder_cpu_ms",
        "ddim16_cpu": "ddim16_cpu_ms",
    }
    return {label: {names[k]: _ms(np.median(v)) for k, v in t.items()} for label, t in times.items()}


def time_encoder_kernels(path: str | Path, device: torch.device, mode: InferenceMode, iters: int) -> dict[str, dict]:
    """The same export loaded in ``mode`` with each of ``policy.inference.ENCODER_KERNELS`` (they differ in
    fp32 on a CPU), timed alternately (``time_alternately``), and ``max_abs_diff``: the largest difference
    of each one's encoder output from the first's, on the probe observation."""
    sync = synchronizer(device)
    policies = {kernels: mode.load(path, device, kernels) for kernels in ENCODER_KERNELS}
    first = next(iter(policies.values()))
    vox, ee = probe_observation(first.preset, first.workspace)
    for policy in policies.values():
        policy.warmup(3)
    result = time_alternately(policies, vox, ee, max(3, iters), sync)
    reference = first.encode(vox, ee).float()
    for kernels, policy in policies.items():
        result[kernels]["max_abs_diff"] = float(f"{(policy.encode(vox, ee).float() - reference).abs().max():.3g}")
    return result


def gemm_gflop_s(device: torch.device | str, n: int = 1024, iters: int = 10) -> dict[str, float]:
    """The device's fp32 GEMM rate with torch's current thread count: n x n matrix products (2 n³ FLOPs
    each), ``gemm_gflop_s`` from the median wall time of ``iters``; on a CPU also ``gemm_cpu_gflop_s`` from
    the median of this process's CPU time, which a shared machine's waiting leaves out."""
    gen = torch.Generator().manual_seed(0)
    a, b = (torch.randn(n, n, generator=gen).to(device) for _ in range(2))
    sync = synchronizer(device)
    a @ b  # warm-up: MKL's/cuBLAS's handles and buffers
    sync()
    wall, cpu = [], []
    for _ in range(iters):
        w0, c0 = time.perf_counter(), time.process_time()
        a @ b
        sync()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    rate = lambda seconds: round(2 * n**3 / (float(np.median(seconds)) * 1e9), 1)
    return {
        "gemm_gflop_s": rate(wall),
        **({"gemm_cpu_gflop_s": rate(cpu)} if torch.device(device).type == "cpu" else {}),
    }


def best_mode(results: dict[str, dict], key: str = "ddim16_p99_ms") -> str | None:
    """The measured mode with the smallest ``key``."""
    measured = {name: r[key] for name, r in results.items() if key in r}
    return min(measured, key=measured.get) if measured else None


OBSERVATIONS = ("twin", "noise")


class SyntheticTrainingSet:
    """Synthetic observations with actions around the gripper state (map-style dataset).

    ``observations``: "twin", the twin's table, block and bowl voxelised (``equivariance.twin_scenes``; no arm, which
    recorded frames hold); "noise", random coloured voxels filling 5 % of the crop's inscribed cylinder, scattered.
    Only the count and spread of the occupied voxels change a step's cost (the encoder's first stage,
    ``models.sparse_stage``; docs/results/model.md counts them)."""

    def __init__(self, preset, workspace, n: int, seed: int = 0, observations: str = "twin"):
        if observations not in OBSERVATIONS:
            raise ValueError(f"observations must be one of {OBSERVATIONS}, got {observations!r}")
        probe = ObservationProbe(preset, workspace)
        if observations == "twin":
            scene = load_twin_config().scene
            parts = [twin_scenes(preset, workspace, min(8, n - a), seed + a, scene=scene) for a in range(0, n, 8)]
        else:
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


class GpuBusySampler:
    """Mean NVML utilisation of one GPU while running: the share of time a kernel was executing
    (NVML's own sampling period is 1/6 to 1 s). ``mean()`` is None without pynvml."""

    def __init__(self, device: torch.device, period_s: float = 0.05):
        self.device, self.period_s = device, period_s
        self.samples: list[float] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        try:
            torch.cuda.utilization(self.device)
        except Exception:  # noqa: BLE001 - pynvml missing or NVML unusable: no figure, no failure
            return
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.samples.append(float(torch.cuda.utilization(self.device)))

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def mean(self) -> float | None:
        return round(float(np.mean(self.samples)), 1) if self.samples else None


class _StepClock:
    """on_step: the host clock after the device finished each step, and the step's wait for data."""

    def __init__(self, device: torch.device, warmup: int, steps: int):
        self.sync = synchronizer(device)
        self.warmup, self.last = warmup, warmup + steps
        self.times: dict[int, float] = {}
        self.cpu_times: dict[int, float] = {}
        self.data_s: dict[int, float] = {}
        self.busy = GpuBusySampler(device) if device.type == "cuda" else None

    def on_step(self, step, metrics):
        self.sync()
        self.times[step] = time.perf_counter()
        self.cpu_times[step] = time.process_time()
        self.data_s[step] = float(metrics.get("data_s", 0.0))
        if self.busy is not None and step == self.warmup:
            self.busy.start()
        if self.busy is not None and step == self.last:
            self.busy.stop()


def measure_training(
    policy,
    data,
    device: str,
    batch_size: int,
    steps: int,
    warmup: int,
    precision: str = "auto",
    data_source: str = "auto",
    noise_repeats: int = 1,
    callbacks: tuple = (),
) -> dict:
    """Samples/s of ``training.loop.train`` on ``device`` (``policy`` trains on: its weights change), with
    ``noise_repeats`` (noise, step) draws per encoder pass; ``callbacks`` run after each step, inside
    the timed steps."""
    device_t = torch.device(device)
    if device_t.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device_t)
    clock = _StepClock(device_t, warmup, steps)
    cfg = TrainConfig(
        steps=warmup + steps,
        batch_size=batch_size,
        warmup_steps=1,
        device=device,
        eval_every=0,
        checkpoint_every=0,
        log_every=1,
        precision=precision,
        data=data_source,
        noise_repeats=noise_repeats,
    )
    with tempfile.TemporaryDirectory(prefix="bench_train_") as tmp:
        result = train(policy, data, None, cfg, tmp, callbacks=[clock, *callbacks])
    seconds = clock.times[warmup + steps] - clock.times[warmup]
    waited = sum(clock.data_s[s] for s in range(warmup + 1, warmup + steps + 1))
    out = {
        "device": device_name(device_t),
        "batch_size": batch_size,
        "precision": result.precision,
        "data": result.data,
        "steps": steps,
        "sec_per_step": float(f"{seconds / steps:.4g}"),
        "samples_per_s": float(f"{batch_size * steps / seconds:.4g}"),
        "data_wait_share": float(f"{waited / seconds:.3g}"),
    }
    if clock.busy is not None:
        out["gpu_busy_pct"] = clock.busy.mean()
        out["peak_memory_gb"] = round(torch.cuda.max_memory_allocated(device_t) / 1e9, 2)
    if device_t.type == "cpu":
        cpu_seconds = clock.cpu_times[warmup + steps] - clock.cpu_times[warmup]
        out["cpu_sec_per_step"] = float(f"{cpu_seconds / steps:.4g}")
        d = cpu_description()
        out.update(cores=d["cores"], avx512=d["avx512"], native_bf16=d["bf16"])
    return out


# What a CPU training step can be made of, for ``measure_training_variants``: each one training's CPU default
# but for one thing.
CPU_VARIANTS = {
    "default": "fp32, the encoder's max-pools before their ReLUs (training's CPU default)",
    "relu_before_pool": "each ReLU before the max-pool after it, the order before (the 56^3 ReLU and its backward)",
    "bf16": "bf16 autocast (the CPU's AVX512-BF16 / AMX, if any)",
    "channels_last": "the voxel input in channels_last_3d memory format (the baseline's default already)",
    "contiguous_input": "the voxel input in the contiguous (N, C, D, H, W) format (the baseline's before)",
    "one_noise_draw": "1 (noise, step) draw per encoder pass instead of noise_repeats",
    "eight_noise_draws": "8 (noise, step) draws per encoder pass instead of noise_repeats",
    "train_mode_every_step": "policy.train() before every step, as training did before (escnn's train() hashes "
    "every basis expansion of the model)",
    "dense_first_stage": "the encoder's first 3^3 conv and 2^3 max-pool computed densely, as before "
    "models.sparse_stage computed them from the occupied voxels",
    "slice_rotation": "the rotation augmentation resampling every x-y slice in float, as before it gathered whole "
    "columns (geometry.slice_resampled_rotation)",
    "previous_optimizer_step": "AdamW's loop over every parameter tensor and the gradient clip walking the model each "
    "step (escnn hashes every basis expansion on a walk), as before training.loop.adamw",
    "previous_default": "dense_first_stage, slice_rotation and previous_optimizer_step together: the CPU step before "
    "all three",
}
VARIANT_NOISE_REPEATS = {"one_noise_draw": 1, "eight_noise_draws": 8}


class _TrainModeEveryStep:
    """The variant ``train_mode_every_step``: ``policy.train()`` between every two steps."""

    def __init__(self, policy):
        self.policy = policy

    def on_step(self, step, metrics):
        self.policy.train()


def variant_policy(policy_name: str, preset, workspace, variant: str):
    """(a fresh policy shaped as ``variant``, the training precision it needs)."""
    if variant not in CPU_VARIANTS:
        raise ValueError(f"training variant {variant!r}: expected one of {tuple(CPU_VARIANTS)}")
    with relu_before_pool_order() if variant == "relu_before_pool" else contextlib.nullcontext():
        policy = fresh_policy(policy_name, preset, workspace)
    if variant in ("channels_last", "contiguous_input"):
        layout = torch.channels_last_3d if variant == "channels_last" else torch.contiguous_format

        def to_layout(module, inputs):
            x = inputs[0]
            if isinstance(x, torch.Tensor):
                return (x.contiguous(memory_format=layout),)
            return (type(x)(x.tensor.contiguous(memory_format=layout), x.type),)  # escnn's GeometricTensor

        policy.model.encoder.register_forward_pre_hook(to_layout)
    return policy, ("bf16" if variant == "bf16" else "fp32")


@contextlib.contextmanager
def _variant_paths(variant: str):
    """The code paths ``variant`` trains through (the earlier ones it names), in force inside."""
    with contextlib.ExitStack() as paths:
        if variant in ("dense_first_stage", "previous_default"):
            paths.enter_context(dense_first_stage())
        if variant in ("slice_rotation", "previous_default"):
            paths.enter_context(slice_resampled_rotation())
        if variant in ("previous_optimizer_step", "previous_default"):
            paths.enter_context(previous_optimizer_step())
        yield


def measure_training_variants(
    policy_name: str,
    preset,
    workspace,
    data,
    variants: list[str],
    batch_size: int,
    steps: int,
    warmup: int,
    rounds: int = 3,
    noise_repeats: int = 1,
) -> dict:
    """Each of ``variants`` timed on the CPU in ``rounds`` alternating rounds: the CPU, and per variant the
    median round's ``sec_per_step`` and ``samples_per_s``, every round's, ``vs_first`` (the first variant's
    median over this one's: above 1 is faster), and the same in CPU seconds (``cpu_sec_per_step``,
    ``cpu_vs_first``)."""
    wall = {name: [] for name in variants}
    cpu = {name: [] for name in variants}
    m = {}
    for _ in range(max(1, rounds)):
        for name in variants:
            policy, precision = variant_policy(policy_name, preset, workspace, name)
            repeats = VARIANT_NOISE_REPEATS.get(name, noise_repeats)
            extra = (_TrainModeEveryStep(policy),) if name == "train_mode_every_step" else ()
            with _variant_paths(name):
                m = measure_training(policy, data, "cpu", batch_size, steps, warmup, precision, "auto", repeats, extra)
            wall[name].append(m["sec_per_step"])
            cpu[name].append(m["cpu_sec_per_step"])
    first, cpu_first = statistics.median(wall[variants[0]]), statistics.median(cpu[variants[0]])
    out = {}
    for name, secs in wall.items():
        med, cpu_med = statistics.median(secs), statistics.median(cpu[name])
        out[name] = {
            "sec_per_step": float(f"{med:.4g}"),
            "samples_per_s": float(f"{batch_size / med:.4g}"),
            "rounds": secs,
            "vs_first": round(first / med, 3),
            "cpu_sec_per_step": float(f"{cpu_med:.4g}"),
            "cpu_rounds": cpu[name],
            "cpu_vs_first": round(cpu_first / cpu_med, 3),
            "what": CPU_VARIANTS[name],
        }
    machine = {k: m[k] for k in ("device", "cores", "avx512", "native_bf16") if k in m}
    return {**machine, "batch_size": batch_size, "steps": steps, "variants": out}


def parse_training_runs(text: str) -> list[tuple[str, str]]:
    """``"bf16,fp32,bf16:loader"`` -> [(precision, data source), ...] for ``measure_training``."""
    runs = []
    for item in text.split(","):
        precision, _, data_source = item.strip().partition(":")
        data_source = data_source or "auto"
        if precision not in PRECISIONS or data_source not in DATA_SOURCES:
            raise ValueError(
                f"training run {item!r}: expected PRECISION[:DATA] with PRECISION in {PRECISIONS} "
                f"and DATA in {DATA_SOURCES}, e.g. bf16:loader"
            )
        runs.append((precision, data_source))
    return runs


def fresh_policy(policy_name: str, preset, workspace, seed: int = 0):
    torch.manual_seed(seed)
    policy = make_policy(policy_name, preset, workspace)
    policy.set_normalizer(Normalizer.from_workspace(workspace))
    return policy
