"""`equidiff bench train`: training throughput (samples/s) on the CPU and on CUDA, same run.

Each device runs the real ``training.loop.train`` loop with its defaults there (CPU: fp32, DataLoader;
CUDA: bf16 autocast, the whole set resident on the GPU) on synthetic observations (``--observations``:
the twin's table, block and bowl voxelised, or scattered random voxels; gripper states near the
workspace centre: only how many voxels are occupied, and how spread, changes the cost) or on recorded
episodes (``--demos``: ``"observations": "demos"`` and ``demo_episodes``), with the
preset's rotation augmentation, and times ``--steps`` optimiser steps after ``--warmup`` untimed ones
(``benches.timing.measure_training``). Prints one JSON line: ``preset``, ``policy``, ``params``,
``cost`` (parameters and FLOPs per sample: encoder, denoising step, DDIM-16, training step;
``benches.cost``), then per device (``cpu``, ``cuda``) ``device`` (the CPU's name and
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

from equidiff_core.benches.throughput import TrainBenchSettings, run_train_bench
from equidiff_core.benches.timing import CPU_VARIANTS, OBSERVATIONS
from equidiff_ros.commands import print_result


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
    parser.add_argument(
        "--threads",
        type=int,
        default=0,
        help="torch intra-op threads on the CPU (0: one per core idle at the start, as every equidiff command)",
    )
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
    parser.add_argument(
        "--observations",
        choices=OBSERVATIONS,
        default="twin",
        help="the synthetic voxels: twin (the twin's table, block and bowl, as training sees them, without the "
        "arm) or noise (scattered random voxels, 5 %% of the crop's cylinder: more, and spread wider)",
    )
    parser.add_argument(
        "--demos",
        nargs="+",
        default=(),
        metavar="PATH",
        help="train on these recorded episodes (bags, or folders of them) instead of synthetic observations: "
        "what your own frames cost a step, the arm included (e.g. `equidiff twin collect`'s)",
    )


def run(args) -> int:
    settings = TrainBenchSettings(
        preset=args.preset,
        policy=args.policy,
        device=args.device,
        batch_size=args.batch_size,
        cuda_batch_size=args.cuda_batch_size,
        steps=args.steps,
        warmup=args.warmup,
        samples=args.samples,
        cpu_precision=args.cpu_precision,
        runs=args.runs,
        threads=args.threads,
        rotation_aug=args.rotation_aug,
        noise_repeats=args.noise_repeats,
        variants=None if args.variants is None else tuple(args.variants),
        rounds=args.rounds,
        cpu=not args.no_cpu,
        observations=args.observations,
        demos=tuple(args.demos),
    )
    return print_result(run_train_bench(settings), "bench train")
