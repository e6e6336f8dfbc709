"""Checkpoints of a split serve (``[[serve]] checkpoint = K`` under several processes).

Every ``K`` slices (at the window boundaries one process would checkpoint at), :class:`SlabCheckpoint`
gathers to rank 0 what each process needs to go on: its planes of the last three slices, its own figures
(the task's error sums over its slab) and, for slice-Newton's chord steps, the Hessian blocks its
factorisation was made from. Rank 0 assembles from them the state of one process's windowed run
(``_checkpoint.stream_state``: the same keys, the whole lattice's slices) with a ``split`` entry holding
what is each process's own, and hands it to its ``save``. At the start of a resumed run, rank 0 hands each
process its part of the state (its planes of the three slices and of the kept slices so far, and its own
entries when the state was written by as many processes), which :func:`restore` puts into its slab.

A state written by another number of processes (or by one) is taken up too: the slices and the counters
are the same, but the factorisation of the chord steps is not carried over (the first slice assembles a
fresh Jacobian), and the error sums go on from their totals.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import torch.distributed as dist

from .._collective import world
from .._layout import lattice_dims
from .._options import option
from ._checkpoint import CACHE_KEYS, STATE_VERSION
from ._grid import Block, assemble

if TYPE_CHECKING:  # _decomp holds the slab run and takes a SlabCheckpoint (no import at run time)
    from ._decomp import _SlabRun

__all__ = ["SlabCheckpoint", "restore", "stream_chunk"]

#: The Newton cache entries a state carries: the window state's, but the factorisation (kept per part apart).
_CACHE_KEYS = tuple(k for k in CACHE_KEYS if k != "factored")


def stream_chunk(slice_bytes: int, steps: int, checkpoint: int | None) -> int:
    """The new slices of one window of one process's windowed run (``_stream._Stream``)."""
    chunk = max(4, option("serve_window_bytes") // max(slice_bytes, 1))
    return max(1, min(chunk, steps - 2, checkpoint or steps))


@dataclass
class SlabCheckpoint:
    """The checkpoints of one split serve (every process holds one; ``save`` and ``state`` on rank 0 only).

    ``every`` is ``K``; ``own()`` gives this process's figures to carry (gathered into the state's
    ``split.own``), ``put(own)`` puts them back; ``save(state)`` writes the state; ``state`` is the state
    to go on from (None: from the start)."""

    every: int
    own: Callable[[], Any]
    #: puts this process's own figures back (None: the state was written by another decomposition)
    put: Callable[[Any], None]
    save: Callable[[dict[str, Any]], None] | None = None
    state: dict[str, Any] | None = None
    saved: int = 0
    chunk: int = field(default=0)

    def start(self, run: _SlabRun) -> None:
        """Hand every process its part of :attr:`state` (rank 0's) and put it into its slab ``run``."""
        rank, size = world()
        sites = int(np.prod([run.init.sizes[d] for d in lattice_dims(run.init)[1:]]))
        self.chunk = stream_chunk(8 * sites * run.f.ncomp, run.slices, self.every)
        parts: list[Any] = [None] * size
        if rank == 0 and self.state is not None:
            parts = [_part(self.state, run, block) for block in run.blocks]
        got: list[Any] = [parts[0]]
        if size > 1:
            dist.scatter_object_list(got, parts if rank == 0 else None, src=0)
        if got[0] is not None:
            self.put(restore(run, got[0]))
            self.saved = run.done - 1

    def __call__(self, run: _SlabRun) -> None:
        """After slice ``run.done``: the checkpoint, when one is due (every process takes part)."""
        base = run.done - 1
        if base - self.saved < self.every or base % self.chunk or run.done + 1 >= run.slices:
            return
        self.saved = base
        run.flag.maxima()  # the gate before the gather
        newton = run.newton
        factored = None if newton is None else newton.cache.get("factored") if "solve" in newton.cache else None
        mine = (np.stack([run.own(r) for r in range(3)]), self.own(), factored)
        parts: list[Any] = [mine]
        if world()[1] > 1:
            parts = [None] * world()[1]
            dist.gather_object(mine, parts if world()[0] == 0 else None, dst=0)
        if world()[0] == 0 and self.save is not None:
            self.save(_state(run, self.chunk, parts))


def _state(run: _SlabRun, chunk: int, parts: list[Any]) -> dict[str, Any]:
    """One process's windowed-run state of the split run ``run`` (rank 0), from every process's ``parts``."""
    rows = torch.from_numpy(assemble([p[0] for p in parts], run.block.grid, 1))  # (3, planes, ..., components)
    s, newton = run.done, run.newton
    cache = {} if newton is None else {k: newton.cache[k] for k in _CACHE_KEYS if k in newton.cache}
    counters = [0, 0, float(run.worst), s - 1] if newton is None else [newton.total_it, newton.max_it, run.worst, 0]
    factored = [p[2] for p in parts]
    return {
        "version": STATE_VERSION,
        "steps": int(run.slices),
        "chunk": int(chunk),
        "shape": [int(n) for n in rows.shape[1:]],
        "base": s - 1,
        "done": s + 1,
        "nkept": int(np.count_nonzero(run.kept_at <= s)),
        "head": rows[1:3].clone(),
        "before": rows[0].reshape(-1, rows.shape[-1]).clone(),  # (sites, components), as one process's
        "on_affine": newton is None,
        "counters": [int(counters[0]), int(counters[1]), float(counters[2]), int(counters[3])],
        "per_anchor": None,
        "cache": cache,
        "split": {
            "processes": world()[1],
            "grid": list(run.block.grid),
            "own": [p[1] for p in parts],
            "factored": None if any(f is None for f in factored) else factored,
        },
    }


def _part(state: dict[str, Any], run: _SlabRun, block: Block) -> dict[str, Any]:
    """The part of ``state`` (with its ``kept_values``) of the process holding ``block``."""
    split = state.get("split") or {}
    grid = split.get("grid", [split.get("processes")])  # a state of slabs may not say its grid
    same = split.get("processes") == world()[1] and list(grid) == list(block.grid)
    two = np.asarray(state["head"])
    head = np.concatenate([np.asarray(state["before"]).reshape(1, *two.shape[1:]), two])
    kept = np.asarray(state["kept_values"]).reshape(int(state["nkept"]), *head.shape[1:])
    factored = split.get("factored") if same else None
    index = run.blocks.index(block)
    return {
        "own": split["own"][index] if same else None,
        "rows": block.take(head, 1),
        "kept": block.take(kept, 1),
        "done": int(state["done"]) - 1,
        "on_affine": bool(state["on_affine"]),
        "counters": state["counters"],
        "cache": {k: v for k, v in state["cache"].items() if k in _CACHE_KEYS},
        "factored": None if factored is None else factored[index],
    }


def restore(run: _SlabRun, part: dict[str, Any]) -> Any:
    """Put ``part`` into the slab run ``run``; this process's own figures (None when the state was written by
    another decomposition)."""
    n = part["rows"].shape[0]
    run.window[:n] = part["rows"].reshape(n, -1)
    run.done = int(part["done"])
    run.kept = [k[run.block.own].copy() for k in part["kept"]]  # the block's own sites
    total_it, max_it, worst, _ = part["counters"]
    run.worst = float(worst)
    newton = run.newton
    if newton is not None:
        newton.total_it, newton.max_it = int(total_it), int(max_it)
        newton.cache.update(part["cache"])
        if part["factored"] is not None:  # the chord steps go on with the same factorisation
            blocks, target = part["factored"]
            newton.refactor(blocks, target)
    return part["own"]
