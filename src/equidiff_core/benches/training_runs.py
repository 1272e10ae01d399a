"""``equidiff train`` runs for the benches (each in a process of its own, ``equidiff_core.training.process``):
one recipe for every policy, runs side by side, what they recorded (steps, recipe, fit of the training samples) and the two checks made before any roll-out.

Every policy of a bench trains with the same recipe (``Recipe``: preset, steps, batch, warm-up, seed,
noise draws, EMA); only rotation augmentation (by design), the baseline's own peak learning rate
(each network at the rate it fits its demos with at this budget: docs/results/model.md) and how fast it ran
(device, data path, time budget) may differ, and ``recipe_differences`` names any other difference
from the run.json files ``equidiff train`` writes. ``training_fit`` reads the DDIM action error on the training
samples that ``equidiff train --val-fraction 0`` records at its end; ``under_fit`` names the policies
whose error exceeds ``max_ratio`` times the reference policy's: such a policy has not learned its own
demos, so rolling it out measures the budget or the network, not what the bench asks.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from ..models.baseline import baseline_encoder_channels
from ..policy.file import export_policy
from ..training.job import TrainingSpec
from ..training.loop import load_policy_from_checkpoint

# Settings that may differ between a bench's runs: rotation augmentation by design, and what only
# changes how fast the same recipe ran (device, data path, time budget).
RECIPE_FREE = ("rotation_aug", "device", "data", "max_minutes")
# the benches' second gate: a policy's training-sample action error at most this times EquiDiff's
MAX_FIT_RATIO = 1.5
# The benches' default peak learning rates for 6000 steps of batch 8: EquiDiff fits its 40 demos at
# 5e-4, the plain-CNN baseline only at 1e-3 (docs/results/model.md, "The baseline's learning rate").
EQUIDIFF_LR = 5e-4
BASELINE_LR = 1e-3


class TrainRunError(RuntimeError):
    """`equidiff train` failed, did not stop or wrote no policy."""


@dataclass(frozen=True)
class Recipe:
    """What every ``equidiff train`` run of a bench shares."""

    preset: str
    steps: int
    batch_size: int
    lr: float
    seed: int
    device: str
    noise_repeats: int = 1
    ema: bool = False
    max_minutes: float | None = None
    lab_config: Path | None = None
    baseline_lr: float | None = None  # the baseline's peak learning rate (None: ``lr``)

    def lr_of(self, policy: str) -> float:
        """The peak learning rate ``policy`` trains with."""
        return self.baseline_lr if policy == "baseline" and self.baseline_lr is not None else self.lr

    def train_spec(self, policy: str, rotation_aug: str, bags: list[Path], out: Path) -> TrainingSpec:
        """The ``equidiff train`` run for ``policy`` on ``bags`` into ``out``: no held-out episodes (the fit of
        the training samples is scored once, at the end), four checkpoints, warm-up min(500, steps / 10)."""
        return TrainingSpec(
            bags=tuple(bags),
            out=out,
            policy=policy,
            preset=self.preset,
            rotation_aug=rotation_aug,
            steps=self.steps,
            batch_size=self.batch_size,
            lr=self.lr_of(policy),
            seed=self.seed,
            device=self.device,
            val_fraction=0.0,
            eval_every=10**9,
            checkpoint_every=max(10, self.steps // 4),
            warmup_steps=min(500, max(1, self.steps // 10)),
            progress=False,
            noise_repeats=self.noise_repeats,
            ema=self.ema,
            lab_config=self.lab_config,
            max_minutes=self.max_minutes,
            # the bench owns ``out`` (start_run puts its train.log there first): an interrupted run goes on
            # where it stopped, a new one starts
            resume=True,
        )


def train_command(spec: TrainingSpec) -> list[str]:
    """``spec``'s run in a process of its own (``equidiff_core.training.process``)."""
    return [sys.executable, "-m", "equidiff_core.training.process", spec.to_json()]


def start_run(spec: TrainingSpec, threads: int) -> subprocess.Popen:
    """``spec``'s run in the background with ``threads`` torch threads, its output appended to
    ``spec.out/train.log``."""
    spec.out.mkdir(parents=True, exist_ok=True)
    with open(spec.out / "train.log", "ab") as log:
        return subprocess.Popen(
            train_command(spec),
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env={**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)},
        )


def wait_for_runs(runs: dict[str, subprocess.Popen], outs: dict[str, Path], deadline: float | None = None) -> None:
    """Wait for every run; a failing run stops the others within 10 s (their checkpoints and logs stay)
    and every run that failed by itself is reported with its log's tail. ``deadline`` (monotonic) is a
    backstop for runs that do not stop."""
    stopped = set()  # runs stopped here: not failures of their own

    def failures() -> TrainRunError | None:
        lines = []
        for name, run in runs.items():
            if run.returncode not in (None, 0) and name not in stopped:
                log = outs[name] / "train.log"
                tail = log.read_text(errors="replace")[-2000:] if log.is_file() else ""
                lines.append(f"equidiff train {name} failed (exit {run.returncode}; log {log}):\n{tail}")
        return TrainRunError("\n".join(lines)) if lines else None

    try:
        while any(run.poll() is None for run in runs.values()):
            if any(run.returncode not in (None, 0) for run in runs.values()):
                _wait_all(runs.values(), grace_s=10.0)  # the others may be failing too: report them all
                raise failures()
            if deadline is not None and time.monotonic() > deadline:
                raise TrainRunError("equidiff train did not stop within its time budget")
            time.sleep(0.5)
    finally:
        for name, run in runs.items():
            if run.poll() is None:
                stopped.add(name)
                run.terminate()
                run.wait()
    error = failures()
    if error is not None:
        raise error
    for name, out in outs.items():
        if not (out / "policy.pt").is_file():
            raise TrainRunError(f"equidiff train {name} wrote no {out / 'policy.pt'}")


def _wait_all(runs, grace_s: float) -> None:
    end = time.monotonic() + grace_s
    while any(run.poll() is None for run in runs) and time.monotonic() < end:
        time.sleep(0.2)


def trained_steps(run_dir: Path) -> int | None:
    """The last step in ``run_dir/history.json`` (None if there is none)."""
    try:
        history = json.loads((run_dir / "history.json").read_text())
        steps = [h.get("step") for h in history if isinstance(h, dict) and "step" in h]
        return int(max(steps)) if steps else None  # history steps count from 1
    except (OSError, ValueError):
        return None


def training_recipe(run_dir: Path) -> dict | None:
    """How ``equidiff train`` trained the policy in ``run_dir`` (run.json's recipe; None if not recorded)."""
    try:
        return json.loads((run_dir / "run.json").read_text())["recipe"]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def recipe_differences(recipes: dict[str, dict | None], lr_by_run: dict[str, float] | None = None) -> list[str]:
    """The recipe settings the policies were trained with differently (runs without a run.json are not
    compared): a comparison needs the same budget for all. With ``lr_by_run`` (each run's peak learning rate
    as the bench's flags name it, ``Recipe.lr_of``), each run's lr is checked against its own instead
    of against the others'."""
    known = {name: recipe for name, recipe in recipes.items() if recipe is not None}
    free = set(RECIPE_FREE) | ({"lr"} if lr_by_run is not None else set())
    keys = sorted({key for recipe in known.values() for key in recipe} - free)
    differences = [
        f"{key}: " + ", ".join(f"{name} {recipe.get(key)}" for name, recipe in known.items())
        for key in keys
        if len({json.dumps(recipe.get(key)) for recipe in known.values()}) > 1
    ]
    wrong_lr = [
        f"{name} {recipe['lr']} where the bench asks for {lr_by_run[name]:g}"
        for name, recipe in known.items()
        if lr_by_run is not None
        and name in lr_by_run
        and "lr" in recipe
        and not math.isclose(float(recipe["lr"]), lr_by_run[name])
    ]
    return differences + (["lr: " + ", ".join(wrong_lr)] if wrong_lr else [])


def training_fit(run_dir: Path) -> dict | None:
    """The DDIM action error on the training samples at the end of the run in ``run_dir`` (history.json's
    last ``train_action_*`` row: fixed noise, samples spread over the training episodes): ``pos_err_m``,
    ``width_err_m``, ``mse``, ``samples``, ``step``; None when the run recorded none."""
    try:
        history = json.loads((run_dir / "history.json").read_text())
    except (OSError, ValueError):
        return None
    rows = [h for h in history if isinstance(h, dict) and "train_action_pos_err_m" in h]
    if not rows:
        return None
    row = rows[-1]
    # as recorded, not rounded: the gate compares them (rounded, 2.34 cm against 1.5 x 1.56 cm once
    # failed a policy that was within 1.5x)
    return {
        "pos_err_m": float(row["train_action_pos_err_m"]),
        "width_err_m": float(row["train_action_width_err_m"]),
        "mse": float(row["train_action_mse"]),
        "samples": row.get("train_action_samples"),
        "step": row.get("step"),
    }


def under_fit(fits: dict[str, dict | None], reference: str, max_ratio: float = MAX_FIT_RATIO) -> list[str]:
    """The policies whose training-sample position error exceeds ``max_ratio`` times ``reference``'s
    (``training_fit`` results). Policies without a recorded fit, or a reference without one, are not judged
    (``max_ratio`` 0: no gate)."""
    ref = fits.get(reference)
    if not max_ratio or ref is None:
        return []
    limit = max_ratio * ref["pos_err_m"]
    return [name for name, fit in fits.items() if fit is not None and fit["pos_err_m"] > limit]


def fit_ratios(fits: dict[str, dict | None], reference: str) -> dict[str, float | None]:
    """Each policy's training-sample position error over ``reference``'s (None where either is unknown)."""
    ref = fits.get(reference)
    return {
        name: None
        if fit is None or ref is None or not ref["pos_err_m"]
        else round(fit["pos_err_m"] / ref["pos_err_m"], 3)
        for name, fit in fits.items()
    }


# a finished run's committed weights when its policy.pt is not kept (training.slim_checkpoint)
SLIM_CHECKPOINT = "weights.ckpt"


# a run folder holding only this file is another bench's run (its relative path inside): one EquiDiff
# trained on the 40 demos serves bench generalization and bench demos without a second copy
SAME_AS = "same_as"


def resolve_run(run_dir: Path) -> Path:
    """``run_dir``, or the run its ``same_as`` file names (relative to ``run_dir``)."""
    pointer = run_dir / SAME_AS
    if pointer.is_file():
        return (run_dir / pointer.read_text().strip()).resolve()
    return run_dir


def run_policy(run_dir: Path, cache_dir: Path) -> Path:
    """The exported policy of the finished run in ``run_dir`` (``resolve_run``): its ``policy.pt``, else its
    ``weights.ckpt`` (``training.loop.slim_checkpoint``) exported once into ``cache_dir/policy.pt``;
    FileNotFoundError if neither."""
    run_dir = resolve_run(run_dir)
    policy = run_dir / "policy.pt"
    if policy.is_file():
        return policy
    slim = run_dir / SLIM_CHECKPOINT
    if not slim.is_file():
        raise FileNotFoundError(f"no {policy} or {slim}")
    cached = cache_dir / "policy.pt"
    if not cached.is_file() or cached.stat().st_mtime < slim.stat().st_mtime:
        cache_dir.mkdir(parents=True, exist_ok=True)
        export_policy(load_policy_from_checkpoint(slim), cached)
    return cached


def encoder_summary(policy_name: str, preset) -> str:
    """What a policy's voxel encoder is, for a bench's JSON: EquiDiff's escnn fields or the baseline's width."""
    if policy_name == "equidiff":
        return f"escnn C{preset.group_order}, regular fields {'/'.join(map(str, preset.encoder_channels))}"
    width = f"width {preset.baseline_width}" if preset.baseline_width else "parameter-matched"
    channels = "/".join(map(str, baseline_encoder_channels(preset)))
    return f"plain Conv3d, {width} (channels {channels}), {preset.baseline_init} init"
