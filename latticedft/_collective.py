"""Collectives over the process group (:mod:`torch.distributed`), each the identity without one.

Training in several processes (``--workers N``, ``torchrun``) combines what each process read of its share
of the data: sums, and the minima and maxima of the input scaling and the training range. Tensors travel as
float64 (through the process's GPU under ``nccl``, on the CPU under ``gloo``) and come back on their own
device and dtype.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
import torch.distributed as dist

__all__ = ["alone", "group_device", "is_parallel", "merged_max", "merged_min", "reduce", "world"]

#: Inside :func:`alone`: this process works by itself although it belongs to a group.
_ALONE = [False]


def world() -> tuple[int, int]:
    """(rank, number of processes) of the initialised process group; ``(0, 1)`` without one (or inside
    :func:`alone`)."""
    if not _ALONE[0] and dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


@contextmanager
def alone() -> Iterator[None]:
    """Within, this process works as if it were the only one (:func:`world` is ``(0, 1)``): no collective is
    entered, so that work one process does by itself inside a group (rank 0's calibration after training)
    does not wait on processes that are not taking part."""
    before = _ALONE[0]
    _ALONE[0] = True
    try:
        yield
    finally:
        _ALONE[0] = before


def is_parallel() -> bool:
    """True when more than one process shares the work."""
    return world()[1] > 1


def group_device() -> torch.device:
    """Where tensors travel for a collective: the process's GPU under ``nccl``, else the CPU."""
    if dist.get_backend() == "nccl":
        return torch.device("cuda", torch.cuda.current_device())
    return torch.device("cpu")


def reduce(t: torch.Tensor, op: dist.ReduceOp.RedOpType) -> torch.Tensor:
    """``t`` reduced over the processes by ``op`` (a new tensor; ``t`` itself without a process group)."""
    if not is_parallel():
        return t
    buf = t.detach().to(group_device(), torch.float64).clone()
    dist.all_reduce(buf, op=op)
    return buf.to(t.device, t.dtype)


def _merged(t: torch.Tensor | None, shape: tuple[int, ...], largest: bool) -> torch.Tensor | None:
    if not is_parallel():
        return t
    fill = -torch.inf if largest else torch.inf
    own = torch.full(shape, fill, dtype=torch.float64) if t is None else t.to(torch.float64)
    out = reduce(own, dist.ReduceOp.MAX if largest else dist.ReduceOp.MIN)
    if bool((out == fill).all()):
        return None  # no process had a value
    return out if t is None else out.to(t.dtype)


def merged_min(t: torch.Tensor | None, shape: tuple[int, ...]) -> torch.Tensor | None:
    """The elementwise minimum over the processes of ``t`` (of ``shape``; None where a process has none, and
    back when none has)."""
    return _merged(t, shape, largest=False)


def merged_max(t: torch.Tensor | None, shape: tuple[int, ...]) -> torch.Tensor | None:
    """The elementwise maximum over the processes, as :func:`merged_min`."""
    return _merged(t, shape, largest=True)
