"""Success against DDIM denoising steps, in the in-process twin (``equidiff bench steps``; the command's help text
defines the JSON keys, docs/denoising_steps.md says how to read them).

One policy file is sampled at several step counts: its own sampler (the baseline, always measured) and each of
``steps`` with the timestep ``spacing`` asked (``models.sampling.make_inference_scheduler``). Each is rolled out on
the same scenes as ``equidiff twin evaluate`` (``twin.evaluate.evaluate_policy``, the twin's latency budget, one
torch thread), with ``twin.chunking.ChunkingProbe`` watching the commands at chunk switches, and its ``predict``
is timed on one thread in the same run, the samplers taking turns. Each sampler's roll-outs are kept in
OUT/<sampler>/ and reused by a later call with the same settings, so an interrupted run resumes; OUT/result.json
and the PNG are rewritten after every sampler. ``run_steps_bench`` returns the JSON line as a dict, or raises
``BenchError``; its progress goes to this module's logger."""

from __future__ import annotations

import json
import logging
import os
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from equidiff_core.benches import BenchError
from equidiff_core.benches.figures import save_with_note
from equidiff_core.benches.rollouts import cached_rollouts, policy_digest, summarize
from equidiff_core.benches.stats import paired_comparison, paired_outcomes
from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.models.equivariance import twin_scenes
from equidiff_core.models.sampling import TIMESTEP_SPACINGS
from equidiff_core.policy.file import CheckpointError
from equidiff_core.policy.inference import InferencePolicy, load_inference_policy
from equidiff_core.runtime.machine import cpu_model
from equidiff_core.runtime.output_files import refuse_existing, staged_output, write_output_text
from equidiff_core.twin.chunking import ChunkingProbe
from equidiff_core.twin.config import load_twin_config
from equidiff_core.twin.demos import DirectRecorder
from equidiff_core.twin.evaluate import ROLLOUT_THREADS, evaluate_policy, torch_threads
from equidiff_core.twin.shipped import SHIPPED_CHECKPOINT

STEP_COUNTS = (16, 8, 4, 2, 1)
PLOT_NAME = "success_vs_inference.png"

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class StepsSettings:
    """``equidiff bench steps``'s settings: its flags, same names (the command's help says more)."""

    checkpoint: Path | None  # policy.pt (None: the shipped checkpoint)
    steps: tuple[int, ...]  # DDIM step counts, rolled out in this order after the baseline (may be empty with compare)
    spacing: str  # their timestep spacing (of TIMESTEP_SPACINGS); the baseline keeps the policy's own
    episodes: int  # scenes per sampler, the same for all
    seed: int  # the first scene seed
    max_duration: float | None  # sim seconds per episode (None: twin.yaml's)
    latency_ms: float  # each chunk takes effect this long after its observation (the twin's budget)
    timing_calls: int  # timed predict calls per sampler
    out: Path  # roll-outs, result.json and the PNG
    plot: Path | None  # also write the PNG here
    device: str = "cpu"
    precision: str = "fp32"
    lab_config: Path | None = None
    twin_config: Path | None = None
    force: bool = False  # replace an existing ``plot``
    compare: tuple[Path, ...] = ()  # other policy files (distilled ones), each at its own sampler, after the steps


def sampler_name(steps: int, spacing: str, timesteps: tuple[int, ...] | None = None) -> str:
    """``ddim4_trailing``; with explicit timesteps (a distilled sampler's) ``ddim4_t90-60-12-0``."""
    return f"ddim{steps}_{spacing}" if timesteps is None else f"ddim{steps}_t{'-'.join(map(str, timesteps))}"


COMPARED = "__"  # joins a compared file's name and its sampler in its row's name


def compared_name(path: Path, policy: InferencePolicy) -> str:
    """A compared file's row: its name (its folder's for a run's ``policy.pt``) and its own sampler."""
    label = path.parent.name if path.stem == "policy" else path.stem
    return (
        f"{label}{COMPARED}{sampler_name(policy.inference_steps, policy.timestep_spacing, policy.explicit_timesteps)}"
    )


def time_predict(policies: dict[str, InferencePolicy], calls: int, vox: np.ndarray, ee: np.ndarray) -> dict:
    """Each policy's ``predict`` on one observation, ``calls`` times on one torch thread, the policies taking
    turns (a load that comes and goes falls on all alike): {name: {"median_ms", "p99_ms", "calls"}}."""
    times: dict[str, list[float]] = {name: [] for name in policies}
    with torch_threads(1):
        for policy in policies.values():
            policy.predict(vox, ee, seed=0)  # first-call costs out of the figures
        for i in range(calls):
            for name, policy in policies.items():
                t0 = time.perf_counter()
                policy.predict(vox, ee, seed=i)
                times[name].append(1000 * (time.perf_counter() - t0))
    return {
        name: {
            "median_ms": round(statistics.median(ms), 2),
            "p99_ms": round(float(np.percentile(ms, 99)), 2),
            "calls": len(ms),
        }
        for name, ms in times.items()
    }


def plot_steps(rows: list[dict], path: Path, title: str, note: str = "") -> Path:
    """PNG of success (%, 95 % interval as error bars) against the median inference time (ms, the bar to the
    right reaching p99), one point per sampler labelled with its step count, the compared files' in a legend
    (they often land on one another; matplotlib's Figure, no pyplot)."""
    fig = Figure(figsize=(5.2, 3.8), dpi=120)
    ax = fig.subplots()
    markers = iter("o^vD<>p")
    for row in rows:
        if row["success"] is None:
            continue
        x, y, ci = row["inference_median_ms"], 100 * row["success"], row["success_ci95"]
        baseline, compared = row["baseline"], COMPARED in row["sampler"]  # a compared file at its own sampler
        ax.errorbar(
            [x],
            [y],
            yerr=[[y - 100 * ci[0]], [100 * ci[1] - y]],
            xerr=[[0.0], [row["inference_p99_ms"] - x]],
            marker="s" if baseline else (next(markers, "o") if compared else "o"),
            color="black" if baseline else ("tab:orange" if compared else "tab:blue"),
            capsize=3,
            label=f"{row['sampler'].split(COMPARED)[0]} ({row['steps']} steps)" if compared else None,
        )
        if not compared:
            label = f"{row['steps']}" + (" (policy's own)" if baseline else "")
            ax.annotate(label, (x, y), textcoords="offset points", xytext=(6, 6), fontsize=8)
    if any(COMPARED in row["sampler"] for row in rows):
        ax.legend(fontsize=7, loc="lower right")
    ax.set_xlabel("inference time per chunk, ms (median; bar to p99), one thread")
    ax.set_ylabel("success, % (95 % interval)")
    ax.set_ylim(-5, 105)
    widest = max((r["inference_p99_ms"] for r in rows), default=1.0)
    ax.set_xlim(0, 1.35 * widest)  # room for the labels right of the slowest point
    ax.grid(alpha=0.3)
    ax.set_title(title, fontsize=9)
    return save_with_note(fig, path, note)


def _load(settings: StepsSettings, checkpoint: Path, steps: int | None = None, spacing: str | None = None):
    try:
        return load_inference_policy(
            checkpoint,
            device=settings.device,
            precision=settings.precision,
            inference_steps=steps,
            timestep_spacing=spacing,
        )
    except (CheckpointError, ValueError) as err:
        raise BenchError(str(err), 2) from err


def _chunking_summary(path: Path, settings: dict) -> dict | None:
    """The probe's summary saved beside a sampler's roll-outs with exactly ``settings`` (None: none saved)."""
    try:
        payload = json.loads(path.read_text())
        return payload["summary"] if payload["settings"] == json.loads(json.dumps(settings)) else None
    except (OSError, ValueError, KeyError, TypeError):
        return None


def run_steps_bench(settings: StepsSettings) -> dict:
    """Every sampler rolled out and timed: the bench's JSON line (also OUT/result.json). BenchError (exit status
    2) for settings it cannot run with, a missing or unloadable checkpoint, or a named plot that exists."""
    if settings.episodes < 1 or settings.timing_calls < 1 or not (settings.steps or settings.compare):
        raise BenchError("need --episodes >= 1, --timing-calls >= 1 and a step count or a --compare file", 2)
    if settings.spacing not in TIMESTEP_SPACINGS:
        raise BenchError(f"--spacing must be one of {TIMESTEP_SPACINGS}, got {settings.spacing!r}", 2)
    if not (np.isfinite(settings.latency_ms) and settings.latency_ms >= 0):
        raise BenchError(f"--latency-ms must be finite and >= 0, got {settings.latency_ms}", 2)
    if settings.plot is not None:  # a file the user named: refused now, not after hours of roll-outs
        refuse_existing(settings.plot, settings.force)
    checkpoint = settings.checkpoint or SHIPPED_CHECKPOINT
    for path in (checkpoint, *settings.compare):
        if not path.is_file():
            raise BenchError(f"no policy file at {path}", 2)
    t_start = time.monotonic()
    lab = load_lab_config(settings.lab_config or default_config_dir() / "lab.yaml")
    cfg = load_twin_config(settings.twin_config)
    max_duration = settings.max_duration or cfg.episode.max_duration_s
    own = _load(settings, checkpoint)
    base = sampler_name(own.inference_steps, own.timestep_spacing, own.explicit_timesteps)
    policies = {base: own}
    files = {base: checkpoint}  # each sampler's policy file
    for k in settings.steps:
        name = sampler_name(k, settings.spacing)
        if name not in policies:
            policies[name] = _load(settings, checkpoint, k, settings.spacing)
            files[name] = checkpoint
    for path in settings.compare:
        other = _load(settings, path)
        name = compared_name(path, other)
        if name in policies:
            raise BenchError(f"--compare {path}: a second {name}", 2)
        policies[name], files[name] = other, path
    vox, ee = twin_scenes(own.preset, own.workspace, count=1, seed=0, scene=cfg.scene)
    logger.info(f"[steps] timing {', '.join(policies)}: {settings.timing_calls} calls each, one thread")
    load_before = os.getloadavg()[0]  # the timing shares the CPU with whatever else runs: say how busy it was
    timing = time_predict(policies, settings.timing_calls, vox[0, 0].numpy(), ee[0, 0].numpy())
    load = [round(load_before, 2), round(os.getloadavg()[0], 2)]
    seeds = list(range(settings.seed, settings.seed + settings.episodes))
    digests = {path: policy_digest(path) for path in set(files.values())}
    rows: list[dict] = []
    outcomes: dict[str, dict[int, bool]] = {}
    rec = None
    try:
        for name, policy in policies.items():
            rollout_settings = {
                "seeds": seeds,
                "max_duration_s": max_duration,
                "latency_s": settings.latency_ms / 1000,
                "policy_digest": digests[files[name]],
                "inference_steps": policy.inference_steps,
                "timestep_spacing": policy.timestep_spacing,
                **({"timesteps": list(policy.explicit_timesteps)} if policy.explicit_timesteps is not None else {}),
                "precision": policy.precision,
                "threads": ROLLOUT_THREADS,
            }
            chunking_path = settings.out / name / "chunking.json"

            fresh = []  # set when this sampler is rolled out now, not reused

            def roll_out(
                name=name, policy=policy, rollout_settings=rollout_settings, chunking_path=chunking_path, fresh=fresh
            ):
                nonlocal rec
                fresh.append(True)
                rec = rec or DirectRecorder(cfg, lab)
                probe = ChunkingProbe()
                episodes = evaluate_policy(
                    policy,
                    cfg,
                    lab,
                    seeds,
                    max_duration,
                    recorder=rec,
                    latency_s=settings.latency_ms / 1000,
                    probe=probe,
                    threads=ROLLOUT_THREADS,
                    log=lambda s: logger.info(f"[{name}] {s}"),
                )
                payload = {"settings": rollout_settings, "summary": probe.summary()}
                write_output_text(chunking_path, json.dumps(payload) + "\n", force=True)  # the bench's own
                return episodes

            episodes = cached_rollouts(
                settings.out / name / "rollouts.json",
                rollout_settings,
                roll_out,
                lambda s, name=name: logger.info(f"[{name}] {s}"),
            )
            outcomes[name] = {e.seed: e.success for e in episodes}
            chunking = _chunking_summary(chunking_path, rollout_settings)
            summary = summarize(episodes)
            row = {
                "sampler": name,
                "policy": str(files[name]),
                "steps": policy.inference_steps,
                "spacing": policy.timestep_spacing,
                "timesteps": policy.timesteps,
                "baseline": name == base,
                **summary,
                "paired_vs_baseline": None
                if name == base
                else paired_comparison(*paired_outcomes(outcomes[name], outcomes[base])),
                "inference_median_ms": timing[name]["median_ms"],
                "inference_p99_ms": timing[name]["p99_ms"],
                "inference_vs_baseline": round(timing[name]["median_ms"] / timing[base]["median_ms"], 3),
                "failed_predictions": sum(e.failed_predictions for e in episodes),
                "boundary_dv_p95_mps": None if chunking is None else chunking["boundary_dv_p95_mps"],
                "chunking": chunking,
            }
            rows.append(row)
            logger.info(
                f"[{name}] {summary['successes']} of {summary['episodes']} ({row['success_ci95']}), inference "
                f"median {row['inference_median_ms']} ms, boundary dv p95 {row['boundary_dv_p95_mps']} m/s"
            )
            if fresh:  # what an interrupted run leaves: the figures so far (reused ones add nothing to redraw)
                _result(settings, rows, policies, timing, load, checkpoint, seeds, max_duration, t_start)
    finally:
        if rec is not None:
            rec.close()
    result = _result(settings, rows, policies, timing, load, checkpoint, seeds, max_duration, t_start)
    result["complete"] = True
    write_output_text(settings.out / "result.json", json.dumps(result) + "\n", force=True)
    if settings.plot is not None:
        with staged_output(settings.plot, force=settings.force) as staged:
            staged.path.write_bytes(Path(result["plot"]).read_bytes())
    return result


def _result(settings, rows, policies, timing, load, checkpoint, seeds, max_duration, t_start) -> dict:
    """The JSON line so far, written to OUT/result.json with its plot (``complete`` false until every sampler
    has been rolled out)."""
    own = next(iter(policies.values()))
    cpu = cpu_model()
    title = (
        f"{checkpoint.parent.name}: success on {len(seeds)} unseen scenes against DDIM steps\n"
        f"(in-process twin, L = {settings.latency_ms:g} ms; {cpu})"
    )
    note = f"seeds {seeds[0]}-{seeds[-1]}, {max_duration:g} s episodes, {settings.precision}; steps spaced " + (
        f"{settings.spacing}; the square is the policy's own sampler"
    )
    plot = plot_steps(rows, settings.out / PLOT_NAME, title, note)
    result = {
        "bench": "steps",
        "rows": rows,
        "pending": [name for name in policies if name not in {r["sampler"] for r in rows}],
        "timing": timing,
        "timing_load_average_1min": load,  # before and after the timing
        "seeds": [seeds[0], seeds[-1]],
        "episodes": len(seeds),
        "max_duration_s": max_duration,
        "latency_budget_ms": settings.latency_ms,
        "precision": settings.precision,
        "device": settings.device,
        "threads": ROLLOUT_THREADS,
        "timing_threads": 1,
        "cpu": cpu,
        "checkpoint": str(checkpoint),
        "preset": own.preset.name,
        "out": str(settings.out),
        "plot": str(plot),
        "wall_s": round(time.monotonic() - t_start, 1),
        "complete": False,
    }
    write_output_text(settings.out / "result.json", json.dumps(result) + "\n", force=True)  # the bench's own
    return result
