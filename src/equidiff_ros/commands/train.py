"""`equidiff train BAGS... --out DIR`: train EquiDiff or the baseline from recorded episodes.

Bags -> ``DemoDataset`` (decoded once, cached under ``--cache-dir``), whole episodes held out
for validation (``--val-fraction``, split saved in ``DIR/split.json`` and reused on resume),
then ``equidiff_core.training.train`` (AdamW + cosine, periodic checkpoints, resume from
``DIR/last.ckpt``); ``DIR/run.json`` keeps the summary and the recipe (device, batch, lr, ...).
On every evaluation the held-out episodes are sampled with DDIM and
scored by action MSE (absolute targets, metres/rot6d/metres); ``DIR/training.png`` plots the
loss and the evaluation curves. Deterministic for a given ``--seed`` on the same device.

Data-parallel on several GPUs (or CPU processes) with torchrun, e.g.
``torchrun --nproc-per-node 4 -m equidiff_ros.cli train bags/ --out runs/ddp --device cuda``:
every rank decodes the same episodes and split, rank 0 alone writes files and prints
(``equidiff_core.distributed``). ``--batch-size`` is per rank.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from equidiff_core.observation import STATE_TOLERANCE_S


def add_arguments(parser) -> None:
    from equidiff_core.presets import BASELINE_INITS, ROTATION_AUGS

    parser.add_argument("bags", nargs="+", help="bag directories, or folders holding bag directories")
    parser.add_argument("--out", required=True, help="output directory (checkpoints, policy.pt, plots)")
    parser.add_argument("--policy", choices=("equidiff", "baseline"), default="equidiff")
    parser.add_argument("--preset", default="compact", help="model preset: paper, compact or tiny (default compact)")
    parser.add_argument(
        "--rotation-aug",
        choices=ROTATION_AUGS,
        default=None,
        help="random yaw rotation of voxels, state and actions while training (default: the preset's)",
    )
    parser.add_argument(
        "--baseline-width",
        type=int,
        default=None,
        help="the baseline encoder's n_hidden (official channels n/16 ... n; default: the preset's; 0: channels "
        "matched to EquiDiff's parameter count, the baselines trained before the width existed)",
    )
    parser.add_argument(
        "--baseline-init",
        choices=BASELINE_INITS,
        default=None,
        help="the baseline encoder's initialisation: torch (PyTorch's default) or he (default: the preset's)",
    )
    parser.add_argument("--steps", type=int, default=20000)
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--lr", type=float, default=1e-4)
    parser.add_argument("--warmup-steps", type=int, default=500)
    parser.add_argument(
        "--ema", action="store_true", help="keep an EMA of the weights (the paper's real-robot runs do not)"
    )
    parser.add_argument(
        "--noise-repeats",
        type=int,
        default=1,
        help="(noise, step) draws per observation per step, one encoder pass for all (default 1, the paper's)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    parser.add_argument("--val-fraction", type=float, default=0.1, help="fraction of episodes held out (default 0.1)")
    parser.add_argument("--eval-every", type=int, default=1000)
    parser.add_argument(
        "--eval-max-samples",
        type=int,
        default=64,
        help="held-out samples scored by action MSE at each evaluation (DDIM sampling)",
    )
    parser.add_argument("--checkpoint-every", type=int, default=1000)
    parser.add_argument(
        "--max-minutes",
        type=float,
        default=None,
        help="stop after this much training time, then checkpoint and export as at the end",
    )
    parser.add_argument("--num-workers", type=int, default=0)
    parser.add_argument(
        "--precision",
        choices=("auto", "fp32", "bf16"),
        default="auto",
        help="auto: bf16 autocast on CUDA, fp32 on the CPU",
    )
    parser.add_argument(
        "--data",
        choices=("auto", "device", "loader"),
        default="auto",
        help="auto: the whole training set on the GPU when it fits in half its free memory, a DataLoader on the CPU",
    )
    parser.add_argument("--resume", action="store_true", help="continue from OUT/last.ckpt")
    parser.add_argument("--lab-config", help="lab.yaml (workspace); default: the installed one")
    parser.add_argument("--cache-dir", help="decoded-episode cache (default OUT/dataset_cache)")
    parser.add_argument("--tolerance", type=float, default=STATE_TOLERANCE_S, help="state/voxel stamp tolerance, s")
    parser.add_argument("--rerun", metavar="FILE.rrd|spawn|HOST:PORT", help="also log training to rerun")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar (logs every eval instead)")


class ActionMseEvaluator:
    """on_eval: DDIM-sample the held-out set and add ``val_action_mse`` (+ position/width errors) to the metrics.

    Without held-out episodes (``--val-fraction 0``) it scores training samples and says so
    (``train_action_mse``)."""

    def __init__(self, policy, val_set, max_samples: int, batch_size: int, seed: int, prefix: str = "val"):
        self.policy, self.val_set, self.prefix = policy, val_set, prefix
        self.max_samples, self.batch_size, self.seed = max_samples, batch_size, seed

    def on_eval(self, step, metrics, samples):
        import numpy as np
        import torch

        if self.val_set is None or len(self.val_set) == 0 or self.max_samples <= 0:
            return
        n = min(self.max_samples, len(self.val_set))
        # evenly spread over the held-out episodes, same samples at every evaluation
        idx = np.unique(np.linspace(0, len(self.val_set) - 1, n).round().astype(int))
        gen = torch.Generator().manual_seed(self.seed)
        was_training = self.policy.training
        self.policy.eval()
        sq, pos, width = [], [], []
        with torch.no_grad():
            for a in range(0, len(idx), self.batch_size):
                items = [self.val_set[int(i)] for i in idx[a : a + self.batch_size]]
                batch = {k: torch.stack([it[k] for it in items]) for k in ("voxels", "ee", "action")}
                noise = torch.randn((len(items), self.policy.preset.horizon, self.policy.codec.dim), generator=gen)
                out = self.policy.predict_action(
                    {"voxels": batch["voxels"], "ee": batch["ee"]},
                    noise=noise.to(next(self.policy.parameters()).device),
                )
                pred = out["action_pred"].detach().cpu().double()
                gt = batch["action"].double()
                sq.append(((pred - gt) ** 2).mean(dim=(1, 2)))
                pos.append((pred[..., :3] - gt[..., :3]).norm(dim=-1).mean(dim=1))
                width.append((pred[..., 9] - gt[..., 9]).abs().mean(dim=1))
        self.policy.train(was_training)
        p = self.prefix
        metrics[f"{p}_action_mse"] = float(torch.cat(sq).mean())
        metrics[f"{p}_action_pos_err_m"] = float(torch.cat(pos).mean())
        metrics[f"{p}_action_width_err_m"] = float(torch.cat(width).mean())
        metrics[f"{p}_action_samples"] = len(idx)


class ProgressBar:
    def __init__(self, total: int, initial: int, enabled: bool):
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=initial, unit="step", dynamic_ncols=True, file=sys.stderr)
        self.last_eval = ""

    def on_step(self, step, metrics):
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix_str(f"loss {metrics['loss']:.4f}{self.last_eval}", refresh=False)

    def on_eval(self, step, metrics, samples):
        mse = metrics.get("val_action_mse", metrics.get("train_action_mse"))
        self.last_eval = f" val_mse {mse:.5f}" if mse is not None else f" val_loss {metrics.get('val_loss', 0):.4f}"
        line = f"step {step}: " + ", ".join(f"{k} {v:.5g}" for k, v in metrics.items() if isinstance(v, float))
        (self.bar.write if self.bar is not None else print)(line)

    def on_end(self, result):
        if self.bar is not None:
            self.bar.close()


def plot_history(history: list[dict], path: Path) -> Path:
    """Training loss (and its running mean) and the evaluation curves, one PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    train = [(h["step"], h["loss"]) for h in history if "loss" in h]
    evals = [h for h in history if "val_loss" in h]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    ax = axes[0]
    if train:
        s, l = map(np.asarray, zip(*train))
        ax.plot(s, l, lw=0.8, alpha=0.5, label="train loss")
        k = max(1, len(l) // 20)
        if k > 1 and len(l) > k:
            ax.plot(s[k - 1 :], np.convolve(l, np.ones(k) / k, mode="valid"), lw=1.5, label=f"mean of {k}")
    if evals:
        ax.plot([h["step"] for h in evals], [h["val_loss"] for h in evals], "o-", label="val loss")
    ax.set_xlabel("step")
    ax.set_ylabel("diffusion loss (noise MSE)")
    ax.set_yscale("log")
    ax.legend()
    ax = axes[1]
    p = "val" if any("val_action_mse" in h for h in evals) else "train"
    mse = [(h["step"], h[f"{p}_action_mse"]) for h in evals if f"{p}_action_mse" in h]
    if mse:
        ax.plot(*zip(*mse), "o-", label="held-out action MSE" if p == "val" else "training-set action MSE")
        ax.set_yscale("log")
        ax.legend(loc="upper left")
    pos = [(h["step"], h[f"{p}_action_pos_err_m"]) for h in evals if f"{p}_action_pos_err_m" in h]
    if pos:
        ax2 = ax.twinx()
        ax2.plot(*zip(*pos), "s--", color="tab:red", label="position error (m)")
        ax2.set_ylabel("mean position error, m")
        ax2.legend(loc="upper right")
    ax.set_xlabel("step")
    ax.set_ylabel("action MSE (absolute targets)")
    ax.set_title("evaluation on held-out episodes" if p == "val" else "evaluation (no held-out episodes)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


class PlotWriter:
    def __init__(self, path: Path, history_before: list[dict]):
        self.path, self.history = path, list(history_before)

    def on_step(self, step, metrics):
        pass

    def on_eval(self, step, metrics, samples):
        pass

    def on_end(self, result):
        plot_history(result.history, self.path)


def _load_split(out: Path, episodes, val_fraction: float, seed: int, resume: bool, write: bool = True):
    from equidiff_core.dataset import split_episodes

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


def run(args) -> int:
    from equidiff_core import distributed
    from equidiff_core.training import TrainingError, resolve_device

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
    from equidiff_core.config import ConfigError, default_config_dir, load_lab_config
    from equidiff_core.dataset import DatasetConfig, DemoDataset, load_episodes
    from equidiff_core.policies import make_policy
    from equidiff_core.presets import get_preset
    from equidiff_core.training import (
        TrainConfig,
        TrainingError,
        seed_everything,
        train,
    )

    out = Path(args.out)
    main = dist_info.is_main
    say = (lambda m: print(f"equidiff train: {m}", file=sys.stderr)) if main else (lambda m: None)
    if (out / "last.ckpt").exists() and not args.resume:
        # every rank sees the same: rank 0 writes the first checkpoint only after all ranks joined DDP
        print(
            f"equidiff train: {out}/last.ckpt exists; pass --resume to continue it or choose a new --out",
            file=sys.stderr,
        )
        return 2
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
        from equidiff_core.training import load_training_checkpoint

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
        try:
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
        "checkpoint": str(result.checkpoint),
        "policy": str(result.exported),
        "plot": str(out / "training.png"),
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
