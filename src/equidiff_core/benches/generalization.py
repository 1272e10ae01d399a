"""EquiDiff against two non-equivariant baselines on unseen object yaw (``equidiff bench generalization``).

Records narrow-yaw demos (or reuses them), trains EquiDiff, the baseline and the baseline with rotation
augmentation side by side with one recipe (``equidiff train`` runs, ``training_runs``), then gates and
rolls them out in-process on the sim clock: the training-fit gate, in-range scenes, then unseen yaw. The
command's help text describes the protocol and its exit codes; ``run_generalization`` takes its
``GeneralizationSettings`` and returns the bench's JSON line as a dict, or raises ``BenchError``; its
progress goes to this module's logger.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from equidiff_core.benches import BenchError
from equidiff_core.benches.demo_sets import count_demos, demos_off_range, ensure_demos
from equidiff_core.benches.rollouts import cached_rollouts, policy_digest, summarize
from equidiff_core.benches.stats import paired_comparison, paired_outcomes
from equidiff_core.benches.training_runs import (
    Recipe,
    TrainRunError,
    encoder_summary,
    fit_ratios,
    recipe_differences,
    run_policy,
    start_run,
    trained_steps,
    training_fit,
    training_recipe,
    under_fit,
    wait_for_runs,
)
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.runtime.output_files import write_output_text
from equidiff_core.twin.config import load_twin_job_configs
from equidiff_core.twin.demos import DirectRecorder
from equidiff_core.twin.evaluate import evaluate_policy
from equidiff_core.twin.yaw_range import in_range_yaw_seeds, unseen_yaw_seeds, yaw_breakdown

# The three policies compared, in the order they are reported: EquiDiff (Vo), DiffPo-C (Vo)
# and DiffPo-C (Vo) with rotation augmentation ("CNN + Aug" in the paper's appendix).
POLICIES = ("equidiff", "baseline", "baseline_aug")

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class GeneralizationSettings:
    """``equidiff bench generalization``'s settings: its flags, same names (the command's help says more)."""

    recipe: Recipe  # what every training shares: preset, steps (--train-steps), batch, lr, seed, device, ...
    demos: int  # narrow-yaw demos recorded for the training
    eval_episodes: int  # unseen-yaw scenes per policy
    in_range_episodes: int  # scenes per policy inside the training range, rolled out first (0: none)
    train_yaw: tuple[float, float]  # the demos' block yaw range, degrees
    rotation_aug: str  # training rotation augmentation of equidiff and baseline
    baseline_aug: str  # rotation augmentation of baseline_aug
    min_in_range: float  # the in-range gate: fraction of the in-range scenes every policy must solve (0: no gate)
    max_fit_ratio: float  # the training-fit gate: action error at most this times EquiDiff's (0: no gate)
    policies: tuple[str, ...]  # the POLICIES to train now (the others must already be in ``out``)
    out: Path | None  # work directory (None: runs/bench_generalization_<time>)
    demos_dir: Path | None  # demos recorded earlier (None: record them into ``out``)
    trained: Path | None  # roll out DIR/<policy> trained elsewhere instead of recording and training
    max_duration: float  # sim seconds per roll-out
    latency_ms: float  # each chunk takes effect this long after its observation
    twin_config: Path | None  # twin.yaml (None: the installed one); lab.yaml is the recipe's

    def quick(self) -> GeneralizationSettings:
        """The plumbing check (``--quick``): 4 demos, 30 steps of tiny, one short roll-out per policy and stage,
        no gates (no policy acts after 30 steps: the gates would stop every quick run)."""
        return dataclasses.replace(
            self,
            recipe=dataclasses.replace(self.recipe, steps=30, preset="tiny"),
            demos=4,
            eval_episodes=1,
            min_in_range=0.0,
            max_fit_ratio=0.0,
            in_range_episodes=min(self.in_range_episodes, 1),
            max_duration=min(self.max_duration, 6.0),  # a few chunks each: enough to test the plumbing
        )


def _recipe(name: str, settings: GeneralizationSettings) -> tuple[str, str]:
    """``equidiff train``'s --policy and --rotation-aug for one of POLICIES."""
    if name == "baseline_aug":
        return "baseline", settings.baseline_aug
    return name, settings.rotation_aug


def _start_training(
    name: str, bags: Path, out: Path, settings: GeneralizationSettings, threads: int
) -> subprocess.Popen:
    """The ``equidiff train`` run for one of POLICIES in the background, its output in ``out/train.log``."""
    policy, rotation_aug = _recipe(name, settings)
    spec = settings.recipe.train_spec(policy, rotation_aug, [bags], out)
    logger.info(f"[bench] training {name}: {spec.settings_text()}")
    return start_run(spec, threads)


def _train_all(demos_dir: Path, out: Path, settings: GeneralizationSettings) -> dict[str, Path]:
    """The policies at the same time, the CPU cores shared out (torch's intra-op threads scale
    poorly on few cores). On CUDA they share the GPU.

    A failing run stops the others within 10 s (their checkpoints and ``train.log`` stay), so an
    error is not held back until the longest run ends; every run that failed is reported."""
    names = [name for name in POLICIES if name in settings.policies]
    threads = max(1, (os.cpu_count() or 2) // len(names))
    # train stops itself at --max-minutes and exports; this deadline is only a backstop
    deadline = (
        None if settings.recipe.max_minutes is None else time.monotonic() + settings.recipe.max_minutes * 60 + 600
    )
    runs = {name: _start_training(name, demos_dir, out / name, settings, threads) for name in names}
    wait_for_runs(runs, {name: out / name for name in names}, deadline)
    return {name: out / name / "policy.pt" for name in runs}


def run_generalization(settings: GeneralizationSettings) -> dict:
    """The whole bench: its JSON line (also in OUT/result.json once rolled out). A stopped bench returns too:
    ``under_fit`` names the policies the training-fit gate stopped (nothing rolled out), ``failed_in_range``
    those the in-range gate stopped (not rolled out at unseen yaw), ``pending`` the policies still to train.
    BenchError for settings or inputs it cannot run with (exit status 2) or a failed training (1)."""
    if settings.eval_episodes < 1 or settings.in_range_episodes < 0 or not 0.0 <= settings.min_in_range <= 1.0:
        raise BenchError(
            "need --eval-episodes >= 1, --in-range-episodes >= 0 and --min-in-range in [0, 1]",
            2,
        )
    if settings.recipe.device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
        settings = dataclasses.replace(settings, recipe=dataclasses.replace(settings.recipe, device=device))
    t_start = time.monotonic()
    configs = load_twin_job_configs(settings.recipe.lab_config, settings.twin_config)
    lab, cfg = configs.lab, configs.twin
    train_cfg = cfg.with_yaw_range(tuple(settings.train_yaw))
    out = settings.out or Path("runs") / time.strftime("bench_generalization_%Y%m%d_%H%M%S")
    out.mkdir(parents=True, exist_ok=True)

    if settings.trained is not None:
        try:
            policies, steps_done = _trained_policies(settings.trained, out)
        except FileNotFoundError as err:
            raise BenchError(str(err), 2) from err
        n_demos = (
            count_demos(settings.demos_dir) if settings.demos_dir else _trained_demos(settings.trained / "equidiff")
        )
        run_dirs = {name: settings.trained / name for name in POLICIES}
        return _evaluate(settings, cfg, lab, out, policies, steps_done, n_demos, {}, run_dirs)
    demos_dir, n_demos = ensure_demos(
        settings.demos_dir, out, settings.demos, train_cfg, lab, settings.recipe.seed, log=logger.info
    )
    wrong, unrecorded = demos_off_range(demos_dir, tuple(settings.train_yaw))
    if wrong:  # demos of another yaw range would measure something else: refuse before any training
        raise BenchError(
            f"{len(wrong)} demos in {demos_dir} were drawn from another block "
            f"yaw range than --train-yaw {settings.train_yaw[0]:g} {settings.train_yaw[1]:g}, e.g. {wrong[0]}",
            2,
        )
    if unrecorded:
        logger.info(
            f"[bench] {unrecorded} demos in {demos_dir} do not record the yaw range they were drawn from "
            "(recorded before episodes kept it): make sure it is --train-yaw"
        )
    t_demos = time.monotonic()

    try:
        trained_now = _train_all(demos_dir, out, settings)
    except TrainRunError as err:  # the demos stay: a rerun need not record them again
        raise BenchError(f"{err}\nthe demos are kept: rerun with --demos-dir {demos_dir}") from err
    t_train = time.monotonic()
    minutes = {"demos": round((t_demos - t_start) / 60, 1), "train": round((t_train - t_demos) / 60, 1)}
    pending = [name for name in POLICIES if not (out / name / "policy.pt").is_file()]
    if pending:  # trained in parts (one machine-session each on a small CPU): roll out once all are in --out
        result = {
            "trained": list(trained_now),
            "pending": pending,
            "train_steps_by_policy": {name: trained_steps(out / name) for name in trained_now},
            "demos": n_demos,
            "out": str(out),
            "next": f"equidiff bench generalization --out {out} --demos-dir {demos_dir} --policies "
            f"{' '.join(pending)} with this call's recipe flags",
            "minutes": minutes,
        }
        return result
    policies = {name: out / name / "policy.pt" for name in POLICIES}
    steps_done = {name: trained_steps(out / name) or settings.recipe.steps for name in policies}
    return _evaluate(
        settings,
        cfg,
        lab,
        out,
        policies,
        steps_done,
        n_demos,
        minutes,
    )


def _trained_policies(folder: Path, out: Path) -> tuple[dict, dict]:
    """Policies and steps trained of a finished run laid out like this bench's own (DIR/<policy>/policy.pt,
    or a committed DIR/<policy>/weights.ckpt exported into OUT/<policy>/)."""
    policies = {}
    for name in POLICIES:
        try:
            policies[name] = run_policy(folder / name, out / name)
        except FileNotFoundError as err:
            needed = ", ".join(f"DIR/{name}/policy.pt" for name in POLICIES)
            raise FileNotFoundError(f"{err}: --trained needs {needed} (or weights.ckpt)") from None
    return policies, {name: trained_steps(folder / name) for name in policies}


def _trained_demos(run_dir: Path) -> int | None:
    """Episodes the run trained on, from ``equidiff train``'s saved split (None if not recorded)."""
    try:
        split = json.loads((run_dir / "split.json").read_text())
        return len(split["train"]) + len(split.get("val", []))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def in_range_failures(in_range_success: dict[str, float | None], min_in_range: float) -> list[str]:
    """The policies that solved fewer than ``min_in_range`` of the in-range scenes (none rolled out: none)."""
    return [name for name, rate in in_range_success.items() if rate is not None and rate < min_in_range]


def _paired_against_equidiff(by_policy: dict[str, dict[int, bool]]) -> dict:
    """EquiDiff against each other policy rolled out on the same scenes (none when EquiDiff was not)."""
    if "equidiff" not in by_policy:
        return {}
    return {
        f"equidiff_vs_{name}": paired_comparison(*paired_outcomes(by_policy["equidiff"], outcomes))
        for name, outcomes in by_policy.items()
        if name != "equidiff"
    }


def _verdict(
    failed: list[str], success: dict, settings: GeneralizationSettings, versus_baseline: dict | None = None
) -> str:
    if failed:
        return (
            f"{', '.join(failed)} solved fewer than {settings.min_in_range:.0%} of the in-range scenes: the training "
            "budget is too small for this comparison (more demos, steps or a GPU); not rolled out at unseen yaw"
        )
    lead = round(100 * (success["equidiff"] - success["baseline"]))
    verdict = (
        f"unseen yaw: equidiff {success['equidiff']:.0%}, baseline {success['baseline']:.0%}, "
        f"baseline_aug {success['baseline_aug']:.0%} (equidiff {lead:+d} points over baseline"
    )
    if versus_baseline and versus_baseline["ci95"] is not None:
        low, high = versus_baseline["ci95"]
        verdict += (
            f", 95 % interval {100 * low:+.0f} to {100 * high:+.0f}, McNemar p = {versus_baseline['p_value']:.3g}: "
            + ("more than chance" if versus_baseline["significant"] else "not distinguishable from chance")
        )
    return verdict + ")"


def _report_under_fit(
    settings: GeneralizationSettings,
    out: Path,
    underfit: list,
    fits: dict,
    recipes: dict,
    steps_done: dict,
    n_demos,
    minutes,
) -> dict:
    """The JSON line of a bench stopped at the training-fit gate (nothing rolled out)."""
    ratios = fit_ratios(fits, "equidiff")
    verdict = (
        "under-fit: "
        + ", ".join(f"{name} ({ratios[name]}x EquiDiff's)" for name in underfit)
        + f": the DDIM action error on a policy's own training samples is more than {settings.max_fit_ratio:g}x "
        f"EquiDiff's ({fits['equidiff']['pos_err_m'] * 100:.1f} cm), so it has not fit its demos and its "
        "roll-outs would measure its network or training, not generalisation; nothing rolled out"
    )
    result = {
        **{f"{name}_success": None for name in POLICIES},
        **{f"{name}_in_range_success": None for name in POLICIES},
        "failed_in_range": [],
        "under_fit": underfit,
        "verdict": verdict,
        "equidiff_minus_baseline_points": None,
        "goal_met": None,
        "train_fit": fits,
        "train_fit_vs_equidiff": ratios,
        "max_fit_ratio": settings.max_fit_ratio,
        "demos": n_demos,
        "train_steps_by_policy": steps_done,
        "training_recipes": recipes,
        "minutes": minutes,
    }
    write_output_text(out / "result.json", json.dumps(result) + "\n", force=True)  # the bench's own, rewritten
    return result


def _evaluate(
    settings: GeneralizationSettings,
    cfg,
    lab,
    out: Path,
    policies: dict,
    steps_done: dict,
    n_demos,
    minutes: dict,
    run_dirs: dict | None = None,
) -> dict:
    """The training-fit gate, in-range rollouts of every policy, the in-range gate, then (if both passed)
    the unseen-yaw rollouts; the JSON line (``under_fit`` or ``failed_in_range`` name the policies a gate
    stopped)."""
    run_dirs = run_dirs or {name: path.parent for name, path in policies.items()}
    recipes = {name: training_recipe(run_dirs[name]) for name in policies}
    recipe = settings.recipe
    differences = recipe_differences(recipes, {name: recipe.lr_of(_recipe(name, settings)[0]) for name in policies})
    if differences:
        raise BenchError(
            "the policies were not trained with the same recipe ("
            + "; ".join(differences)
            + "): retrain the odd ones out",
            2,
        )
    # the second gate, before any roll-out: a policy that has not fit its own demos is under-fit
    fits = {name: training_fit(run_dirs[name]) for name in policies}
    underfit = under_fit(fits, "equidiff", settings.max_fit_ratio)
    if underfit:
        return _report_under_fit(settings, out, underfit, fits, recipes, steps_done, n_demos, minutes)
    t_eval = time.monotonic()
    seeds = unseen_yaw_seeds(cfg, tuple(settings.train_yaw), settings.eval_episodes)
    in_range = in_range_yaw_seeds(cfg, tuple(settings.train_yaw), settings.in_range_episodes)
    loaded = {name: load_inference_policy(path, device=settings.recipe.device) for name, path in policies.items()}
    stages: dict[str, dict] = {name: {} for name in policies}
    outcomes: dict[str, dict[str, dict[int, bool]]] = {
        "in_range": {},
        "unseen": {},
    }  # label -> policy -> seed -> solved
    intervals: dict[str, dict[str, list | None]] = {"in_range": {}, "unseen": {}}
    by_yaw: dict[str, dict] = {}
    rec = DirectRecorder(cfg, lab)

    def roll_out(name: str, label: str, scene_seeds: list[int]) -> float | None:
        if not scene_seeds:
            return None
        rollout_settings = {
            "seeds": scene_seeds,
            "max_duration_s": settings.max_duration,
            "latency_s": settings.latency_ms / 1000,
            "policy_digest": policy_digest(policies[name]),
        }
        episodes = cached_rollouts(
            out / name / f"rollouts_{label}.json",
            rollout_settings,
            lambda: evaluate_policy(
                loaded[name],
                cfg,
                lab,
                scene_seeds,
                settings.max_duration,
                recorder=rec,
                latency_s=settings.latency_ms / 1000,
                log=lambda s: logger.info(f"[{name}, {label}] {s}"),
            ),
            lambda s: logger.info(f"[{name}, {label}] {s}"),
        )
        summary = summarize(episodes)  # how far failures got: reached the block, lifted it, closest TCP
        outcomes[label][name] = {e.seed: e.success for e in episodes}
        intervals[label][name] = summary["success_ci95"]
        stages[name][label] = {k: summary[k] for k in ("reached", "lifted", "median_closest_to_block_m")}
        if label == "unseen":
            by_yaw[name] = yaw_breakdown(episodes, tuple(settings.train_yaw))
        return summary["success"]

    try:
        in_range_success = {name: roll_out(name, "in_range", in_range) for name in policies}
        failed = in_range_failures(in_range_success, settings.min_in_range)
        success = {name: None if failed else roll_out(name, "unseen", seeds) for name in policies}
    finally:
        rec.close()
    t_end = time.monotonic()
    lead = None if failed else round(100 * (success["equidiff"] - success["baseline"]), 1)
    paired = {label: _paired_against_equidiff(by_policy) for label, by_policy in outcomes.items()}
    result = {
        **{f"{name}_success": success[name] for name in policies},  # unseen yaw; null when not rolled out
        **{f"{name}_success_ci95": intervals["unseen"].get(name) for name in policies},
        **{f"{name}_in_range_success": in_range_success[name] for name in policies},
        **{f"{name}_in_range_success_ci95": intervals["in_range"].get(name) for name in policies},
        "failed_in_range": failed,
        "verdict": _verdict(failed, success, settings, paired["unseen"].get("equidiff_vs_baseline")),
        "equidiff_minus_baseline_points": lead,
        # each baseline against EquiDiff on the same scenes: difference, paired 95 % interval, McNemar p
        "paired": paired,
        # the issue's goal for the twin: EquiDiff >= 80 % at unseen yaw, >= 30 points above the baseline
        "goal_met": None if failed else bool(success["equidiff"] >= 0.8 and lead >= 30),
        "min_in_range": settings.min_in_range,
        "in_range_episodes": settings.in_range_episodes,
        "latency_budget_ms": settings.latency_ms,
        "stages": stages,
        # unseen-yaw success by what C4 (offset modulo 90 deg) and C8 (modulo 45 deg) map into the range
        "unseen_by_yaw": by_yaw,
        "train_fit": fits,
        "train_fit_vs_equidiff": fit_ratios(fits, "equidiff"),
        "under_fit": [],
        "max_fit_ratio": settings.max_fit_ratio,
        "demos": n_demos,
        "train_steps": min((v for v in steps_done.values() if v is not None), default=None),
        "train_steps_by_policy": steps_done,  # differ when --max-minutes stopped the slower ones first
        "eval_episodes": settings.eval_episodes,
        "train_yaw_range_deg": list(settings.train_yaw),
        "eval_yaw": f"block yaw >= 15 deg outside the training range, modulo 180 deg (seeds {seeds[0]}..)",
        "preset": "/".join(sorted({p.preset.name for p in loaded.values()})),  # as the policies were trained
        "rotation_aug": {name: p.preset.rotation_aug for name, p in loaded.items()},
        "encoders": {name: encoder_summary(p.name, p.preset) for name, p in loaded.items()},
        "device": settings.recipe.device,  # of the evaluation; the training's is in training_recipes
        "training_recipes": recipes,
        "minutes": {**minutes, "eval": round((t_end - t_eval) / 60, 1)},
    }
    write_output_text(out / "result.json", json.dumps(result) + "\n", force=True)  # the bench's own, rewritten
    return result
