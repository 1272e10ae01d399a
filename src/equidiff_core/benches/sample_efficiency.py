"""Sample efficiency, as the paper's Table 2 measures it: closed-loop success against the number of demos.

EquiDiff and the baseline (DiffPo-C, Vo) train on the first 10, 20 and 40 of the same narrow-yaw
demos (nested subsets, ``demo_sets.nested_subsets``) with one recipe and seed, and each is rolled out
on the same scenes inside the demos' yaw range. ``OUT/<policy>_<count>/`` holds each run (what
``equidiff train`` writes, plus ``rollouts.json``, the roll-outs done, so that a bench finished in
parts rolls nothing out twice). ``run_demos_bench`` takes its ``DemosSettings`` and returns the bench's JSON
line as a dict, or raises ``BenchError``; its progress goes to this module's logger.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from matplotlib.figure import Figure

from equidiff_core.benches import BenchError
from equidiff_core.benches.demo_sets import demos_off_range, ensure_demos, nested_subsets
from equidiff_core.benches.figures import save_with_note
from equidiff_core.benches.rollouts import cached_rollouts, policy_digest, summarize
from equidiff_core.benches.stats import paired_comparison, paired_outcomes
from equidiff_core.benches.training_runs import (
    SLIM_CHECKPOINT,
    Recipe,
    TrainRunError,
    encoder_summary,
    fit_ratios,
    recipe_differences,
    resolve_run,
    run_policy,
    start_run,
    trained_steps,
    training_fit,
    training_recipe,
    under_fit,
    wait_for_runs,
)
from equidiff_core.policy.file import read_policy_file
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.policy.presets import preset_from_dict
from equidiff_core.runtime.output_files import refuse_existing, staged_output, write_output_text
from equidiff_core.twin.config import load_twin_job_configs
from equidiff_core.twin.demos import DirectRecorder
from equidiff_core.twin.evaluate import evaluate_policy
from equidiff_core.twin.yaw_range import in_range_yaw_seeds

POLICIES = ("equidiff", "baseline")
DEMO_COUNTS = (10, 20, 40)

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DemosSettings:
    """``equidiff bench demos``'s settings: its flags, same names (the command's help says more)."""

    recipe: Recipe  # what every training shares: preset, steps (--train-steps), batch, lr, seed, device, ...
    counts: tuple[int, ...]  # the demo counts compared
    policies: tuple[str, ...]  # the POLICIES to train now
    train_counts: tuple[int, ...] | None  # the counts to train now (None: ``counts``)
    eval_episodes: int  # in-range scenes per run
    max_duration: float  # sim seconds per roll-out
    latency_ms: float  # each chunk takes effect this long after its observation
    train_yaw: tuple[float, float]  # the demos' block yaw range, degrees
    max_fit_ratio: float  # under-fit: training-sample action error above this times EquiDiff's (0: no gate)
    out: Path | None  # work directory (None: runs/bench_demos_<time>)
    demos_dir: Path | None  # narrow-yaw demos recorded earlier (None: record them into ``out``)
    trained: Path | None  # roll out DIR/<policy>_<count> trained elsewhere; train nothing
    plot: Path | None  # also write the PNG here
    twin_config: Path | None  # twin.yaml (None: the installed one); lab.yaml is the recipe's
    force: bool = False  # replace an existing ``plot``


def run_name(policy: str, count: int) -> str:
    return f"{policy}_{count}"


def success_table(success: dict[str, Any], counts: list[int]) -> dict[str, dict[str, Any]]:
    """{run name: value} -> {policy: {count (str, for JSON): value}} (a success rate, or its interval)."""
    return {
        policy: {str(n): success.get(run_name(policy, n)) for n in counts}
        for policy in POLICIES
        if any(run_name(policy, n) in success for n in counts)
    }


def plot_success(
    table: dict[str, dict[str, float | None]],
    episodes: int,
    path: Path,
    note: str = "",
    intervals: dict[str, dict[str, list | None]] | None = None,
) -> Path:
    """PNG of success (%) against demos, one line per policy, each point with its 95 % interval as an error bar
    when ``intervals`` (same layout as ``table``) has it (matplotlib's Figure, no pyplot: no display needed)."""
    labels = {"equidiff": "EquiDiff (Vo)", "baseline": "DiffPo-C (Vo)"}
    fig = Figure(figsize=(5.0, 3.6), dpi=120)
    ax = fig.subplots()
    for i, (policy, row) in enumerate(table.items()):
        points = [(int(n), 100 * rate) for n, rate in row.items() if rate is not None]
        if points:
            xs, ys = zip(*points)
            # a small horizontal offset per policy keeps overlapping error bars apart
            shifted = [x * (1 + 0.025 * (i - (len(table) - 1) / 2)) for x in xs]
            cis = [((intervals or {}).get(policy) or {}).get(str(x)) for x in xs]
            errors = [
                [y - 100 * ci[0] if ci else 0.0 for y, ci in zip(ys, cis)],
                [100 * ci[1] - y if ci else 0.0 for y, ci in zip(ys, cis)],
            ]
            ax.errorbar(shifted, ys, yerr=errors, marker="o", capsize=3, label=labels.get(policy, policy))
            for x, y in zip(shifted, ys):
                ax.annotate(f"{y:.0f}", (x, y), textcoords="offset points", xytext=(8, 0), va="center", fontsize=8)
    counts = sorted({int(n) for row in table.values() for n in row})
    ax.set_xticks(counts)
    ax.set_xlabel("demos")
    ax.set_ylabel(f"success, % of {episodes} scenes (95 % interval)")
    ax.set_ylim(-5, 105)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")  # "best" weighs the lines, not the error bars, and covered one
    ax.set_title("Block in bowl (twin), in-range yaw", fontsize=9)
    return save_with_note(fig, path, note)


def evaluate_runs(
    runs_dir: Path,
    out: Path,
    counts: list[int],
    cfg,
    lab,
    episodes: int,
    train_yaw: tuple[float, float],
    max_duration_s: float,
    latency_s: float,
    max_fit_ratio: float,
    device: str = "cpu",
    lr_by_policy: dict[str, float] | None = None,
    log=logger.info,
) -> dict:
    """Roll out every run ``runs_dir/<policy>_<count>/policy.pt`` (or its committed ``weights.ckpt``,
    ``training_runs.run_policy``) on the same ``episodes`` in-range scenes and
    return the bench's result (see the module doc); ValueError when the runs' recipes differ (with
    ``lr_by_policy``, when a run's peak learning rate is not its policy's).

    Roll-outs are saved in ``out/<run>/rollouts.json`` and reused by a later call with the same scenes,
    settings and policy file."""
    names = [run_name(p, n) for p in POLICIES for n in counts]
    run_dirs = {name: resolve_run(runs_dir / name) for name in names}
    recipes = {name: training_recipe(run_dirs[name]) for name in names}
    differences = recipe_differences(
        recipes, None if lr_by_policy is None else {run_name(p, n): lr_by_policy[p] for p in POLICIES for n in counts}
    )
    if differences:
        raise ValueError(
            "the runs were not trained with the same recipe (" + "; ".join(differences) + "): retrain the odd ones out"
        )
    fits = {name: training_fit(run_dirs[name]) for name in names}
    ratios, underfit = {}, []
    for n in counts:
        at_n = {p: fits[run_name(p, n)] for p in POLICIES}
        ratios.update({run_name(p, n): r for p, r in fit_ratios(at_n, "equidiff").items()})
        underfit += [run_name(p, n) for p in under_fit(at_n, "equidiff", max_fit_ratio)]
    seeds = in_range_yaw_seeds(cfg, train_yaw, episodes)
    t0 = time.monotonic()
    summaries, encoders, outcomes, rec = {}, {}, {}, None
    try:
        for name in names:
            policy_file = run_policy(runs_dir / name, out / name)
            settings = {
                "seeds": seeds,
                "max_duration_s": max_duration_s,
                "latency_s": latency_s,
                "policy_digest": policy_digest(policy_file),
            }

            def roll_out(name=name, policy_file=policy_file) -> list:
                nonlocal rec
                rec = rec or DirectRecorder(cfg, lab)
                return evaluate_policy(
                    load_inference_policy(policy_file, device=device),
                    cfg,
                    lab,
                    seeds,
                    max_duration_s,
                    recorder=rec,
                    latency_s=latency_s,
                    log=lambda s: log(f"[{name}] {s}"),
                )

            done = cached_rollouts(
                out / name / "rollouts.json", settings, roll_out, lambda s, name=name: log(f"[{name}] {s}")
            )
            summaries[name] = summarize(done)
            outcomes[name] = {e.seed: e.success for e in done}
            config, _ = read_policy_file(policy_file)
            encoders[name] = encoder_summary(config["policy"], preset_from_dict(config["preset"]))
    finally:
        if rec is not None:
            rec.close()
    table = success_table({name: s["success"] for name, s in summaries.items()}, counts)
    intervals = success_table({name: s["success_ci95"] for name, s in summaries.items()}, counts)
    paired = {
        str(n): paired_comparison(
            *paired_outcomes(outcomes[run_name("equidiff", n)], outcomes[run_name("baseline", n)])
        )
        for n in counts
    }
    recipe = recipes[names[0]] or {}
    lrs = {p: (recipes[run_name(p, counts[0])] or {}).get("lr") for p in POLICIES}
    note = ", ".join(
        f"{k} {recipe[k]}" for k in ("preset", "schedule_steps", "batch_size", "noise_repeats", "lr") if k in recipe
    ) + (f" (baseline {lrs['baseline']})" if lrs["baseline"] not in (None, recipe.get("lr")) else "")
    plot = plot_success(table, episodes, out / "success_vs_demos.png", note, intervals)
    return {
        "bench": "demos",
        "success": table,
        "success_ci95": intervals,
        # EquiDiff against the baseline at each demo count, on the same scenes: difference, interval, McNemar p
        "paired": paired,
        "counts": list(counts),
        "eval_episodes": episodes,
        "eval_scenes": f"block yaw inside the demos' range {list(train_yaw)} (modulo 180 deg), seeds {seeds[0]}..",
        "stages": summaries,
        "encoders": encoders,
        "train_fit": fits,
        "train_fit_vs_equidiff": ratios,
        "under_fit": underfit,
        "max_fit_ratio": max_fit_ratio,
        "train_steps": {name: trained_steps(run_dirs[name]) for name in names},
        "recipe": recipe,
        "lr_by_policy": lrs,
        "max_duration_s": max_duration_s,
        "latency_budget_ms": round(latency_s * 1000, 1),
        "device": device,
        "plot": str(plot),
        "minutes": {"eval": round((time.monotonic() - t0) / 60, 1)},
    }


def run_demos_bench(settings: DemosSettings) -> dict:
    """The whole bench (train what is asked, roll out once every run is in OUT): its JSON line (also in
    OUT/result.json once rolled out; ``pending`` names the runs still to train). BenchError for settings or
    inputs it cannot run with (exit status 2) or a failed training (1)."""
    if settings.eval_episodes < 1 or min(settings.counts) < 1:
        raise BenchError("need --eval-episodes >= 1 and positive --counts", 2)
    if settings.plot is not None:  # a file the user named: refused now, not after hours of training
        refuse_existing(settings.plot, settings.force)
    if settings.recipe.device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
        settings = dataclasses.replace(settings, recipe=dataclasses.replace(settings.recipe, device=device))
    t_start = time.monotonic()
    configs = load_twin_job_configs(settings.recipe.lab_config, settings.twin_config)
    lab, cfg = configs.lab, configs.twin
    out = settings.out or Path("runs") / time.strftime("bench_demos_%Y%m%d_%H%M%S")
    out.mkdir(parents=True, exist_ok=True)
    runs_dir = settings.trained or out
    all_runs = [run_name(p, n) for p in POLICIES for n in settings.counts]
    minutes = {}
    if settings.trained is None:
        demos_dir, _ = ensure_demos(
            settings.demos_dir,
            out,
            max(settings.counts),
            cfg.with_yaw_range(tuple(settings.train_yaw)),
            lab,
            settings.recipe.seed,
            log=logger.info,
        )
        wrong, _ = demos_off_range(demos_dir, tuple(settings.train_yaw))
        if wrong:
            raise BenchError(
                f"{len(wrong)} demos in {demos_dir} were drawn from another block yaw "
                f"range than --train-yaw, e.g. {wrong[0]}",
                2,
            )
        try:
            subsets = nested_subsets(demos_dir, settings.counts)
        except ValueError as err:
            raise BenchError(str(err), 2) from err
        minutes["demos"] = round((time.monotonic() - t_start) / 60, 1)
        t_train = time.monotonic()
        try:
            trained_now = train_runs(settings, out, subsets)
        except TrainRunError as err:
            raise BenchError(f"{err}\nrerun the same command to resume") from err
        minutes["train"] = round((time.monotonic() - t_train) / 60, 1)
        pending = [name for name in all_runs if not (resolve_run(out / name) / "policy.pt").is_file()]
        if pending:
            return {
                "bench": "demos",
                "trained": trained_now,
                "pending": pending,
                "out": str(out),
                "next": f"equidiff bench demos --out {out} --demos-dir {demos_dir} --policies "
                + " ".join(p for p in POLICIES if any(name.startswith(p + "_") for name in pending))
                + " --train-counts "
                + " ".join(str(n) for n in settings.counts if any(name.endswith(f"_{n}") for name in pending))
                + " with this call's recipe flags",
                "minutes": minutes,
            }
    missing = [
        name
        for name in all_runs
        if not any((resolve_run(runs_dir / name) / f).is_file() for f in ("policy.pt", SLIM_CHECKPOINT))
    ]
    if missing:
        raise BenchError(f"no policy.pt or {SLIM_CHECKPOINT} for {', '.join(missing)} in {runs_dir}", 2)
    try:
        result = evaluate_runs(
            runs_dir,
            out,
            settings.counts,
            cfg,
            lab,
            settings.eval_episodes,
            tuple(settings.train_yaw),
            settings.max_duration,
            settings.latency_ms / 1000,
            settings.max_fit_ratio,
            settings.recipe.device,
            lr_by_policy={p: settings.recipe.lr_of(p) for p in POLICIES},
            log=logger.info,
        )
    except ValueError as err:  # the runs' recipes differ
        raise BenchError(str(err), 2) from err
    result["minutes"] = {**minutes, **result["minutes"]}
    if settings.plot is not None:
        with staged_output(settings.plot, force=settings.force) as staged:
            shutil.copyfile(result["plot"], staged.path)
    write_output_text(out / "result.json", json.dumps(result) + "\n", force=True)  # the bench's own, rewritten
    return result


def train_runs(settings: DemosSettings, out: Path, subsets: dict[int, list[Path]]) -> list[str]:
    """Train the requested runs not trained yet, side by side; their names."""
    recipe = settings.recipe
    counts = settings.train_counts or settings.counts
    todo = [
        (policy, n)
        for policy in POLICIES
        if policy in settings.policies
        for n in counts
        if n in subsets and not (resolve_run(out / run_name(policy, n)) / "policy.pt").is_file()
    ]
    if not todo:
        return []
    threads = max(1, (os.cpu_count() or 2) // len(todo))
    runs, outs = {}, {}
    for policy, n in todo:
        name = run_name(policy, n)
        outs[name] = out / name
        spec = recipe.train_spec(policy, "none", subsets[n], outs[name])
        logger.info(f"[bench] training {name} on {n} demos: {spec.settings_text()}")
        runs[name] = start_run(spec, threads)
    deadline = (
        None if settings.recipe.max_minutes is None else time.monotonic() + settings.recipe.max_minutes * 60 + 600
    )
    wait_for_runs(runs, outs, deadline)
    return list(runs)
