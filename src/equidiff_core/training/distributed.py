"""Data-parallel training across processes with ``torch.distributed`` (used by ``training.loop.train``).

Launch with torchrun, one process per GPU (or per CPU socket), e.g.::

    torchrun --nproc-per-node 4 -m equidiff_ros.cli train bags/ --out runs/ddp --device cuda

torchrun sets ``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``, ``MASTER_ADDR`` and ``MASTER_PORT``;
:func:`init_from_env` joins the process group from them (NCCL on GPUs, gloo on the CPU), also
when torchrun started a single process (``--nproc-per-node 1``): a group of one runs the same
collectives and DDP wrapper as N GPUs, which is how one GPU checks the N-GPU path. Without
torchrun (``WORLD_SIZE`` unset or 1 and its rendezvous variables absent) every helper here
answers for a single process and does nothing, so the same code runs alone or in a group.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist


class DistributedError(RuntimeError):
    pass


@dataclass(frozen=True)
class DistInfo:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    backend: str | None = None  # None: a single process, no group

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        """In a process group (of one or more ranks): collectives and DDP run."""
        return self.backend is not None


def env_world_size() -> int:
    """The world size torchrun asked for (1 when not launched by torchrun)."""
    try:
        return int(os.environ.get("WORLD_SIZE", "1"))
    except ValueError as err:
        raise DistributedError(f"WORLD_SIZE={os.environ['WORLD_SIZE']!r} is not an integer") from err


TORCHRUN_VARIABLES = ("RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


def launched_by_torchrun() -> bool:
    """torchrun set this process's rendezvous (any world size, one included)."""
    return env_world_size() > 1 or all(k in os.environ for k in ("WORLD_SIZE", *TORCHRUN_VARIABLES))


def env_local_rank() -> int:
    """This process's index on its machine (torchrun's LOCAL_RANK; 0 when not launched by torchrun)."""
    return int(os.environ.get("LOCAL_RANK", "0"))


def backend_for(device_type: str) -> str:
    return "nccl" if device_type == "cuda" else "gloo"


def init_from_env(device_type: str | None = None) -> DistInfo:
    """Join the process group described by torchrun's environment (idempotent).

    ``device_type``: "cuda" or "cpu", picks NCCL or gloo; None: NCCL when CUDA is available. On
    CUDA each process then uses ``cuda:LOCAL_RANK``."""
    if dist.is_available() and dist.is_initialized():
        return info()
    if not launched_by_torchrun():
        return DistInfo()
    if not dist.is_available():
        raise DistributedError("launched by torchrun but this torch build has no torch.distributed")
    missing = [k for k in TORCHRUN_VARIABLES if k not in os.environ]
    if missing:
        raise DistributedError(f"WORLD_SIZE > 1 but {', '.join(missing)} unset: launch with torchrun")
    if device_type is None:
        device_type = "cuda" if torch.cuda.is_available() else "cpu"
    backend = backend_for(device_type)
    local_rank = env_local_rank()
    if backend == "nccl":
        if local_rank >= torch.cuda.device_count():
            raise DistributedError(f"LOCAL_RANK {local_rank} but only {torch.cuda.device_count()} GPUs here")
        torch.cuda.set_device(local_rank)
    dist.init_process_group(backend=backend)  # reads RANK, WORLD_SIZE, MASTER_ADDR, MASTER_PORT
    return info()


def info() -> DistInfo:
    if not (dist.is_available() and dist.is_initialized()):
        return DistInfo()
    return DistInfo(
        rank=dist.get_rank(), world_size=dist.get_world_size(), local_rank=env_local_rank(), backend=dist.get_backend()
    )


def rank() -> int:
    return info().rank


def world_size() -> int:
    return info().world_size


def is_main() -> bool:
    return info().is_main


def barrier() -> None:
    i = info()
    if i.distributed:
        # NCCL: name this rank's GPU, or the barrier guesses one (and warns)
        dist.barrier(device_ids=[torch.cuda.current_device()] if i.backend == "nccl" else None)


def all_reduce_sum(values: list[float], device: torch.device | str = "cpu") -> list[float]:
    """Element-wise sum over all ranks (one collective for the whole list); the values alone without a group."""
    if not info().distributed:
        return [float(v) for v in values]
    t = torch.tensor(values, dtype=torch.float64, device=device)  # gloo and NCCL both reduce doubles
    dist.all_reduce(t, op=dist.ReduceOp.SUM)
    return t.tolist()


def all_reduce_mean(values: list[float], device: torch.device | str = "cpu") -> list[float]:
    n = world_size()
    return [v / n for v in all_reduce_sum(values, device)]


def broadcast_object(obj, src: int = 0):
    """``obj`` of rank ``src`` on every rank (pickled; fine for a checkpoint read once at start)."""
    if not info().distributed:
        return obj
    box = [obj if rank() == src else None]
    dist.broadcast_object_list(box, src=src)
    return box[0]


def all_gather_object(obj) -> list:
    """Every rank's ``obj``, in rank order (``[obj]`` alone)."""
    if not info().distributed:
        return [obj]
    out = [None] * world_size()
    dist.all_gather_object(out, obj)
    return out


def shutdown() -> None:
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def parameter_digest(module: torch.nn.Module) -> str:
    """SHA-256 of ``module``'s parameters (names, shapes, exact bytes): equal on ranks that are in sync."""
    import hashlib

    h = hashlib.sha256()
    for name, p in module.named_parameters():
        t = p.detach().to("cpu", copy=True).contiguous()
        h.update(f"{name}:{tuple(t.shape)}:{t.dtype}".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()
