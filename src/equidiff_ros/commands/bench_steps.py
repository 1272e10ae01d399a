"""`equidiff bench steps`: success against DDIM denoising steps, with inference time and chunk-boundary velocity change.

    equidiff bench steps --out runs/bench_steps                       # shipped checkpoint, 50 unseen scenes
    equidiff bench steps --out runs/bench_steps --steps 4 1 8 2 16    # the most telling first
    equidiff bench steps --checkpoint runs/x/policy.pt --episodes 10 --steps 4 --out /tmp/steps
    equidiff bench steps --out runs/bench_steps --steps --compare runs/policy_ddim4.pt   # a distilled policy

One policy file sampled with DDIM at each of ``--steps`` (timesteps spaced by ``--spacing``; "leading", the
policies' own, puts a single step at t = 0, which returns the noise, so few-step rows default to "trailing") and,
always, at its own sampler (the baseline: the preset's steps or the file's ``sampler`` entry). Each is rolled out
on the same scenes as `equidiff twin evaluate --episodes N` (seeds from 100000, twin.yaml's episode length, the
twin's latency budget, one torch thread, fp32), and its ``predict`` timed on one thread in the same run, the
samplers taking turns. ``--compare FILE...`` adds other policy files, a distilled few-step policy above all
(`equidiff distill`), each at its own sampler on the same scenes, paired against the baseline: its row is named
``<file>__ddim<k>_from<t>``, drawn in orange and named in the legend.

Prints one JSON line: ``rows``, one per sampler, baseline first: ``policy`` (its file), ``steps``, ``spacing``,
``timesteps``, ``success`` with ``successes``, ``episodes`` and ``success_ci95`` (Wilson 95 %), ``reached``,
``lifted``,
``paired_vs_baseline`` (same scenes: difference, paired bootstrap 95 % interval, McNemar p),
``inference_median_ms`` / ``inference_p99_ms`` / ``inference_vs_baseline`` (median ratio),
``boundary_dv_p95_mps`` (the commanded TCP velocity's change at chunk switches, p95, as in `bench chunking`) and
``chunking`` (that probe's other figures); then ``cpu``, the seeds, episode length, latency, ``plot`` (success
against inference time, PNG) and ``complete``.

Each sampler's roll-outs are kept in OUT/<sampler>/ and reused by a later call with the same settings: an
interrupted run resumes where it stopped, and OUT/result.json and OUT/success_vs_inference.png are rewritten
(whole, renamed into place) after every sampler (``pending`` names those still to roll out). ``--plot FILE`` is
a file you name: an existing one is refused (exit 2) before anything runs, unless ``--force``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from equidiff_core.benches.denoising_steps import STEP_COUNTS, StepsSettings, run_steps_bench
from equidiff_core.models.sampling import TIMESTEP_SPACINGS
from equidiff_core.runtime.jobs import progress_lines
from equidiff_core.twin.config import EVALUATION_FIRST_SEED
from equidiff_ros.commands import add_force_argument, print_result
from equidiff_ros.commands.twin_run import add_precision_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = __doc__.split("\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--checkpoint", type=Path, default=None, help="policy.pt (default: the shipped checkpoint)")
    parser.add_argument(
        "--steps",
        type=int,
        nargs="*",
        default=list(STEP_COUNTS),
        help="DDIM step counts, rolled out in this order (none: only the baseline and --compare)",
    )
    parser.add_argument(
        "--compare",
        type=Path,
        nargs="+",
        default=[],
        help="other policy files (a distilled policy: `equidiff distill`), each at its own sampler, same scenes",
    )
    parser.add_argument(
        "--spacing", choices=TIMESTEP_SPACINGS, default="trailing", help="their timestep spacing (default trailing)"
    )
    parser.add_argument("--episodes", type=int, default=50, help="scenes per sampler, the same for all")
    parser.add_argument("--seed", type=int, default=EVALUATION_FIRST_SEED, help="first scene seed (twin evaluate's)")
    parser.add_argument("--max-duration", type=float, default=None, help="sim seconds per episode (twin.yaml's)")
    parser.add_argument("--latency-ms", type=float, default=100.0, help="the twin's latency budget")
    parser.add_argument("--timing-calls", type=int, default=100, help="timed predict calls per sampler")
    parser.add_argument("--out", type=Path, default=Path("runs/bench_steps"), help="roll-outs, result.json, PNG")
    parser.add_argument("--plot", type=Path, default=None, help="also write the PNG here")
    parser.add_argument("--device", default="cpu", help="policy device: cpu | cuda | auto")
    add_precision_argument(parser)
    parser.add_argument("--lab-config", type=Path, default=None)
    parser.add_argument("--twin-config", type=Path, default=None)
    add_force_argument(parser, "replace an existing --plot")


def run(args: argparse.Namespace) -> int:
    settings = StepsSettings(
        checkpoint=args.checkpoint,
        steps=tuple(args.steps),
        compare=tuple(args.compare),
        spacing=args.spacing,
        episodes=args.episodes,
        seed=args.seed,
        max_duration=args.max_duration,
        latency_ms=args.latency_ms,
        timing_calls=args.timing_calls,
        out=args.out,
        plot=args.plot,
        device=args.device,
        precision=args.precision,
        lab_config=args.lab_config,
        twin_config=args.twin_config,
        force=args.force,
    )
    with progress_lines():
        result = run_steps_bench(settings)
    return print_result(result, "bench steps")
