"""Several processes: which share of the training data this process reads, and the collectives that combine
the shares (:mod:`torch.distributed`).

Training runs data-parallel when a process group is initialised (by ``torchrun``, by
``latticedft train/run --workers N``, or by the caller before :func:`latticedft.learn`): every process
reads its share of the chunks and the partial sums are combined here, so every process ends with the same
model. Without a process group (the usual case) every function is the single-process identity.

Tensors are reduced as float64 on the CPU (``gloo``); under ``nccl`` they travel through the process's GPU.
The backend follows the training device (:func:`latticedft._device.backend_for_device`): NCCL when the
processes train on CUDA, each on ``cuda:<LOCAL_RANK>``, gloo otherwise.
"""

from __future__ import annotations

import datetime

import numpy as np
import torch
import torch.distributed as dist

from .._collective import group_device, reduce
from .._collective import is_parallel as is_parallel
from .._collective import world as world
from .._device import backend_for_device, resolve_device
from .._procenv import env_world, local_rank, local_world

__all__ = [
    "world",
    "is_parallel",
    "all_sum",
    "all_min",
    "all_max",
    "all_gather",
    "broadcast",
    "backend_for",
    "init_from_env",
]


def _reduce(t: torch.Tensor, op: dist.ReduceOp.RedOpType) -> torch.Tensor:
    return reduce(t, op)


def all_sum(t: torch.Tensor) -> torch.Tensor:
    """The sum over processes of ``t`` (a new tensor; ``t`` itself without a process group)."""
    return _reduce(t, dist.ReduceOp.SUM)


def all_min(t: torch.Tensor) -> torch.Tensor:
    """The elementwise minimum over processes."""
    return _reduce(t, dist.ReduceOp.MIN)


def all_max(t: torch.Tensor) -> torch.Tensor:
    """The elementwise maximum over processes."""
    return _reduce(t, dist.ReduceOp.MAX)


def all_gather(a: np.ndarray) -> list[np.ndarray]:
    """Every process's array of one common shape, in rank order (``[a]`` without a process group)."""
    if not is_parallel():
        return [a]
    dev = group_device()
    t = torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64)).to(dev)
    out = [torch.empty_like(t) for _ in range(world()[1])]
    dist.all_gather(out, t)
    return [o.cpu().numpy() for o in out]


def broadcast(t: torch.Tensor, src: int) -> torch.Tensor:
    """Rank ``src``'s tensor ``t`` in every process (the others pass a tensor of its shape); ``t`` itself
    without a process group."""
    if not is_parallel():
        return t
    buf = t.detach().to(group_device(), torch.float64).contiguous().clone()
    dist.broadcast(buf, src=src)
    return buf.cpu()


def backend_for(local_processes: int, device: str | None = None) -> str:
    """``nccl`` when the processes train on CUDA (``device`` resolves to a GPU), NCCL is built in and every
    local process can have a GPU of its own; else ``gloo``."""
    if backend_for_device(resolve_device(device)) != "nccl":
        return "gloo"
    if dist.is_nccl_available() and torch.cuda.device_count() >= local_processes:
        return "nccl"
    return "gloo"


def init_from_env(timeout_s: float = 1800.0, device: str | None = None) -> bool:
    """Join the process group that ``torchrun`` (or ``--workers``) describes in the environment
    (``RANK``, ``WORLD_SIZE``, ``MASTER_ADDR``, ``MASTER_PORT``); True when this process is one of several.

    ``device`` is the training device (:func:`latticedft.learn`'s): CUDA selects NCCL, with this process on
    ``cuda:<LOCAL_RANK>`` (its ``"cuda"`` from then on); anything else gloo.
    Does nothing when the group is already initialised or ``WORLD_SIZE`` is absent or 1. Each process then
    uses ``torch.get_num_threads() // LOCAL_WORLD_SIZE`` threads (at least one): processes on one machine
    share its cores.
    """
    if dist.is_available() and dist.is_initialized():
        return is_parallel()
    if env_world() <= 1:
        return False
    local = local_world()
    backend = backend_for(local, device)
    if backend == "nccl":
        torch.cuda.set_device(local_rank())
    dist.init_process_group(backend, timeout=datetime.timedelta(seconds=timeout_s))
    torch.set_num_threads(max(1, torch.get_num_threads() // max(local, 1)))
    return True
