"""One ``equidiff train`` run: bags -> episodes and their train/validation split -> ``training.loop.train`` -> run.json.

``run_training(TrainingSpec)`` returns the run's summary (the JSON line the command prints) or raises
``TrainJobError``; its progress goes to this module's logger. The split is saved in OUT/split.json and reused
on resume; OUT/run.json keeps the summary and the recipe it trained with (read back by
``benches.training_runs``, which starts runs in their own process through ``equidiff_core.training.process``).
The command's help text says more.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from equidiff_core.config import ConfigError, default_config_dir, load_lab_config
from equidiff_core.data.dataset import DemoDataset, load_episodes, split_episodes
from equidiff_core.data.episode_arrays import DatasetConfig
from equidiff_core.data.segments import FrameSource, SourceWeights
from equidiff_core.models.state import learned_state_dict
from equidiff_core.perception.observation import STATE_TOLERANCE_S
from equidiff_core.policy.diffusion import make_policy
from equidiff_core.policy.file import CheckpointError, weights_sha256
from equidiff_core.policy.presets import get_preset
from equidiff_core.runtime.jobs import JobError
from equidiff_core.runtime.output_files import occupied, staged_output
from equidiff_core.training import distributed
from equidiff_core.training.callbacks import ActionMseEvaluator, PlotWriter, ProgressBar
from equidiff_core.training.config import TrainConfig, TrainingError, resolve_device
from equidiff_core.training.loop import load_policy_from_checkpoint, load_training_checkpoint, seed_everything, train
from equidiff_core.wire.pointcloud import VoxelGridSpec

logger = logging.getLogger(__name__)


class TrainJobError(JobError):
    """``equidiff train`` could not run: exit status 2 for a request that cannot be run as asked (an existing
    OUT, conflicting or out-of-range settings, no torchrun group), 1 when the data or the training failed."""


# the settings that name files: paths in a TrainingSpec, strings in its JSON
_PATH_FIELDS = ("out", "lab_config", "cache_dir", "init_from")


@dataclass(frozen=True)
class TrainingSpec:
    """One ``equidiff train`` run: the command's flags, with their names and defaults (``--no-progress`` is
    ``progress=False``); the command's help says what each does. ``to_json`` / ``from_json`` carry it to
    a run in another process (``equidiff_core.training.process``)."""

    bags: tuple[Path, ...]  # bag directories, or folders holding bag directories
    out: Path  # the run directory (checkpoints, policy.pt, plots, split.json, run.json)
    policy: str | None = None  # equidiff or baseline; None: equidiff, or init_from's
    preset: str | None = None  # None: compact, or init_from's
    rotation_aug: str | None = None  # None: the preset's
    baseline_width: int | None = None  # None: the preset's; 0: channels matched to EquiDiff's parameter count
    baseline_init: str | None = None  # None: the preset's
    steps: int = 20000  # the cosine schedule's length
    batch_size: int = 64  # per rank
    lr: float = 1e-4  # peak learning rate
    warmup_steps: int = 500
    ema: bool = False
    noise_repeats: int = 1  # (noise, step) draws per observation per step
    seed: int = 0
    device: str = "auto"  # auto, cpu, cuda or cuda:N
    val_fraction: float = 0.1  # of the episodes, held out whole
    eval_every: int = 1000
    eval_max_samples: int = 64  # samples scored by DDIM action MSE at each evaluation
    checkpoint_every: int = 1000
    max_minutes: float | None = None  # time budget: stop, checkpoint and export when spent
    num_workers: int = 0
    precision: str = "auto"  # auto, fp32 or bf16
    data: str = "auto"  # auto, device or loader
    resume: bool = False  # continue OUT's run
    force: bool = False  # replace OUT once the new run is complete
    lab_config: Path | None = None  # lab.yaml (workspace); None: the installed one
    cache_dir: Path | None = None  # decoded-episode cache; None: OUT/dataset_cache
    tolerance: float = STATE_TOLERANCE_S  # state/voxel stamp tolerance, s
    rerun: str | None = None  # also log to rerun: FILE.rrd, spawn or HOST:PORT
    progress: bool = True  # the progress bar (without it every evaluation is logged)
    # fine-tuning: start from this run's weights (last.ckpt or a slim weights.ckpt), its preset and normaliser
    init_from: Path | None = None
    intervention_weight: float = SourceWeights.intervention  # an operator's correction frame, against a demo's 1
    policy_frame_weight: float = SourceWeights.policy  # the policy's own frames in a roll-out (0: left out)

    def to_json(self) -> str:
        """The spec as one JSON object (paths as strings)."""
        fields = dataclasses.asdict(self)
        fields["bags"] = [str(bag) for bag in self.bags]
        fields.update({name: None if fields[name] is None else str(fields[name]) for name in _PATH_FIELDS})
        return json.dumps(fields)

    def settings_text(self) -> str:
        """``name=value`` for the output folder and each setting away from its default (the bags left out),
        for a progress line."""
        defaults = TrainingSpec(bags=(), out=self.out)
        changed = [
            f"{field.name}={getattr(self, field.name)}"
            for field in dataclasses.fields(self)
            if field.name not in ("bags", "out") and getattr(self, field.name) != getattr(defaults, field.name)
        ]
        return " ".join([f"out={self.out}", *changed])

    @classmethod
    def from_json(cls, text: str) -> TrainingSpec:
        """The spec ``to_json`` wrote; TypeError for a field it does not know."""
        fields = json.loads(text)
        fields["bags"] = tuple(Path(bag) for bag in fields["bags"])
        fields.update({name: None if fields.get(name) is None else Path(fields[name]) for name in _PATH_FIELDS})
        return cls(**fields)


def _load_split(out: Path, episodes, val_fraction: float, seed: int, resume: bool, write: bool = True):
    split_file = out / "split.json"
    by_path = {str(ep.path.resolve()): ep for ep in episodes}
    if resume and split_file.is_file():
        saved = json.loads(split_file.read_text())
        missing = [p for p in saved["train"] + saved["val"] if p not in by_path]
        if missing:
            raise TrainJobError(f"resuming needs the same episodes; missing: {missing[:3]}")
        return [by_path[p] for p in saved["train"]], [by_path[p] for p in saved["val"]]
    train, val = split_episodes(episodes, val_fraction, seed)
    if not write:  # another rank writes the same split
        return train, val
    out.mkdir(parents=True, exist_ok=True)
    split_file.write_text(
        json.dumps(
            {
                "seed": seed,
                "val_fraction": val_fraction,
                "train": [str(e.path.resolve()) for e in train],
                "val": [str(e.path.resolve()) for e in val],
            },
            indent=1,
        )
    )
    return train, val


def run_training(spec: TrainingSpec) -> dict | None:
    """One ``equidiff train`` run; returns its summary (the command's JSON line, also in OUT/run.json), None
    on the ranks other than 0, or raises ``TrainJobError``. Under torchrun every rank calls it; rank 0
    alone writes files and logs."""
    try:
        dist_info = distributed.init_from_env(resolve_device(spec.device).type)
    except (distributed.DistributedError, TrainingError) as err:
        raise TrainJobError(str(err), 2) from err
    try:
        return _run(spec, dist_info)
    finally:
        distributed.shutdown()


def _run(spec: TrainingSpec, dist_info) -> dict | None:
    """OUT as the run directory: a new one (trained in place, so that a killed run can be resumed), the
    one to continue (``resume``), or one to replace (``force``: the new run trains beside it and
    replaces it only once complete). A new run that stops before its first checkpoint leaves no OUT."""
    out = Path(spec.out)
    if spec.resume and spec.force:
        raise TrainJobError("--resume continues OUT and --force replaces it: pass one of them", 2)
    # every rank sees the same: rank 0 writes into OUT only after all ranks got here
    if not spec.resume and occupied(out):
        if not spec.force:
            raise TrainJobError(
                f"{out} exists and holds files; pass --resume to continue its run, --force to "
                "replace it once the new run is complete, or choose a new --out",
                2,
            )
        return _replace_run(spec, dist_info, out)
    existed = out.exists()
    try:
        return _train_into(spec, dist_info, out, out)
    except BaseException:
        if dist_info.is_main and not spec.resume:
            _discard_unstarted(out, existed)
        raise


def _replace_run(spec: TrainingSpec, dist_info, out: Path) -> dict | None:
    """``force`` over an existing run: every rank trains into one folder staged beside OUT, which
    replaces OUT once the run completed; a failed run leaves OUT as it was."""
    if not dist_info.is_main:
        return _train_into(spec, dist_info, Path(distributed.broadcast_object(None)), out)
    with staged_output(out, force=True) as staged:
        staged.path.mkdir()
        distributed.broadcast_object(str(staged.path))
        return _train_into(spec, dist_info, staged.path, out)


def _discard_unstarted(out: Path, existed: bool) -> None:
    """What a new run wrote before its first checkpoint (split, decoded episodes): without it a rerun would
    be refused. A run with a checkpoint stays, to be continued with --resume."""
    if not out.is_dir() or (out / "last.ckpt").exists():
        return
    if not existed:
        shutil.rmtree(out)
        return
    for child in out.iterdir():  # OUT was an empty folder: keep the folder
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child)
        else:
            child.unlink()


def _train_into(spec: TrainingSpec, dist_info, out: Path, named: Path) -> dict | None:
    """The run, written into ``out``; the paths its summary and run.json name are under ``named``
    (OUT itself, or the folder a --force run is staged in before it replaces OUT)."""
    main = dist_info.is_main
    say = logger.info if main else (lambda m: None)
    lab = load_lab_config(spec.lab_config or default_config_dir() / "lab.yaml")
    start = _starting_policy(spec, lab.workspace) if spec.init_from is not None else None
    preset = start.preset if start is not None else _preset(spec)
    try:
        weights = SourceWeights(intervention=spec.intervention_weight, policy=spec.policy_frame_weight)
    except ValueError as err:
        raise TrainJobError(str(err), 2) from err
    data_cfg = DatasetConfig.from_preset(
        preset,
        resolution=lab.workspace.resolution,
        grid=VoxelGridSpec.of(lab.workspace, lab.base_frame),  # every bag's grids must be this lab's
        state_tolerance_s=spec.tolerance,
        cache_dir=str(spec.cache_dir or out / "dataset_cache"),
    )
    episodes, skipped = load_episodes(spec.bags, data_cfg, log=say)
    if not episodes:
        raise TrainJobError("no usable episodes")
    train_eps, val_eps = _load_split(out, episodes, spec.val_fraction, spec.seed, spec.resume, write=main)
    train_set = DemoDataset(train_eps, data_cfg, weights)
    val_set = DemoDataset(val_eps, data_cfg, weights) if val_eps else None
    if len(train_set) == 0:
        raise TrainJobError(
            "the training episodes are too short for one window "
            f"(need >= {preset.horizon - preset.n_action_steps + 1} observations)"
        )
    say(
        f"{len(train_eps)} train episodes ({len(train_set)} samples), "
        f"{len(val_eps)} held out ({len(val_set) if val_set else 0} samples), {len(skipped)} skipped; "
        f"{start.name if start is not None else spec.policy or 'equidiff'} / {preset.name}"
        + (f"; {dist_info.world_size} data-parallel ranks ({dist_info.backend})" if dist_info.distributed else "")
    )

    try:
        cfg = TrainConfig(
            steps=spec.steps,
            batch_size=spec.batch_size,
            lr=spec.lr,
            warmup_steps=spec.warmup_steps,
            ema=spec.ema,
            noise_repeats=spec.noise_repeats,
            seed=spec.seed,
            device=spec.device,
            eval_every=spec.eval_every,
            checkpoint_every=spec.checkpoint_every,
            num_workers=spec.num_workers,
            max_minutes=spec.max_minutes,
            precision=spec.precision,
            data=spec.data,
        )
    except ValueError as err:  # a setting out of range, e.g. --noise-repeats 0
        raise TrainJobError(str(err), 2) from err
    seed_everything(spec.seed)  # the initial weights come from the global RNG: seed before building
    start_weights = None if start is None else weights_sha256(learned_state_dict(start.model))
    policy = start if start is not None else make_policy(spec.policy or "equidiff", preset, lab.workspace)
    start_step = 0
    if main and spec.resume and (out / "last.ckpt").exists():  # for the progress bar
        start_step = int(load_training_checkpoint(out / "last.ckpt")["step"])
    callbacks = [
        ActionMseEvaluator(
            policy,
            val_set if val_set is not None else train_set,
            spec.eval_max_samples,
            min(spec.batch_size, 32),
            spec.seed,
            "val" if val_set is not None else "train",
        ),
        ProgressBar(spec.steps, start_step, main and spec.progress),
        PlotWriter(out / "training.png", []),
    ]
    if spec.rerun and main:
        try:  # rerun-sdk is an optional extra: imported only when asked for
            from equidiff_core.viz.training_callback import RerunTrainingCallback
        except ImportError as err:
            raise TrainJobError(f"--rerun needs the viz extra (rerun-sdk): {err}", 2) from err
        callbacks.append(RerunTrainingCallback.from_target(spec.rerun))
    try:
        result = train(policy, train_set, val_set, cfg, out, callbacks=callbacks)
    except TrainingError as err:
        raise TrainJobError(str(err)) from err
    if not main:
        return None
    evals = [h for h in result.history if "val_loss" in h]
    losses = [h["loss"] for h in result.history if "loss" in h]
    summary = {
        "checkpoint": str(named / result.checkpoint.relative_to(out)),
        "policy": str(named / result.exported.relative_to(out)),
        "plot": str(named / "training.png"),
        "steps": result.steps,
        "final_loss": losses[-1] if losses else None,
        "val_action_mse": evals[-1].get("val_action_mse") if evals else None,
        "train_action_mse": evals[-1].get("train_action_mse") if evals else None,
        "train_episodes": len(train_eps),
        "val_episodes": len(val_eps),
        "skipped": len(skipped),
        # what the training samples' current frames were (data.segments): the expert's are demo + operator
        "samples_by_source": _samples_by_source(train_set),
    }
    if result.stopped:
        summary["stopped"] = result.stopped
    # what trained this policy, for whoever evaluates it elsewhere (bench generalization --trained)
    recipe = {
        "device": str(next(policy.parameters()).device),
        "preset": preset.name,
        "rotation_aug": preset.rotation_aug,
        "schedule_steps": spec.steps,  # the cosine schedule's length; "steps" above is how many ran
        "batch_size": spec.batch_size,
        "lr": spec.lr,
        "warmup_steps": spec.warmup_steps,
        "noise_repeats": spec.noise_repeats,
        "ema": spec.ema,
        "seed": spec.seed,
        "max_minutes": spec.max_minutes,
        "world_size": result.world_size,
        "precision": result.precision,
        "data": result.data,
        "init_from": None if spec.init_from is None else str(spec.init_from),
        "init_weights_sha256": None if start is None else start_weights,
        "source_weights": {"intervention": weights.intervention, "policy": weights.policy},
    }
    (out / "run.json").write_text(json.dumps({**summary, "recipe": recipe}, indent=1) + "\n")
    return summary


def _preset(spec: TrainingSpec):
    overrides = {
        "rotation_aug": spec.rotation_aug,
        "baseline_width": spec.baseline_width,
        "baseline_init": spec.baseline_init,
    }
    overrides = {key: value for key, value in overrides.items() if value is not None}
    if overrides.get("baseline_width") == 0:
        overrides["baseline_width"] = None
    try:
        return get_preset(spec.preset or "compact", **overrides)
    except ConfigError as err:  # an unknown preset or an override out of range
        raise TrainJobError(str(err), 2) from err


def _starting_policy(spec: TrainingSpec, workspace):
    """The policy ``spec.init_from`` holds, to fine-tune: its kind, preset and normaliser are the run's, so a flag
    that asks for others is refused rather than ignored."""
    conflicting = [
        f"--{name.replace('_', '-')}"
        for name in ("policy", "preset", "rotation_aug", "baseline_width", "baseline_init")
        if getattr(spec, name) is not None
    ]
    if conflicting:
        raise TrainJobError(f"--init-from brings its own model: drop {', '.join(conflicting)}", 2)
    try:
        start = load_policy_from_checkpoint(spec.init_from, device="cpu", ema=True)
    except (CheckpointError, OSError) as err:
        raise TrainJobError(f"--init-from {spec.init_from}: {err}", 2) from err
    if start.workspace != workspace:
        raise TrainJobError(
            f"--init-from {spec.init_from} was trained for workspace {start.workspace}, this lab's is {workspace}", 2
        )
    return start.train()


def _samples_by_source(dataset: DemoDataset) -> dict[str, int]:
    """How many of ``dataset``'s samples have their current frame from each source."""
    counts = np.bincount(dataset.sources.astype(np.intp), minlength=len(FrameSource))
    return {source.name.lower(): int(counts[source]) for source in FrameSource}
