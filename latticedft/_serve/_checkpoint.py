"""The state of a field served through a rolling window, taken at a window boundary and put back.

``serve(..., checkpoint=K)`` with an ``on_slice`` object that has a ``checkpointer`` (the case pipeline's
resumable tasks): every ``K`` slices, at the end of a window, :func:`stream_state` gives what serving needs to
go on from there (the last two slices and the one before them, the slice index, the iteration counters, the
extrapolation record, the Newton cache with the Hessian blocks its factorisation was made from) and the
checkpointer stores it (``save(state)``). At the start of a resumed run the checkpointer's ``load()`` gives
it back (with the kept slices so far) and :func:`restore_stream` puts it into the fresh window.

The window holds at most ``K`` new slices, so that an interrupted and an uninterrupted run see the same
windows: the served slices, the counters and the figures measured window by window are the same bit for bit.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np
import torch

from .._errors import InputError
from ._solvers import factor_step
from ._stepper import SliceRun

__all__ = [
    "CACHE_KEYS",
    "STATE_VERSION",
    "Checkpointer",
    "WindowRun",
    "keep_factored",
    "restore_stream",
    "stream_state",
]

#: The layout of the state; a checkpoint of another layout is refused.
STATE_VERSION = 2

#: The Newton cache entries kept (``solve`` is rebuilt from ``factored``: the blocks and target it was made from);
#: an entry that steers later slices (as ``fresh_first``) belongs here, or a resumed run takes other steps.
CACHE_KEYS = ("solver", "dmax", "mscale", "singular", "used", "fresh_first", "factored")


class Checkpointer(Protocol):
    """Where a window's state goes (``save``) and comes back from (``load``: None to start afresh)."""

    def save(self, state: dict[str, Any]) -> None: ...

    def load(self) -> dict[str, Any] | None: ...


class WindowRun(SliceRun, Protocol):
    """A windowed run as its state is taken and put back (``_stream._Stream``): the stepper's run
    (:class:`._stepper.SliceRun`, whose slice held at position 0, ``base``, moves on window by window) with
    the window (``buf``: ``chunk + 2`` slices), the slices of the field (``steps``) and handed out so far
    (``done``), the one before the window (``before``), the kept slices (``kept_values``, the first ``nkept``
    filled), the training-range excess per anchor slice (``per_anchor``) and the slices the affine recurrence
    served (``affine_slices``)."""

    steps: int
    chunk: int
    buf: torch.Tensor
    base: int
    done: int
    nkept: int
    before: torch.Tensor | None
    kept_values: np.ndarray
    per_anchor: np.ndarray | None
    affine_slices: int


def _shape_key(run: WindowRun) -> dict[str, Any]:
    """What a state must agree with to be put into ``run``: the slices, the window and the lattice."""
    return {"steps": int(run.steps), "chunk": int(run.chunk), "shape": [int(s) for s in run.buf.shape[1:]]}


def stream_state(run: WindowRun, on_affine: bool) -> dict[str, Any]:
    """The state of the windowed run ``run`` (a ``_stream._Stream``) just after its window moved on."""
    cache = {k: run.cache[k] for k in CACHE_KEYS if k in run.cache}
    if "solve" not in run.cache:
        cache.pop("factored", None)  # the factorisation was dropped after a failed step
    per_anchor = None if run.per_anchor is None else run.per_anchor[: max(run.done - 1, 0)].copy()
    return {
        "version": STATE_VERSION,
        **_shape_key(run),
        "base": int(run.base),
        "done": int(run.done),
        "nkept": int(run.nkept),
        "head": run.buf[:2].clone(),
        "before": None if run.before is None else run.before.clone(),
        "on_affine": bool(on_affine),
        "counters": [int(run.total_it), int(run.max_it), float(run.worst), int(run.affine_slices)],
        "per_anchor": per_anchor,
        "cache": cache,
    }


def restore_stream(run: WindowRun, state: dict[str, Any]) -> bool:
    """Put ``state`` (with ``kept_values``, the kept slices so far) into the fresh run ``run``; returns whether
    the affine recurrence was still serving."""
    if state.get("version") != STATE_VERSION or any(state.get(k) != v for k, v in _shape_key(run).items()):
        raise InputError.at(
            "checkpoint", "the checkpoint was written for other slices, window or lattice; run without --resume"
        )
    run.base, run.done, run.nkept = state["base"], state["done"], state["nkept"]
    run.buf[:2] = state["head"]
    run.before = state["before"]
    run.total_it, run.max_it, run.worst, run.affine_slices = state["counters"]
    if run.per_anchor is not None and state["per_anchor"] is not None:
        run.per_anchor[: len(state["per_anchor"])] = state["per_anchor"]
    run.kept_values[: run.nkept] = np.asarray(state["kept_values"]).reshape(run.nkept, *run.kept_values.shape[1:])
    run.cache.update(state["cache"])
    if "factored" in run.cache:  # the chord steps go on with the same factorisation
        blocks, target = run.cache["factored"]
        run.cache["solve"], _ = factor_step(run.sys, blocks, run.vol, run.cache.get("solver", "auto"), target)
    run.bar.update(run.done - 2)
    return bool(state["on_affine"])


def keep_factored(cache: dict[str, Any]) -> None:
    """Ask slice-Newton to keep, beside each factorisation, the Hessian blocks and target it was made from."""
    cache["keep_factored"] = True
