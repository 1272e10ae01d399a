"""The training loop shared by EquiDiff and the baseline (used by ``equidiff train``).

AdamW (lr 1e-4, weight decay 1e-6), cosine schedule with 500 warm-up steps (diffusers'
``get_cosine_schedule_with_warmup``), optional EMA, CPU or CUDA picked automatically.

On CUDA the forward pass runs under bf16 autocast (weights, gradients and optimiser stay fp32)
and the whole training set sits on the GPU (``training.batches.DeviceBatchSource``); on the CPU training
stays fp32 and draws batches through a DataLoader (``precision`` / ``data`` override both).

Launched by torchrun (``distributed.py``), each process trains one data-parallel replica:
DistributedDataParallel averages the gradients, every rank draws a disjoint shard of each epoch,
rank 0 alone evaluates and writes checkpoints, history and the export. The logged loss is the
mean over ranks.

EMA: escnn 1.0.11 modules cannot be deep-copied (GroupElement.__hash__ raises), so instead of
diffusion_policy's ``deepcopy(model)`` we keep diffusers' ``EMAModel`` over the parameter
tensors and swap the averaged weights in for evaluation and export.

Files in ``out_dir``: ``last.ckpt`` (resumable: weights, optimiser, schedule, EMA, step,
history, config; loads with ``torch.load(weights_only=True)``), ``history.json`` and
``policy.pt`` (the exported inference policy, see ``policy/inference.py``). ``without_optimizer_state``
writes a checkpoint to share without the optimiser's moments; it still resumes, with fresh moments.

The run's configuration, its result and the resolution of ``auto`` settings are in ``training.config``.
"""

from __future__ import annotations

import contextlib
import json
import math
import random
import time
from collections.abc import Iterable
from contextvars import ContextVar
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from ..config import Workspace, from_dict, to_dict
from ..models.state import learned_state_dict, load_learned_state, parameters_only, refresh_escnn_caches
from ..policy.diffusion import DiffusionPolicy, make_policy
from ..policy.file import (
    HASH_KEY,
    CheckpointError,
    CheckpointFormatError,
    export_policy,
    load_checked,
    read_policy_file,
    save_atomically,
    weights_sha256,
)
from ..policy.normalizer import Normalizer
from ..policy.presets import preset_from_dict
from . import distributed
from .batches import DeviceBatchSource, loader_batches, make_sampler
from .config import (
    TrainConfig,
    TrainingError,
    TrainResult,
    resolve_data,
    resolve_device,
    resolve_precision,
)

CKPT_FORMAT = "equidiff_train_ckpt"
CKPT_VERSION = 1


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def fit_normalizer(dataset: Dataset, workspace) -> Normalizer:
    """From ``data.dataset.normalizer_arrays() -> (actions (N, 10), ee (N, 10))`` if it has one (cheap),
    else by reading every sample's action and ee."""
    if hasattr(dataset, "normalizer_arrays"):
        actions, ee = dataset.normalizer_arrays()
    else:
        items = [dataset[i] for i in range(len(dataset))]
        actions = np.concatenate([np.asarray(s["action"]).reshape(-1, 10) for s in items])
        ee = np.concatenate([np.asarray(s["ee"]).reshape(-1, 10) for s in items])
    return Normalizer.fit(actions, ee, workspace)


class Ema:
    """diffusers' EMAModel over the parameters (no deepcopy of the escnn model)."""

    def __init__(self, policy: DiffusionPolicy, decay: float):
        from diffusers.training_utils import EMAModel

        self.params = list(policy.model.parameters())
        self.ema = EMAModel(self.params, decay=decay, use_ema_warmup=True, power=0.75)
        self.model = policy.model

    def step(self):
        self.ema.step(self.params)

    def copy_to_model(self):
        """Leave the averaged weights in the model (a policy loaded to run, not to train on)."""
        self.ema.copy_to(self.params)
        refresh_escnn_caches(self.model)

    @contextlib.contextmanager
    def swapped_in(self):
        self.ema.store(self.params)
        self.copy_to_model()
        try:
            yield
        finally:
            self.ema.restore(self.params)
            refresh_escnn_caches(self.model)

    def state_dict(self):
        return self.ema.state_dict()

    def load_state_dict(self, state):
        self.ema.load_state_dict(state)


_PREVIOUS_OPTIMIZER_STEP: ContextVar[bool] = ContextVar("previous_optimizer_step", default=False)


@contextlib.contextmanager
def previous_optimizer_step():
    """Training inside steps its optimiser as it did before ``adamw`` and the cached parameter list: AdamW's loop
    over every tensor, and the gradient clip walking the model each step (``equidiff bench train --variants
    previous_optimizer_step``)."""
    token = _PREVIOUS_OPTIMIZER_STEP.set(True)
    try:
        yield
    finally:
        _PREVIOUS_OPTIMIZER_STEP.reset(token)


def adamw(params: list[torch.nn.Parameter], **hyper) -> torch.optim.AdamW:
    """AdamW over ``params`` through torch's fused kernel where it has one (CPU and CUDA tensors): one pass over
    all the tensors, where the default loops over EquiDiff's many small ones (docs/results/model.md, "What a CPU
    training step costs"). The same update, to fp32 rounding."""
    fused = all(p.device.type in ("cpu", "cuda") for p in params) and not _PREVIOUS_OPTIMIZER_STEP.get()
    return torch.optim.AdamW(params, fused=fused or None, **hyper)


def _to_numpy(x):
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


class _PolicyLoss(torch.nn.Module):
    """``policy.compute_loss`` as a module's forward: DistributedDataParallel averages gradients only
    for what runs through its forward."""

    def __init__(self, policy: DiffusionPolicy):
        super().__init__()
        self.policy = policy

    def forward(self, batch: dict, generator: torch.Generator, noise_repeats: int) -> torch.Tensor:
        return self.policy.compute_loss(batch, generator=generator, noise_repeats=noise_repeats)


def train(
    policy: DiffusionPolicy,
    train_set: Dataset,
    val_set: Dataset | None,
    cfg: TrainConfig,
    out_dir: str | Path,
    callbacks: Iterable[Any] = (),
) -> TrainResult:
    """Train ``policy`` for ``cfg.steps`` in all (resuming ``out_dir/last.ckpt`` when it exists).

    Under torchrun every rank calls this with the same arguments; callbacks run on rank 0 only."""

    out_dir = Path(out_dir)
    device = resolve_device(cfg.device)
    try:
        dist_info = distributed.init_from_env(device.type)
    except distributed.DistributedError as err:
        raise TrainingError(str(err)) from err
    main = dist_info.is_main
    if main:
        out_dir.mkdir(parents=True, exist_ok=True)
    callbacks = list(callbacks) if main else []
    precision = resolve_precision(cfg.precision, device)
    data = resolve_data(cfg, train_set, device)
    seed_everything(cfg.seed)
    if len(train_set) == 0:
        raise TrainingError("training set is empty")
    if policy.normalizer is None:
        policy.set_normalizer(fit_normalizer(train_set, policy.workspace))
    policy.to(device)

    from diffusers.optimization import get_cosine_schedule_with_warmup

    # Listed once: each walk of an escnn model hashes every basis expansion, and the gradient clip would walk it
    # every step.
    params = list(policy.model.parameters())
    # A checkpoint's optimiser state brings its own kernel choice: one written before ``adamw`` resumes unfused.
    optimizer = adamw(params, lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay)
    walk_each_step = _PREVIOUS_OPTIMIZER_STEP.get()
    scheduler = get_cosine_schedule_with_warmup(optimizer, cfg.warmup_steps, max(cfg.steps, 1))
    ema = Ema(policy, cfg.ema_decay) if cfg.ema else None
    history: list[dict] = []
    step = 0

    ckpt_path = out_dir / "last.ckpt"
    # rank 0 reads the checkpoint and hands it to the others: all ranks resume from the same state
    state = distributed.broadcast_object(load_training_checkpoint(ckpt_path) if main and ckpt_path.exists() else None)
    if state is not None:
        if state["config"]["policy"] != policy.name or state["config"]["preset"] != policy.preset.to_dict():
            raise TrainingError(f"{ckpt_path} was written for a different policy/preset; use a new out_dir")
        load_learned_state(policy.model, state["model"])
        step = int(state["step"])
        history = json.loads(state["history_json"])
        if state["optimizer"] is not None:
            optimizer.load_state_dict(state["optimizer"])
        else:  # shared without it (without_optimizer_state): AdamW re-estimates its moments from here
            history.append({"step": step, "resumed": "without optimiser state: fresh AdamW moments"})
        # the learning rate is the schedule's at this step (a longer --steps stretches the schedule)
        scheduler.load_state_dict(state["lr_scheduler"])
        for group, base_lr, factor in zip(optimizer.param_groups, scheduler.base_lrs, scheduler.lr_lambdas):
            group["lr"] = base_lr * factor(scheduler.last_epoch)
        if ema is not None and state.get("ema") is not None:
            ema.load_state_dict(state["ema"])
        policy.set_normalizer(Normalizer.from_dict(state["config"]["normalizer"]))
    del state

    def save_checkpoint():
        if not main:
            return
        state = {
            "format": CKPT_FORMAT,
            "version": CKPT_VERSION,
            "step": step,
            "config": policy.config_dict(),
            "train_config": to_dict(cfg),
            "model": learned_state_dict(policy.model),
            "optimizer": optimizer.state_dict(),
            "lr_scheduler": scheduler.state_dict(),
            "ema": ema.state_dict() if ema else None,
            "history_json": json.dumps(history),
        }
        state[HASH_KEY] = weights_sha256(state["model"])  # checked at load
        save_atomically(state, ckpt_path)
        (out_dir / "history.json").write_text(json.dumps(history, indent=1))

    loss_fn: torch.nn.Module = _PolicyLoss(policy)
    if dist_info.distributed:
        import inspect

        from torch.nn.parallel import DistributedDataParallel as DDP

        # rank 0's weights and buffers are broadcast once; no buffer sync per step: the models' buffers
        # are constants (no batch norm statistics). Newer torch renamed broadcast_buffers.
        no_buffer_sync = (
            "forward_sync_buffers"
            if "forward_sync_buffers" in inspect.signature(DDP).parameters
            else "broadcast_buffers"
        )
        loss_fn = DDP(loss_fn, device_ids=[device] if device.type == "cuda" else None, **{no_buffer_sync: False})
    # every rank: the same epoch permutations (sampler seed), its own augmentation and noise draws
    sampler = make_sampler(train_set, cfg.seed + step, dist_info.rank, dist_info.world_size)
    if data == "device":
        batches = DeviceBatchSource.from_dataset(train_set, device).batches(sampler, cfg.batch_size)
    else:
        batches = loader_batches(train_set, sampler, cfg.batch_size, cfg.num_workers)
    aug_gen = torch.Generator().manual_seed(cfg.seed * 7919 + step + 1_000_003 * dist_info.rank)
    autocast = (
        (lambda: torch.autocast(device.type, dtype=torch.bfloat16)) if precision == "bf16" else contextlib.nullcontext
    )

    t_last = time.perf_counter()
    deadline = None if cfg.max_minutes is None else time.monotonic() + 60.0 * cfg.max_minutes
    stopped = None
    past_deadline = False
    while step < cfg.steps:
        if past_deadline:
            stopped = f"time budget of {cfg.max_minutes:g} min reached"
            history.append({"step": step, "stopped": stopped})
            break
        if (
            not policy.training
        ):  # back from an evaluation; escnn's train() walks and hashes every basis, so not every step
            policy.train()
        t_data = time.perf_counter()
        batch = next(batches)
        data_s = time.perf_counter() - t_data  # the loader's share of the step (bench train reports it)
        with autocast():
            loss = loss_fn(batch, aug_gen, cfg.noise_repeats)
        # one collective a step: the mean loss (a NaN anywhere stops every rank together) and whether
        # any rank is past the time budget (all stop after the same step)
        loss_sum, late = distributed.all_reduce_sum(
            [float(loss.item()), float(deadline is not None and time.monotonic() > deadline)],
            device if dist_info.backend == "nccl" else "cpu",
        )
        mean_loss = loss_sum / dist_info.world_size
        past_deadline = late > 0
        if not math.isfinite(mean_loss):
            raise TrainingError(f"loss became {mean_loss} at step {step}")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if cfg.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(policy.model.parameters() if walk_each_step else params, cfg.grad_clip)
        optimizer.step()
        scheduler.step()
        if ema is not None:
            ema.step()
        step += 1
        metrics = {"step": step, "loss": mean_loss, "lr": scheduler.get_last_lr()[0], "data_s": data_s}
        if step % cfg.log_every == 0 or step == 1 or step == cfg.steps:
            now = time.perf_counter()
            metrics["sec_per_step"] = (now - t_last) / (cfg.log_every if step > 1 else 1)
            t_last = now
            history.append(metrics)
        for cb in callbacks:
            if hasattr(cb, "on_step"):
                cb.on_step(step, metrics)
        if main and cfg.eval_every and (step % cfg.eval_every == 0 or step == cfg.steps):
            # the other ranks wait in the next step's collectives meanwhile
            with ema.swapped_in() if ema else contextlib.nullcontext():
                ev, samples = evaluate(policy, val_set if val_set is not None else train_set, cfg, device)
            ev["step"] = step
            history.append(ev)
            for cb in callbacks:
                if hasattr(cb, "on_eval"):
                    cb.on_eval(step, ev, samples)
        if cfg.checkpoint_every and step % cfg.checkpoint_every == 0 and step < cfg.steps:
            save_checkpoint()

    if dist_info.distributed:
        # DDP keeps replicas equal by construction; check it, since a diverged rank 0 would be saved silently
        digests = distributed.all_gather_object(distributed.parameter_digest(policy.model))
        if len(set(digests)) > 1:
            raise TrainingError(f"data-parallel ranks diverged: parameter digests {digests}")
        history.append(
            {"step": step, "world_size": dist_info.world_size, "backend": dist_info.backend, "param_digests": digests}
        )
    save_checkpoint()
    exported = out_dir / "policy.pt"
    if main:
        with ema.swapped_in() if ema else contextlib.nullcontext():
            export_policy(policy, exported)
    distributed.barrier()  # every rank returns once the files are written
    result = TrainResult(ckpt_path, exported, history, step, stopped, dist_info.world_size, precision, data)
    for cb in callbacks:
        if hasattr(cb, "on_end"):
            cb.on_end(result)
    return result


@torch.no_grad()
def evaluate(policy: DiffusionPolicy, dataset: Dataset, cfg: TrainConfig, device) -> tuple[dict, list[dict]]:
    """Validation diffusion loss (fixed seed) and DDIM-sampled predictions for a few samples."""
    policy.eval()
    gen = torch.Generator().manual_seed(12345)
    loader = DataLoader(dataset, batch_size=cfg.batch_size, shuffle=False, num_workers=0)
    losses = []
    first = None
    for i, batch in enumerate(loader):
        if i >= cfg.val_batches:
            break
        first = first if first is not None else batch
        losses.append(float(policy.compute_loss(batch, generator=gen)))
    metrics: dict = {"val_loss": float(np.mean(losses)) if losses else math.nan}
    samples: list[dict] = []
    if first is not None and cfg.eval_samples > 0:
        n = min(cfg.eval_samples, first["voxels"].shape[0])
        out = policy.predict_action(
            {"voxels": first["voxels"][:n], "ee": first["ee"][:n]},
            generator=torch.Generator(device=device).manual_seed(0),
        )
        pred = _to_numpy(out["action_pred"])
        gt = _to_numpy(first["action"][:n])
        ee = _to_numpy(first["ee"][:n, -1])
        samples = [{"pred": pred[j], "gt": gt[j], "ee": ee[j]} for j in range(n)]
        metrics["val_pos_err_m"] = float(np.linalg.norm(pred[..., :3] - gt[..., :3], axis=-1).mean())
        metrics["val_width_err_m"] = float(np.abs(pred[..., 9] - gt[..., 9]).mean())
    return metrics, samples


def load_training_checkpoint(path: str | Path) -> dict:
    return load_checked(path, CKPT_FORMAT, CKPT_VERSION, "checkpoint", "an equidiff training checkpoint", "model")


def without_optimizer_state(path: str | Path, out: str | Path) -> Path:
    """Write ``path``'s training checkpoint to ``out`` without AdamW's moments, for sharing.

    The moments are as large as the weights and the EMA together; the rest (weights, EMA,
    schedule, step, history, recipe) is kept, so the file still loads as a policy and resumes:
    ``train`` then continues the schedule with fresh moments and notes it in the history."""
    state = load_training_checkpoint(path)
    state["optimizer"] = None
    return save_atomically(state, Path(out))


def slim_checkpoint(path: str | Path, out: str | Path) -> Path:
    """The smallest file that reproduces a finished run's policy, for committing: ``path``'s training
    checkpoint with the weights the run exports (the EMA when it kept one) as its only weights, and only
    the parameters (escnn's sampled bases are rebuilt with the model), no raw weights, EMA or optimiser
    moments; history, schedule and config stay. For the compact EquiDiff it holds the 1.3 M escnn
    parameters (~5 MB) where the exported ``policy.pt`` holds the expanded plain filters (~16 MB). ``load_policy_from_checkpoint`` and ``export_policy`` rebuild the exported policy
    from it exactly; a resume from it would start from the averaged weights with fresh moments."""
    state = load_training_checkpoint(path)
    policy = load_policy_from_checkpoint(path, ema=True)
    state["model"] = parameters_only(policy.model)
    state[HASH_KEY] = weights_sha256(state["model"])
    state["ema"] = None
    state["optimizer"] = None
    history = json.loads(state["history_json"])
    history.append({"step": int(state["step"]), "slimmed": "weights are the exported (EMA) ones; no optimiser state"})
    state["history_json"] = json.dumps(history)
    return save_atomically(state, Path(out))


def load_policy_from_checkpoint(path: str | Path, device: str = "cpu", ema: bool = True) -> DiffusionPolicy:
    """Rebuild the training-time policy (escnn for EquiDiff) from ``last.ckpt`` or an exported ``policy.pt``.

    From a run that kept an EMA (``TrainConfig.ema``), ``last.ckpt`` gives the EMA weights: the
    ones training exports to ``policy.pt`` and a robot runs. ``ema=False`` gives the raw
    training weights instead (where training resumes from).
    An exported file holds plain-torch weights: for the baseline they load as-is; for EquiDiff
    use ``policy.inference.load_inference_policy`` instead (the escnn parameters are not recoverable
    from expanded filters)."""
    path = Path(path)
    ema_state = None
    try:
        state = load_training_checkpoint(path)
        config, weights = state["config"], state["model"]
        ema_state = state.get("ema") if ema else None
    except CheckpointFormatError as train_err:  # only another format is worth the other loader
        try:
            config, weights = read_policy_file(path)
        except CheckpointFormatError:
            raise CheckpointError(
                f"{train_err}; not an exported equidiff policy either (last.ckpt or policy.pt expected)"
            ) from None
        if config.get("policy") != "baseline":
            raise CheckpointError(
                f"{path}: an exported EquiDiff policy has no escnn weights; use last.ckpt "
                "or policy.inference.load_inference_policy"
            ) from None
    try:
        policy = make_policy(
            config["policy"],
            preset_from_dict(config["preset"]),
            from_dict(Workspace, config["workspace"], where="workspace"),
        )
        if config.get("normalizer") is not None:
            policy.set_normalizer(Normalizer.from_dict(config["normalizer"]))
        load_learned_state(policy.model, weights)
        if ema_state is not None:
            averaged = Ema(policy, TrainConfig.ema_decay)  # the saved state brings its own decay
            averaged.load_state_dict(ema_state)
            averaged.copy_to_model()
    except (KeyError, ValueError, RuntimeError) as err:
        raise CheckpointError(f"{path}: incompatible checkpoint: {str(err).splitlines()[0]}") from err
    return policy.to(resolve_device(device)).eval()
