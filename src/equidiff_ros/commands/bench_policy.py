"""`equidiff bench policy`: time the exported policy against eager escnn, same weights, same run.

Prints one JSON line with ``preset``, ``params``, ``encoder_ms``, ``step_ms`` (one denoising
step), ``ddim16_median_ms`` and ``ddim16_p99_ms`` (full predict(): encoder + DDIM-16 + decode)
for the exported plain-torch policy with the chosen switches, ``eager_ddim16_median_ms`` for the
training-time model (escnn for EquiDiff) in fp32 eager mode, and ``device``. Random weights by
default (timing does not depend on them); ``--checkpoint policy.pt`` times a trained file.
``inference_steps`` and ``timesteps`` name the sampler every ``predict()`` ran: the preset's DDIM-16, or
the file's own (a distilled few-step policy's, `equidiff distill`), which the ``ddim16_*`` keys then time.
Targets on a 2-core CPU: compact <= 100 ms p99, paper <= 400 ms median.

``--modes bf16-traced,bf16-traced-graph,fp32-traced`` times several ways of running the same
export in one run (``benches.timing.InferenceMode``): the top-level figures are the first measured
mode's, ``modes`` holds each one's (or its error), ``best_mode`` / ``best_ddim16_p99_ms`` the
smallest p99. ``--rtc`` adds RTC-guided sampling (``rtc_median_ms``, ``rtc_vs_plain``).
Every mode reports what the default doubt signal adds (``doubt_signal``, ``doubt_ms``,
``doubt_vs_ddim16_percent`` against ``doubt_ddim16_median_ms``, timed alternately; docs/doubt.md);
``--doubt-samples 2 4 8`` adds the extra ms of K samples per observation (``spread_extra_ms``).
``--compare-relu-order`` adds the same export with the encoder's old order, each ReLU before its
max-pool (``relu_before_pool``; ``relu_order_cpu_ms``: both orders alternately in CPU time).
``encoder_gflop`` (``benches.cost.encoder_flops``) over ``encoder_ms`` gives ``encoder_gflop_s``, and
over ``gemm_gflop_s`` (an fp32 1024² matrix product on the same device and threads, same run)
``encoder_gemm_ratio``. ``--compare-encoder`` adds ``encoder_kernels``: the same export in the first
measured mode with each encoder kernel choice (``onednn``, the default, and ``native``, the path before;
they differ in fp32 on a CPU), timed alternately, and ``encoder_speedup_vs_native``.
"""

from __future__ import annotations

from equidiff_core.benches.throughput import PolicyBenchSettings, run_policy_bench
from equidiff_core.runtime.machine import PRECISIONS
from equidiff_ros.commands import print_result


def add_arguments(parser) -> None:
    parser.add_argument("--preset", default="compact", help="paper | compact | tiny")
    parser.add_argument("--policy", default="equidiff", choices=["equidiff", "baseline"])
    parser.add_argument("--checkpoint", default=None, help="time this exported policy.pt instead of random weights")
    parser.add_argument("--device", default="auto", help="auto | cpu | cuda")
    parser.add_argument(
        "--precision",
        default="auto",
        choices=PRECISIONS,
        help="auto: bf16 on CUDA, fp32 on a CPU",
    )
    parser.add_argument("--no-jit", action="store_true", help="skip torch.jit.trace of encoder and denoiser")
    parser.add_argument(
        "--compile",
        action="store_true",
        help="torch.compile the denoising step (slow the first time, then cached on disk)",
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
        "--doubt-samples",
        type=int,
        nargs="+",
        default=[],
        metavar="K",
        help="also time K DDIM samples per observation in one encoder pass (the spread signal's cost), each K >= 2",
    )
    parser.add_argument(
        "--compare-relu-order",
        action="store_true",
        help="also time the same weights with each ReLU before its max-pool (the encoder order before), in the "
        "first measured mode (adds relu_before_pool: encoder_ms, ddim16_median_ms; relu_order_cpu_ms)",
    )
    parser.add_argument(
        "--compare-encoder",
        action="store_true",
        help="also time the same weights with the fp32 CPU encoder's old kernels (torch's choice), alternately, in "
        "the first measured mode (adds encoder_kernels: onednn and native, encoder_speedup_vs_native)",
    )
    parser.add_argument("--iters", type=int, default=30, help="timed DDIM-16 runs of the exported policy")
    parser.add_argument("--eager-iters", type=int, default=3, help="timed runs of the eager escnn model")
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch intra-op threads (default 1: on a shared machine more threads oversubscribe; 0: one per core idle at the start)",
    )


def run(args) -> int:
    settings = PolicyBenchSettings(
        preset=args.preset,
        policy=args.policy,
        checkpoint=args.checkpoint,
        device=args.device,
        precision=args.precision,
        execution="compiled" if args.compile else "eager" if args.no_jit else "traced",
        graph=args.graph,
        modes=args.modes,
        rtc=args.rtc,
        doubt_samples=tuple(args.doubt_samples),
        compare_relu_order=args.compare_relu_order,
        compare_encoder=args.compare_encoder,
        iters=args.iters,
        eager_iters=args.eager_iters,
        threads=args.threads,
    )
    return print_result(run_policy_bench(settings), "bench policy")
