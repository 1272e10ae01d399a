"""``equidiff bench corrections``: one round of the corrections loop, measured in the twin (docs/corrections.md).

1. The start policy (``bench demos``' 10-demo EquiDiff) is rolled out on ``rollouts`` in-range scenes (seeds from
   ``ROUND_SEEDS_FROM``: disjoint from the held-out scenes and the demos') with takeovers
   (``twin.corrections``): the scripted expert takes over when it judges the episode lost. Every episode is
   recorded and kept (``OUT/round/``; ``round.json`` lists them, so an interrupted round goes on).
2. ``equidiff train --init-from`` fine-tunes the start policy on its demos plus every episode of the round
   (operator frames weigh ``intervention_weight``, the policy's ``policy_frame_weight``), in its own process on
   one thread, into ``OUT/corrected`` (resumed from its last checkpoint when interrupted).
3. The start policy, the corrected one and the reference (``bench demos``' 20-demo EquiDiff) are rolled out on
   the same held-out in-range scenes ``bench demos`` uses (``OUT/<name>/rollouts.json``, its layout: a
   ``bench demos`` roll-out file with the same settings, copied there, is reused).

The result counts the expert-labelled frames each policy trained on (a demo's frames, the operator's frames of
the round) and draws success against them (``success_vs_expert_frames.png``), with ``bench demos``' curve when
its result.json is given.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from ..data.bags import read_episode, read_meta
from ..data.dataset import find_episodes, load_episodes
from ..data.episode_arrays import DatasetConfig
from ..data.segments import FrameSource, frame_sources
from ..policy.doubt import DEFAULT_SIGNAL, DoubtGate, calibrate_doubt
from ..policy.inference import load_inference_policy
from ..runtime.output_files import refuse_existing, staged_output, write_output_text
from ..training.job import TrainingSpec
from ..twin.config import load_twin_job_configs
from ..twin.corrections import CorrectedEpisode, LostRule, corrected_rollouts, trigger_kind
from ..twin.demos import DirectRecorder
from ..twin.evaluate import evaluate_policy
from ..twin.expert import run_direct_episode
from ..twin.sim import DirectSim
from ..twin.yaw_range import in_range_yaw_seeds
from ..wire.topics import TOPIC_POLICY_STATE, TOPIC_TELEOP_ACTIVE, TOPIC_VOXELS
from . import BenchError
from .demo_sets import demos_off_range, ensure_demos, nested_subsets
from .doubt import auroc
from .figures import save_with_note
from .rollouts import policy_digest, resumable_rollouts, summarize
from .stats import paired_comparison, paired_outcomes, success_rate
from .training_runs import SLIM_CHECKPOINT, TrainRunError, resolve_run, run_policy, start_run, wait_for_runs

logger = logging.getLogger(__name__)

# The round's scenes: in-range seeds from here on (the held-out ones start at 20 000 000, the demos' at 0).
ROUND_SEEDS_FROM = 30_000_000
NO_DOUBT = "the round's roll-outs were made before the doubt signal was logged: roll the round out into a new --out"
NO_GATE = "no --gate-quantile: the alarms were not counted (the start policy needs a doubt calibration)"


@dataclass(frozen=True)
class FineTune:
    """The fine-tuning recipe (docs/corrections.md): fewer steps from the start policy's weights, one thread. The
    defaults are the measured round's (docs/results/corrections.md); 1000 steps at 1e-4 with the operator's frames
    weighing 1 did not improve the start policy."""

    steps: int = 2500
    batch_size: int = 8
    lr: float = 3e-4
    warmup_steps: int = 50
    noise_repeats: int = 4
    ema: bool = True
    seed: int = 0
    max_minutes: float = 28.0  # the training alone: with loading and export the fine-tuning stays within 30
    intervention_weight: float = 2.0
    policy_frame_weight: float = 0.0


@dataclass(frozen=True)
class CorrectionsSettings:
    """``equidiff bench corrections``'s settings: its flags, same names."""

    out: Path
    start: Path  # the start run (bench demos' equidiff_10: weights.ckpt or last.ckpt, run.json)
    reference: Path  # the run with more demos to beat (bench demos' equidiff_20)
    demos_dir: Path | None  # the demos (name order = seed order); None: recorded into OUT/demos
    start_demos: int = 10  # the start policy's demos: the first N of demos_dir
    reference_demos: int = 20
    rollouts: int = 12  # scenes of the round: the measured round's size (docs/results/corrections.md)
    eval_episodes: int = 50
    fine_tune: FineTune = field(default_factory=FineTune)
    rule: LostRule = field(default_factory=LostRule)
    train_yaw: tuple[float, float] = (-15.0, 15.0)
    max_duration: float = 30.0
    latency_ms: float = 100.0
    demos_result: Path | None = None  # bench demos' result.json: its EquiDiff curve on the plot
    plot: Path | None = None
    lab_config: Path | None = None
    twin_config: Path | None = None
    force: bool = False
    # the doubt gate at this quantile of the start policy's calibration (equidiff check doubt) counts its alarms
    # on the round; with gate_takes_over its first alarm hands the arm to the expert. None: no gate
    gate_quantile: float | None = None
    gate_takes_over: bool = False
    round_only: bool = False  # stop after the round: its takeovers and the gate's quality, no fine-tuning


def episode_frames(bag: Path) -> dict[str, int]:
    """Observation frames of a bag by source (``data.segments``): a demo's are all ``demo``."""
    episode = read_episode(bag, topics=(TOPIC_VOXELS, TOPIC_POLICY_STATE, TOPIC_TELEOP_ACTIVE))
    sources = frame_sources(episode, np.sort(episode[TOPIC_VOXELS].header_ns()))
    counts = np.bincount(sources.astype(np.intp), minlength=len(FrameSource))
    return {s.name.lower(): int(counts[s]) for s in FrameSource}


def expert_frames_of_seed(cfg, seed: int, observation_hz: float) -> int:
    """A demo's frame count estimated without recording it: the scripted expert run on the seed's scene with
    no cameras (``expert.run_direct_episode``), its time to success plus the success hold at the observation
    rate (a recorded demo has one frame more than whole periods)."""
    sim = DirectSim(cfg)
    try:
        result = run_direct_episode(sim, seed, cfg)
    finally:
        sim.close()
    return int((result.duration_s + cfg.success.hold_s) * observation_hz) + 1


def demo_frames(demos: list[Path], count: int, cfg, observation_hz: float, log=logger.info) -> list[tuple[int, bool]]:
    """(expert frames, counted) of each of the first ``count`` demos: counted in the bags there are, estimated
    (``expert_frames_of_seed``) for the seeds after them, which the demos' name order continues."""
    rows = [(episode_frames(b)["demo"], True) for b in demos[:count]]
    missing = count - len(rows)
    if missing > 0:
        seeds = [s for s in (read_meta(b).seed for b in demos) if s is not None]
        after = max(seeds) + 1 if seeds else 0
        log(f"[corrections] estimating the frames of {missing} demos not recorded here (seeds {after}..)")
        rows += [(expert_frames_of_seed(cfg, after + i, observation_hz), False) for i in range(missing)]
    return rows


def frames_by_count(rows: list[tuple[int, bool]], counts) -> dict[int, dict]:
    """{count: expert frames of the first ``count`` demos, and how many were counted and estimated}."""
    return {
        n: {
            "frames": sum(f for f, _ in rows[:n]),
            "counted": sum(1 for _, c in rows[:n] if c),
            "estimated": sum(1 for _, c in rows[:n] if not c),
        }
        for n in sorted(counts)
    }


def round_summary(episodes: list[CorrectedEpisode], frames: list[dict[str, int]]) -> dict:
    """The round in figures: outcomes, takeovers and why, frames by source."""
    n = len(episodes)
    triggers: dict[str, int] = {}
    for e in episodes:
        if e.trigger:
            kind = trigger_kind(e.trigger)
            triggers[kind] = triggers.get(kind, 0) + 1
    total = {s.name.lower(): sum(f[s.name.lower()] for f in frames) for s in FrameSource}
    taken = [e for e in episodes if e.trigger]
    return {
        "episodes": n,
        "policy_success": success_rate([e.policy_success for e in episodes]),
        "takeovers": len(taken),
        "takeover_success": success_rate([e.success for e in taken]),
        "success_with_takeovers": success_rate([e.success for e in episodes]),
        "triggers": dict(sorted(triggers.items())),
        "median_takeover_s": round(float(np.median([e.takeover_s for e in taken])), 1) if taken else None,
        "frames": total,
    }


def gate_quality(episodes: list[CorrectedEpisode]) -> dict:
    """The doubt signal and gate on the round's roll-outs (docs/corrections.md): the AUROC of each roll-out's
    largest doubt for the policy failing it; with a gate, the failures it flagged while still recoverable
    (its first alarm before the expert judged the episode lost, or its own takeover) and its alarms per
    roll-out the policy solved. Meant for a gate that only watches: one that takes over decides outcomes."""
    measured = [e for e in episodes if e.max_doubt_m is not None]
    gated = [e for e in measured if e.alarms is not None]
    failures = [e for e in gated if not e.policy_success]
    successes = [e for e in gated if e.policy_success]

    def early(e: CorrectedEpisode) -> bool:
        if e.first_alarm_s is None:
            return False
        return e.trigger.startswith("gate:") or e.takeover_s is None or e.first_alarm_s < e.takeover_s

    return {
        "auroc": auroc(
            [e.max_doubt_m for e in measured if not e.policy_success],
            [e.max_doubt_m for e in measured if e.policy_success],
        ),
        "episodes": len(measured),
        "failures_flagged_recoverable": success_rate([early(e) for e in failures]) if failures else None,
        "false_alarms_per_success": round(sum(e.alarms for e in successes) / len(successes), 3) if successes else None,
        "gate_takeovers": sum(1 for e in episodes if e.trigger.startswith("gate:")),
        "reason": NO_DOUBT if not measured else (NO_GATE if not gated else None),
    }


def plot_corrections(points: dict[str, dict], curve: dict[int, dict] | None, path: Path, note: str = "") -> Path:
    """PNG of success (%) against the expert frames a policy trained on: ``points`` {label: {"frames", "rate",
    "ci95"}} (start, corrected, reference), ``curve`` {demos: the same} (fresh demos, ``bench demos``)."""
    fig = Figure(figsize=(5.4, 3.8), dpi=120)
    ax = fig.subplots()

    def bars(rows):
        ys = [100 * r["rate"] for r in rows]
        return ys, [
            [y - 100 * r["ci95"][0] if r.get("ci95") else 0.0 for y, r in zip(ys, rows, strict=True)],
            [100 * r["ci95"][1] - y if r.get("ci95") else 0.0 for y, r in zip(ys, rows, strict=True)],
        ]

    if curve:
        rows = [curve[n] for n in sorted(curve)]
        ys, err = bars(rows)
        ax.errorbar(
            [r["frames"] for r in rows],
            ys,
            yerr=err,
            marker="o",
            capsize=3,
            color="tab:blue",
            alpha=0.8,
            label="fresh demos (bench demos)",
        )
        for n, r, y in zip(sorted(curve), rows, ys, strict=True):
            ax.annotate(f"{n} demos", (r["frames"], y), textcoords="offset points", xytext=(6, -10), fontsize=7)
    markers = {"start": ("s", "tab:gray"), "corrected": ("*", "tab:red"), "reference": ("D", "tab:green")}
    for label, row in points.items():
        if row.get("rate") is None:
            continue
        ys, err = bars([row])
        marker, colour = markers.get(label, ("o", "black"))
        ax.errorbar(
            [row["frames"]],
            ys,
            yerr=err,
            marker=marker,
            markersize=9 if marker == "*" else 6,
            capsize=3,
            color=colour,
            linestyle="none",
            label=f"{label} ({row.get('name', label)})",
        )
        ax.annotate(
            f"{ys[0]:.0f}", (row["frames"], ys[0]), textcoords="offset points", xytext=(8, 0), va="center", fontsize=8
        )
    if "start" in points and "corrected" in points and points["corrected"].get("rate") is not None:
        s, c = points["start"], points["corrected"]
        ax.annotate(
            "",
            (c["frames"], 100 * c["rate"]),
            (s["frames"], 100 * s["rate"]),
            arrowprops={"arrowstyle": "->", "color": "tab:red", "alpha": 0.6},
        )
    ax.set_xlabel("expert-labelled frames trained on (demo + operator)")
    ax.set_ylabel("success, % of held-out scenes (95 % interval)")
    ax.set_ylim(-5, 105)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=7)
    ax.set_title("Corrections against fresh demos (twin, in-range yaw)", fontsize=9)
    return save_with_note(fig, path, note)


def demos_curve(result_path: Path, frames_by_count: dict[int, int]) -> dict[int, dict]:
    """``bench demos``' EquiDiff success per demo count (its result.json) at the frames those demos hold."""
    result = json.loads(result_path.read_text())
    success, ci = result["success"].get("equidiff", {}), result["success_ci95"].get("equidiff", {})
    return {
        n: {"frames": frames_by_count[n], "rate": success[str(n)], "ci95": ci.get(str(n))}
        for n in sorted(frames_by_count)
        if success.get(str(n)) is not None
    }


def _round(
    settings: CorrectionsSettings, cfg, lab, start_policy: Path, start_demos: list[Path], log
) -> list[CorrectedEpisode]:
    """The round's corrected roll-outs, resumed from ``OUT/round.json`` (bags of an episode cut short, not
    listed there, are moved aside, never trained on)."""
    out = settings.out
    bags = out / "round"
    seeds = in_range_yaw_seeds(cfg, settings.train_yaw, settings.rollouts, start=ROUND_SEEDS_FROM)
    record = out / "round.json"
    round_settings = {
        "policy_digest": policy_digest(start_policy),
        "max_duration_s": settings.max_duration,
        "latency_s": settings.latency_ms / 1000,
        "rule": asdict(settings.rule),
    }
    if settings.gate_quantile is not None:  # (a round without a gate keeps its settings as they were)
        round_settings["gate"] = {"quantile": settings.gate_quantile, "takes_over": settings.gate_takes_over}
    done: dict[int, CorrectedEpisode] = {}
    if record.is_file():
        saved = json.loads(record.read_text())
        if saved["settings"] != json.loads(json.dumps(round_settings)):
            raise BenchError(f"{record} was rolled out with other settings: use another --out", 2)
        done = {e["seed"]: CorrectedEpisode(**e) for e in saved["episodes"]}
    listed = {Path(e.bag).name for e in done.values()}
    for stray in find_episodes([bags]) if bags.is_dir() else []:
        if stray.name not in listed:
            aside = out / "round_interrupted"
            aside.mkdir(exist_ok=True)
            shutil.move(str(stray), str(aside / stray.name))
            log(f"[corrections] {stray.name} was cut short: moved to {aside}")
    todo = [s for s in seeds if s not in done]

    def save(episode: CorrectedEpisode) -> None:
        done[episode.seed] = episode
        rows = [asdict(done[s]) for s in seeds if s in done]
        write_output_text(record, json.dumps({"settings": round_settings, "episodes": rows}, indent=1), force=True)

    if todo:  # the start policy (and its gate) only where a scene is still to roll out
        policy = load_inference_policy(start_policy, device="cpu")
        gate = None
        if settings.gate_quantile is not None:
            calibration = policy.doubt_calibration
            if calibration is None:  # as `equidiff check doubt` would: the signal over the start policy's own demos
                demos, skipped = load_episodes(start_demos, DatasetConfig.for_lab(lab))
                if skipped or not demos:
                    raise BenchError(f"calibrating the doubt gate: demos unusable: {skipped[:1]}", 2)
                calibration = calibrate_doubt(policy, demos, DEFAULT_SIGNAL, 1, log=log)
            gate = DoubtGate(calibration, settings.gate_quantile, DEFAULT_SIGNAL, 1)
            log(
                f"[corrections] doubt gate at q{settings.gate_quantile:g} of {len(calibration.values_m)} demo frames: "
                f"{gate.threshold_m * 1000:.1f} mm"
                + (" (it takes over)" if settings.gate_takes_over else " (watching)")
            )
        log(f"[corrections] rolling out {len(todo)} of {len(seeds)} round scenes with takeovers into {bags}")
        corrected_rollouts(
            policy,
            cfg,
            lab,
            todo,
            bags,
            settings.rule,
            settings.max_duration,
            settings.latency_ms / 1000,
            gate=gate,
            gate_takes_over=settings.gate_takes_over,
            on_episode=save,
            log=log,
        )
    return [done[s] for s in seeds]


def _fine_tune(settings: CorrectionsSettings, start_weights: Path, bags: list[Path], log) -> tuple[Path, dict]:
    """``OUT/corrected``: the start policy fine-tuned on ``bags`` (resumed when interrupted); its run folder and
    the wall time it took (``fine_tune.json``, kept from the call that trained)."""
    ft = settings.fine_tune
    run_dir = settings.out / "corrected"
    timing = run_dir / "fine_tune.json"
    if (run_dir / "policy.pt").is_file() and timing.is_file():
        return run_dir, json.loads(timing.read_text())
    spec = TrainingSpec(
        bags=tuple(bags),
        out=run_dir,
        steps=ft.steps,
        batch_size=ft.batch_size,
        lr=ft.lr,
        warmup_steps=ft.warmup_steps,
        ema=ft.ema,
        noise_repeats=ft.noise_repeats,
        seed=ft.seed,
        device="cpu",
        val_fraction=0.0,
        eval_every=10**9,
        checkpoint_every=max(10, ft.steps // 4),
        max_minutes=ft.max_minutes,
        progress=False,
        resume=True,
        lab_config=settings.lab_config,
        init_from=start_weights,
        intervention_weight=ft.intervention_weight,
        policy_frame_weight=ft.policy_frame_weight,
    )
    log(f"[corrections] fine-tuning: {spec.settings_text()} (log {run_dir / 'train.log'})")
    before = json.loads(timing.read_text())["minutes"] if timing.is_file() else 0.0
    t0 = time.monotonic()
    try:
        wait_for_runs(
            {"corrected": start_run(spec, 1)}, {"corrected": run_dir}, time.monotonic() + ft.max_minutes * 60 + 900
        )
    except TrainRunError as err:
        raise BenchError(f"{err}\nrerun the same command to resume") from err
    minutes = round(before + (time.monotonic() - t0) / 60, 1)
    run = json.loads((run_dir / "run.json").read_text())
    summary = {
        "minutes": minutes,
        "steps": run.get("steps"),
        "threads": 1,
        "samples_by_source": run.get("samples_by_source"),
    }
    write_output_text(timing, json.dumps(summary), force=True)
    return run_dir, summary


def _paired(a: dict[int, bool], b: dict[int, bool]) -> dict | None:
    """``stats.paired_comparison`` of two policies' outcomes by scene (None for fewer than two shared scenes)."""
    x, y = paired_outcomes(a, b)
    return paired_comparison(x, y) if len(x) >= 2 else None


def run_corrections_bench(settings: CorrectionsSettings) -> dict:
    """The whole round (see the module doc): its JSON line as a dict (also OUT/result.json). BenchError for
    settings or inputs it cannot run with (2) or a failed training (1)."""
    if settings.rollouts < 1 or settings.eval_episodes < 1:
        raise BenchError("need --rollouts >= 1 and --eval-episodes >= 1", 2)
    if settings.plot is not None:
        refuse_existing(settings.plot, settings.force)
    for name, run in (("--start", settings.start), ("--reference", settings.reference)):
        if not any((resolve_run(run) / f).is_file() for f in (SLIM_CHECKPOINT, "last.ckpt")):
            raise BenchError(f"{name} {run}: no {SLIM_CHECKPOINT} or last.ckpt", 2)
    if settings.demos_result is not None and not settings.demos_result.is_file():
        raise BenchError(f"--demos-result {settings.demos_result}: no such file", 2)
    t_start = time.monotonic()
    configs = load_twin_job_configs(settings.lab_config, settings.twin_config)
    lab, cfg = configs.lab, configs.twin
    out = settings.out
    out.mkdir(parents=True, exist_ok=True)
    log = logger.info
    minutes: dict[str, float] = {}

    demo_cfg = cfg.with_yaw_range(tuple(settings.train_yaw))  # the demos' scenes
    demos_dir, _ = ensure_demos(settings.demos_dir, out, settings.start_demos, demo_cfg, lab, 0, log=log)
    wrong, _ = demos_off_range(demos_dir, tuple(settings.train_yaw))
    if wrong:
        raise BenchError(f"{len(wrong)} demos in {demos_dir} were drawn from another yaw range, e.g. {wrong[0]}", 2)
    all_demos = sorted(find_episodes([demos_dir]), key=lambda p: p.name)
    try:
        start_demos = nested_subsets(demos_dir, [settings.start_demos])[settings.start_demos]
    except ValueError as err:
        raise BenchError(str(err), 2) from err
    start_dir, reference_dir = resolve_run(settings.start), resolve_run(settings.reference)
    start_weights = next(start_dir / f for f in (SLIM_CHECKPOINT, "last.ckpt") if (start_dir / f).is_file())
    policies = {
        "start": run_policy(start_dir, out / "start"),
        "reference": run_policy(reference_dir, out / "reference"),
    }

    t = time.monotonic()
    episodes = _round(settings, cfg, lab, policies["start"], start_demos, log)
    minutes["round"] = round((time.monotonic() - t) / 60, 1)
    bags = [Path(e.bag) for e in episodes]
    frames = [episode_frames(b) for b in bags]

    if settings.round_only:
        return {
            "bench": "corrections",
            "round_only": True,
            "round": round_summary(episodes, frames),
            "round_episodes": [asdict(e) for e in episodes],
            "gate": gate_quality(episodes),
            "gate_settings": {"quantile": settings.gate_quantile, "takes_over": settings.gate_takes_over},
            "rule": asdict(settings.rule),
            "round_scenes": f"block yaw inside {list(settings.train_yaw)}, seeds {ROUND_SEEDS_FROM}..",
            "minutes": minutes,
        }
    run_dir, fine_tune = _fine_tune(settings, start_weights, [*start_demos, *bags], log)
    policies["corrected"] = run_dir / "policy.pt"

    seeds = in_range_yaw_seeds(cfg, settings.train_yaw, settings.eval_episodes)
    t = time.monotonic()
    rec = None
    rollouts = {}
    try:
        for name, policy_file in policies.items():
            eval_settings = {
                "seeds": seeds,
                "max_duration_s": settings.max_duration,
                "latency_s": settings.latency_ms / 1000,
                "policy_digest": policy_digest(policy_file),
            }
            policy = None

            def roll_one(seed: int, name=name, policy_file=policy_file):
                nonlocal rec, policy
                rec = rec or DirectRecorder(cfg, lab)
                policy = policy or load_inference_policy(policy_file, device="cpu")
                return evaluate_policy(
                    policy,
                    cfg,
                    lab,
                    [seed],
                    settings.max_duration,
                    recorder=rec,
                    latency_s=settings.latency_ms / 1000,
                    log=lambda s, name=name: log(f"[{name}] {s}"),
                )[0]

            rollouts[name] = resumable_rollouts(
                out / name / "rollouts.json", eval_settings, roll_one, lambda s, name=name: log(f"[{name}] {s}")
            )
    finally:
        if rec is not None:
            rec.close()
    minutes["eval"] = round((time.monotonic() - t) / 60, 1)

    observation_hz = lab.observation_hz
    t = time.monotonic()
    curve_counts = set()
    if settings.demos_result is not None:  # bench demos' counts: their frames too, for its curve
        curve_counts = {int(n) for n in json.loads(settings.demos_result.read_text())["success"].get("equidiff", {})}
    demo_counts = sorted({settings.start_demos, settings.reference_demos, *curve_counts})
    cache = out / "demo_frames.json"  # counting and estimating take minutes: kept for the next call
    cached = json.loads(cache.read_text()) if cache.is_file() else None
    key = {"demos": [str(p) for p in all_demos], "count": max(demo_counts)}
    if cached is not None and cached["key"] == key:
        rows = [tuple(r) for r in cached["rows"]]
    else:
        rows = demo_frames(all_demos, max(demo_counts), demo_cfg, observation_hz, log)
        write_output_text(cache, json.dumps({"key": key, "rows": rows}), force=True)
    by_count = frames_by_count(rows, demo_counts)
    minutes["frames"] = round((time.monotonic() - t) / 60, 1)
    round_info = round_summary(episodes, frames)
    expert = {
        "start": by_count[settings.start_demos]["frames"],
        "corrected": by_count[settings.start_demos]["frames"] + round_info["frames"]["operator"],
        "reference": by_count[settings.reference_demos]["frames"],
    }
    outcomes = {name: {e.seed: e.success for e in eps} for name, eps in rollouts.items()}
    success = {name: success_rate([e.success for e in eps]) for name, eps in rollouts.items()}
    names = {
        "start": f"equidiff_{settings.start_demos}",
        "corrected": "corrected",
        "reference": f"equidiff_{settings.reference_demos}",
    }
    points = {
        k: {"name": names[k], "frames": expert[k], "rate": success[k]["rate"], "ci95": success[k]["ci95"]}
        for k in expert
    }
    curve = None
    if settings.demos_result is not None:
        curve = demos_curve(settings.demos_result, {n: v["frames"] for n, v in by_count.items()})
    ft = settings.fine_tune
    note = (
        f"round: {len(episodes)} scenes, {round_info['takeovers']} takeovers; fine-tune {fine_tune.get('steps')} steps "
        f"from {names['start']}, lr {ft.lr:g}, operator weight {ft.intervention_weight:g}, policy frames "
        f"{ft.policy_frame_weight:g}; {settings.eval_episodes} held-out scenes"
    )
    plot = plot_corrections(points, curve, out / "success_vs_expert_frames.png", note)
    result = {
        "bench": "corrections",
        "success": {names[k]: success[k] for k in success},
        "paired": {
            "corrected_vs_start": _paired(outcomes["corrected"], outcomes["start"]),
            "corrected_vs_reference": _paired(outcomes["corrected"], outcomes["reference"]),
        },
        "expert_frames": {names[k]: v for k, v in expert.items()},
        "demo_frames": {str(n): v for n, v in by_count.items()},
        "extra_demo_frames": expert["reference"] - expert["start"],
        "round": round_info,
        "round_episodes": [asdict(e) for e in episodes],
        "gate": gate_quality(episodes),
        "rule": asdict(settings.rule),
        "fine_tune": {**asdict(ft), **fine_tune},
        "stages": {names[k]: summarize(v) for k, v in rollouts.items()},
        "eval_episodes": settings.eval_episodes,
        "eval_scenes": f"block yaw inside {list(settings.train_yaw)} (modulo 180 deg), seeds {seeds[0]}..",
        "round_scenes": f"the same yaw range, seeds {ROUND_SEEDS_FROM}..",
        "max_duration_s": settings.max_duration,
        "latency_budget_ms": settings.latency_ms,
        "demos_curve": {str(n): v for n, v in curve.items()} if curve else None,
        "plot": str(plot),
        "minutes": {**minutes, "total_this_call": round((time.monotonic() - t_start) / 60, 1)},
    }
    if settings.plot is not None:
        with staged_output(settings.plot, force=settings.force) as staged:
            shutil.copyfile(plot, staged.path)
    write_output_text(out / "result.json", json.dumps(result) + "\n", force=True)
    return result
