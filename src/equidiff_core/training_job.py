"""One ``equidiff train`` run: bags -> episodes and their train/validation split -> ``training.train`` -> run.json.

The split is saved in OUT/split.json and reused on resume; OUT/run.json keeps the summary the command prints
and the recipe it trained with (read back by ``benches.training_runs``). The command's help text says more.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

from equidiff_core import distributed
from equidiff_core.config import ConfigError, default_config_dir, load_lab_config
from equidiff_core.dataset import DatasetConfig, DemoDataset, load_episodes, split_episodes
from equidiff_core.output_files import occupied, staged_output
from equidiff_core.pointcloud import VoxelGridSpec
from equidiff_core.policies import make_policy
from equidiff_core.presets import get_preset
from equidiff_core.training import (
    TrainConfig,
    TrainingError,
    load_training_checkpoint,
    resolve_device,
    seed_everything,
    train,
)
from equidiff_core.training_callbacks import ActionMseEvaluator, PlotWriter, ProgressBar


def _load_split(out: Path, episodes, val_fraction: float, seed: int, resume: bool, write: bool = True):
    split_file = out / "split.json"
    by_path = {str(ep.path.resolve()): ep for ep in episodes}
    if resume and split_file.is_file():
        saved = json.loads(split_file.read_text())
        missing = [p for p in saved["train"] + saved["val"] if p not in by_path]
        if missing:
            raise SystemExit(f"equidiff train: resuming needs the same episodes; missing: {missing[:3]}")
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


def run_training(args) -> int:
    """One ``equidiff train`` run for its parsed arguments (any object with the same attributes); returns the
    exit status. Under torchrun every rank calls it; rank 0 alone writes files and prints."""
    try:
        dist_info = distributed.init_from_env(resolve_device(args.device).type)
    except (distributed.DistributedError, TrainingError) as err:
        print(f"equidiff train: {err}", file=sys.stderr)
        return 2
    try:
        return _run(args, dist_info)
    finally:
        distributed.shutdown()


def _run(args, dist_info) -> int:
    """OUT as the run directory: a new one (trained in place, so that a killed run can be resumed), the
    one to continue (``--resume``), or one to replace (``--force``: the new run trains beside it and
    replaces it only once complete). A new run that stops before its first checkpoint leaves no OUT."""
    out = Path(args.out)
    force = getattr(args, "force", False)
    if args.resume and force:
        print("equidiff train: --resume continues OUT and --force replaces it: pass one of them", file=sys.stderr)
        return 2
    # every rank sees the same: rank 0 writes into OUT only after all ranks got here
    if not args.resume and occupied(out):
        if not force:
            print(
                f"equidiff train: {out} exists and holds files; pass --resume to continue its run, --force to "
                "replace it once the new run is complete, or choose a new --out",
                file=sys.stderr,
            )
            return 2
        return _replace_run(args, dist_info, out)
    existed = out.exists()
    try:
        status = _train_into(args, dist_info, out, out)
    except BaseException:
        if dist_info.is_main and not args.resume:
            _discard_unstarted(out, existed)
        raise
    if status != 0 and dist_info.is_main and not args.resume:
        _discard_unstarted(out, existed)
    return status


def _replace_run(args, dist_info, out: Path) -> int:
    """``--force`` over an existing run: every rank trains into one folder staged beside OUT, which
    replaces OUT once the run completed; a failed run leaves OUT as it was."""
    if not dist_info.is_main:
        return _train_into(args, dist_info, Path(distributed.broadcast_object(None)), out)
    with staged_output(out, force=True) as staged:
        staged.path.mkdir()
        distributed.broadcast_object(str(staged.path))
        status = _train_into(args, dist_info, staged.path, out)
        if status != 0:
            staged.discard()
    return status


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


def _train_into(args, dist_info, out: Path, named: Path) -> int:
    """The run, written into ``out``; the paths it prints and keeps in run.json are under ``named``
    (OUT itself, or the folder a --force run is staged in before it replaces OUT)."""
    main = dist_info.is_main
    say = (lambda m: print(f"equidiff train: {m}", file=sys.stderr)) if main else (lambda m: None)
    lab = load_lab_config(args.lab_config or default_config_dir() / "lab.yaml")
    overrides = {
        "rotation_aug": args.rotation_aug,
        "baseline_width": args.baseline_width,
        "baseline_init": args.baseline_init,
    }
    overrides = {key: value for key, value in overrides.items() if value is not None}
    if overrides.get("baseline_width") == 0:
        overrides["baseline_width"] = None
    try:
        preset = get_preset(args.preset, **overrides)
    except ConfigError as err:  # an unknown preset or an override out of range
        print(f"equidiff train: {err}", file=sys.stderr)
        return 2
    data_cfg = DatasetConfig.from_preset(
        preset,
        resolution=lab.workspace.resolution,
        grid=VoxelGridSpec.of(lab.workspace, lab.base_frame),  # every bag's grids must be this lab's
        state_tolerance_s=args.tolerance,
        cache_dir=str(args.cache_dir or out / "dataset_cache"),
    )
    episodes, skipped = load_episodes(args.bags, data_cfg, log=say)
    if not episodes:
        print("equidiff train: no usable episodes", file=sys.stderr)
        return 1
    train_eps, val_eps = _load_split(out, episodes, args.val_fraction, args.seed, args.resume, write=main)
    train_set, val_set = DemoDataset(train_eps, data_cfg), DemoDataset(val_eps, data_cfg) if val_eps else None
    if len(train_set) == 0:
        print(
            "equidiff train: the training episodes are too short for one window "
            f"(need >= {preset.horizon - preset.n_action_steps + 1} observations)",
            file=sys.stderr,
        )
        return 1
    say(
        f"{len(train_eps)} train episodes ({len(train_set)} samples), "
        f"{len(val_eps)} held out ({len(val_set) if val_set else 0} samples), {len(skipped)} skipped; "
        f"{args.policy} / {preset.name}"
        + (f"; {dist_info.world_size} data-parallel ranks ({dist_info.backend})" if dist_info.distributed else "")
    )

    try:
        cfg = TrainConfig(
            steps=args.steps,
            batch_size=args.batch_size,
            lr=args.lr,
            warmup_steps=args.warmup_steps,
            ema=args.ema,
            noise_repeats=args.noise_repeats,
            seed=args.seed,
            device=args.device,
            eval_every=args.eval_every,
            checkpoint_every=args.checkpoint_every,
            num_workers=args.num_workers,
            max_minutes=args.max_minutes,
            precision=args.precision,
            data=args.data,
        )
    except ValueError as err:  # a setting out of range, e.g. --noise-repeats 0
        print(f"equidiff train: {err}", file=sys.stderr)
        return 2
    seed_everything(args.seed)  # the initial weights come from the global RNG: seed before building
    policy = make_policy(args.policy, preset, lab.workspace)
    start_step = 0
    if main and args.resume and (out / "last.ckpt").exists():  # for the progress bar
        start_step = int(load_training_checkpoint(out / "last.ckpt")["step"])
    callbacks = [
        ActionMseEvaluator(
            policy,
            val_set if val_set is not None else train_set,
            args.eval_max_samples,
            min(args.batch_size, 32),
            args.seed,
            "val" if val_set is not None else "train",
        ),
        ProgressBar(args.steps, start_step, main and not args.no_progress),
        PlotWriter(out / "training.png", []),
    ]
    if args.rerun and main:
        try:  # rerun-sdk is an optional extra: imported only when asked for
            from equidiff_core.viz.training import RerunTrainingCallback
        except ImportError as err:
            print(f"equidiff train: --rerun needs the viz extra (rerun-sdk): {err}", file=sys.stderr)
            return 2
        callbacks.append(RerunTrainingCallback.from_target(args.rerun))
    try:
        result = train(policy, train_set, val_set, cfg, out, callbacks=callbacks)
    except TrainingError as err:
        print(f"equidiff train: {err}", file=sys.stderr)
        return 1
    if not main:
        return 0
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
    }
    if result.stopped:
        summary["stopped"] = result.stopped
    # what trained this policy, for whoever evaluates it elsewhere (bench generalization --trained)
    recipe = {
        "device": str(next(policy.parameters()).device),
        "preset": preset.name,
        "rotation_aug": preset.rotation_aug,
        "schedule_steps": args.steps,  # the cosine schedule's length; "steps" above is how many ran
        "batch_size": args.batch_size,
        "lr": args.lr,
        "warmup_steps": args.warmup_steps,
        "noise_repeats": args.noise_repeats,
        "ema": args.ema,
        "seed": args.seed,
        "max_minutes": args.max_minutes,
        "world_size": result.world_size,
        "precision": result.precision,
        "data": result.data,
    }
    (out / "run.json").write_text(json.dumps({**summary, "recipe": recipe}, indent=1) + "\n")
    print(json.dumps(summary))
    return 0
