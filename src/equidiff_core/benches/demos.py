"""Sample efficiency, as the paper's Table 2 measures it: closed-loop success against the number of demos.

EquiDiff and the baseline (DiffPo-C, Vo) train on the first 10, 20 and 40 of the same narrow-yaw
demos (nested subsets, ``demo_sets.nested_subsets``) with one recipe and seed, and each is rolled out
on the same scenes inside the demos' yaw range. ``OUT/<policy>_<count>/`` holds each run (what
``equidiff train`` writes, plus ``rollouts.json``, the roll-outs done, so that a bench finished in
parts rolls nothing out twice).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

POLICIES = ("equidiff", "baseline")
DEMO_COUNTS = (10, 20, 40)


def run_name(policy: str, count: int) -> str:
    return f"{policy}_{count}"


def file_digest(path: Path) -> str:
    """sha256 of a policy file: roll-outs saved for one file are not reused for another."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def success_table(success: dict[str, float | None], counts: list[int]) -> dict[str, dict[str, float | None]]:
    """{run name: success} -> {policy: {count (str, for JSON): success}}."""
    return {
        policy: {str(n): success.get(run_name(policy, n)) for n in counts}
        for policy in POLICIES
        if any(run_name(policy, n) in success for n in counts)
    }


def plot_success(table: dict[str, dict[str, float | None]], episodes: int, path: Path, note: str = "") -> Path:
    """PNG of success (%) against demos, one line per policy (matplotlib, Agg: no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = {"equidiff": "EquiDiff (Vo)", "baseline": "DiffPo-C (Vo)"}
    fig, ax = plt.subplots(figsize=(5.0, 3.6), dpi=120)
    for policy, row in table.items():
        points = [(int(n), 100 * rate) for n, rate in row.items() if rate is not None]
        if points:
            xs, ys = zip(*points)
            ax.plot(xs, ys, marker="o", label=labels.get(policy, policy))
            for x, y in points:
                ax.annotate(f"{y:.0f}", (x, y), textcoords="offset points", xytext=(0, 6), ha="center", fontsize=8)
    counts = sorted({int(n) for row in table.values() for n in row})
    ax.set_xticks(counts)
    ax.set_xlabel("demos")
    ax.set_ylabel(f"success, % of {episodes} scenes")
    ax.set_ylim(-5, 105)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left")
    ax.set_title("Block in bowl (twin), in-range yaw" + (f"\n{note}" if note else ""), fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


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
    log=print,
) -> dict:
    """Roll out every run ``runs_dir/<policy>_<count>/policy.pt`` (or its committed ``weights.ckpt``,
    ``training_runs.run_policy``) on the same ``episodes`` in-range scenes and
    return the bench's result (see the module doc); ValueError when the runs' recipes differ.

    Roll-outs are saved in ``out/<run>/rollouts.json`` and reused by a later call with the same scenes,
    settings and policy file."""
    import time

    from ..inference import load_inference_policy, read_policy_file
    from ..presets import preset_from_dict
    from ..twin.demos import DirectRecorder
    from ..twin.evaluate import evaluate_policy, in_range_yaw_seeds
    from .rollouts import load_rollouts, save_rollouts, summarize
    from .training_runs import (
        encoder_summary,
        fit_ratios,
        recipe_differences,
        resolve_run,
        run_policy,
        trained_steps,
        training_fit,
        training_recipe,
        under_fit,
    )

    names = [run_name(p, n) for p in POLICIES for n in counts]
    run_dirs = {name: resolve_run(runs_dir / name) for name in names}
    recipes = {name: training_recipe(run_dirs[name]) for name in names}
    differences = recipe_differences(recipes)
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
    summaries, encoders, rec = {}, {}, None
    try:
        for name in names:
            policy_file = run_policy(runs_dir / name, out / name)
            settings = {
                "seeds": seeds,
                "max_duration_s": max_duration_s,
                "latency_s": latency_s,
                "policy_sha256_16": file_digest(policy_file),
            }
            cache = out / name / "rollouts.json"
            done = load_rollouts(cache, settings)
            if done is None:
                rec = rec or DirectRecorder(cfg, lab)
                done = evaluate_policy(
                    load_inference_policy(policy_file, device=device),
                    cfg,
                    lab,
                    seeds,
                    max_duration_s,
                    recorder=rec,
                    latency_s=latency_s,
                    log=lambda s, name=name: log(f"[{name}] {s}"),
                )
                cache.parent.mkdir(parents=True, exist_ok=True)
                save_rollouts(cache, done, settings)
            else:
                log(f"[{name}] {len(done)} roll-outs reused from {cache}")
            summaries[name] = summarize(done)
            config, _ = read_policy_file(policy_file)
            encoders[name] = encoder_summary(config["policy"], preset_from_dict(config["preset"]))
    finally:
        if rec is not None:
            rec.close()
    table = success_table({name: s["success"] for name, s in summaries.items()}, counts)
    recipe = recipes[names[0]] or {}
    note = ", ".join(
        f"{k} {recipe[k]}" for k in ("preset", "schedule_steps", "batch_size", "noise_repeats", "lr") if k in recipe
    )
    plot = plot_success(table, episodes, out / "success_vs_demos.png", note)
    return {
        "bench": "demos",
        "success": table,
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
        "max_duration_s": max_duration_s,
        "latency_budget_ms": round(latency_s * 1000, 1),
        "device": device,
        "plot": str(plot),
        "minutes": {"eval": round((time.monotonic() - t0) / 60, 1)},
    }
