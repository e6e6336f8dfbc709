"""The checkpoints of a task served split (``[[serve]] checkpoint = K`` under several processes).

Rank 0 writes them, in the layout of one process's (``.<task>.ckpt``, through :class:`TaskCheckpoint`: a
temporary file synced, then renamed): the state :class:`latticedft._serve._slabstate.SlabCheckpoint`
gathers (the last three slices whole, the counters, each process's error sums and Hessian blocks), with the
figures rank 0 measures on the whole slices (the invariant's, the excess over the training range) and the
error sums' totals, so that one process can take it up too. A resumed split task goes on from it: rank 0
reads it back (with the kept slices of the part file) and hands each process its part.

Under ``--resume`` rank 0 first tells the others whether each task that is split is served (the tasks done
before the run stopped are skipped by every process).
"""

from __future__ import annotations

from typing import Any

import torch
import torch.distributed as dist

from .._collective import world
from .._serve._slabstate import SlabCheckpoint
from ._data import TaskData
from ._resume import TaskCheckpoint

__all__ = ["served", "split_checkpoint"]


def served(resume: bool, skip: bool = False) -> bool:
    """Under ``resume``, rank 0 tells every process whether the task is served (``skip``: it was done before
    the run stopped); True without ``resume``."""
    if not resume or world()[1] == 1:
        return True
    go = [not skip]
    dist.broadcast_object_list(go, src=0)
    return bool(go[0])


def split_checkpoint(
    td: TaskData, errors: Any, whole: Any, part: Any, resumed: dict[str, Any] | None
) -> SlabCheckpoint:
    """The checkpoints of ``td`` in this process (``errors``: its slab's error meter; on rank 0 ``whole``, its
    measurements on the whole slices, and ``part``, the task's part file, whose checkpoint it goes on from
    ``resumed``, as read, when not None)."""
    every = int(td.task.options.checkpoint or 0)
    if world()[0] != 0 or whole is None or part is None:
        return SlabCheckpoint(every, errors.own, errors.put)
    ckpt = TaskCheckpoint(part, whole.meter, td.task.name, resumed)
    state = ckpt.load()
    if state is not None:
        _restore_whole(whole, state)

    def put(own: Any) -> None:  # a state of another decomposition: rank 0 goes on from the totals
        m = whole.meter
        errors.put(own if own is not None else (m.max_error, m.sum_sq, m.reference_max, m.count, m.compared))

    return SlabCheckpoint(every, errors.own, put, save=lambda s: _save(whole, ckpt, s), state=state)


def _save(whole: Any, ckpt: TaskCheckpoint, state: dict[str, Any]) -> None:
    """Write ``state`` with rank 0's figures on the whole slices and the totals of the error sums."""
    whole.flush()
    owns = state["split"]["own"]
    m = whole.meter
    m.max_error, m.sum_sq = max(o[0] for o in owns), sum(o[1] for o in owns)
    m.reference_max, m.count, m.compared = max(o[2] for o in owns), sum(o[3] for o in owns), max(o[4] for o in owns)
    if whole.per_anchor is not None:
        state["per_anchor"] = whole.per_anchor[: state["done"] - 1].copy()
    ckpt.save(state)


def _restore_whole(whole: Any, state: dict[str, Any]) -> None:
    """Rank 0's measurements on the whole slices go on from ``state`` (the meter's figures are put back)."""
    if whole.per_anchor is not None and state.get("per_anchor") is not None:
        whole.per_anchor[: len(state["per_anchor"])] = state["per_anchor"]
    whole.prev = torch.as_tensor(state["head"][1])
    whole.start = int(state["done"])
