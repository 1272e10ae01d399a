"""What a training run is asked for (``TrainConfig``), what it gives back (``TrainResult``), and how
``auto`` device, precision and data source resolve on this machine (used by ``training.loop.train``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch.utils.data import Dataset

from ..runtime.machine import PRECISIONS
from . import distributed
from .batches import estimate_nbytes

DATA_SOURCES = ("auto", "device", "loader")
# data "auto" keeps the training set on the GPU when it takes at most this share of the free memory
DEVICE_DATA_SHARE = 0.5


class TrainingError(RuntimeError):
    pass


@dataclass(frozen=True)
class TrainConfig:
    steps: int = 10000
    batch_size: int = 64
    lr: float = 1e-4
    weight_decay: float = 1e-6
    betas: tuple[float, float] = (0.95, 0.999)  # diffusion_policy's AdamW betas
    warmup_steps: int = 500
    ema: bool = False  # the paper's real-robot runs disable EMA
    ema_decay: float = 0.9999  # upper bound of diffusers' warm-up decay schedule
    seed: int = 0
    device: str = "auto"  # "auto" (cuda if available), "cpu", "cuda", "cuda:1"
    eval_every: int = 500  # 0: never
    eval_samples: int = 4  # validation samples passed to on_eval callbacks (DDIM sampled)
    val_batches: int = 4  # batches of the validation set averaged into val_loss
    checkpoint_every: int = 1000  # 0: only at the end
    log_every: int = 10
    num_workers: int = 0
    grad_clip: float = 0.0  # 0: off
    noise_repeats: int = 1  # (noise, step) draws per observation per step, see DiffusionPolicy.compute_loss
    # wall-clock budget: stop after the step that crosses it, then checkpoint and export as usual
    # (the cosine schedule stays the one for ``steps``); None: no limit
    max_minutes: float | None = None
    precision: str = "auto"  # "auto": bf16 autocast on CUDA, fp32 on the CPU; "fp32"; "bf16" (autocast)
    # "auto": the whole set on the device on CUDA (if it fits, see DEVICE_DATA_SHARE), a DataLoader on
    # the CPU; "device"; "loader"
    data: str = "auto"

    def __post_init__(self):
        if self.steps < 0 or self.batch_size < 1:
            raise ValueError("steps must be >= 0 and batch_size >= 1")
        if self.max_minutes is not None and not self.max_minutes > 0:
            raise ValueError(f"max_minutes must be positive, got {self.max_minutes}")
        if self.noise_repeats < 1:
            raise ValueError(f"noise_repeats must be >= 1, got {self.noise_repeats}")
        if not self.lr > 0:  # NaN included
            raise ValueError(f"lr must be positive, got {self.lr}")
        if not 0.0 < self.ema_decay < 1.0:
            raise ValueError("ema_decay must be in (0, 1)")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {self.precision!r}")
        if self.data not in DATA_SOURCES:
            raise ValueError(f"data must be one of {DATA_SOURCES}, got {self.data!r}")


@dataclass
class TrainResult:
    checkpoint: Path
    exported: Path
    history: list[dict] = field(default_factory=list)
    steps: int = 0  # steps trained in all (fewer than asked when max_minutes stopped the run)
    stopped: str | None = None  # why this run ended before cfg.steps (also kept in history)
    world_size: int = 1  # data-parallel processes that trained it
    precision: str = "fp32"  # what "auto" resolved to
    data: str = "loader"


def resolve_device(device: str) -> torch.device:
    """ "auto": CUDA if available; under torchrun on CUDA "auto" and "cuda" mean this rank's ``cuda:LOCAL_RANK``."""
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise TrainingError(f"device {device!r} requested but CUDA is not available")
    if device == "cuda" and distributed.launched_by_torchrun():
        return torch.device("cuda", distributed.env_local_rank())
    return torch.device(device)


def resolve_precision(precision: str, device: torch.device) -> str:
    """ "auto": bf16 autocast on CUDA; fp32 on the CPU (bf16 autocast trained no faster there even on a CPU
    with AVX512-BF16: ``equidiff bench train --cpu-precision bf16``, docs/model.md)."""
    if precision != "auto":
        return precision
    return "bf16" if device.type == "cuda" else "fp32"


def resolve_data(cfg: TrainConfig, train_set: Dataset, device: torch.device) -> str:
    if cfg.data != "auto":
        return cfg.data
    if device.type != "cuda":
        return "loader"
    free, _ = torch.cuda.mem_get_info(device)
    return "device" if estimate_nbytes(train_set) <= DEVICE_DATA_SHARE * free else "loader"
