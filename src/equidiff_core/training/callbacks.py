"""What ``equidiff train`` hooks into ``training.loop.train``: the held-out action error, a progress bar and the plot."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure
from tqdm import tqdm


class ActionMseEvaluator:
    """on_eval: DDIM-sample the held-out set and add ``val_action_mse`` (+ position/width errors) to the metrics.

    Without held-out episodes (``--val-fraction 0``) it scores training samples and says so
    (``train_action_mse``)."""

    def __init__(self, policy, val_set, max_samples: int, batch_size: int, seed: int, prefix: str = "val"):
        self.policy, self.val_set, self.prefix = policy, val_set, prefix
        self.max_samples, self.batch_size, self.seed = max_samples, batch_size, seed

    def on_eval(self, step, metrics, samples):
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
    train = [(h["step"], h["loss"]) for h in history if "loss" in h]
    evals = [h for h in history if "val_loss" in h]
    fig = Figure(figsize=(11, 4))  # no pyplot: no backend or global figure state
    axes = fig.subplots(1, 2)
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
