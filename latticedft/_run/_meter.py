"""A task served with an output cadence (``[[serve]] every``): its figures measured on every slice as it is served.

``serve(..., every=k)`` keeps only every ``k``-th slice; :class:`TaskMeter` is the ``on_slice`` object of
such a task. Its ``on_block`` sees every served slice, in blocks of consecutive slices, and measures what
``serve_task`` would measure on the whole field: the max and RMS error against the reference over the
slices both hold (the numbers of :func:`latticedft.compare`) and the task's invariant at every slice.

The invariant is a function of a field; it is evaluated on windows of consecutive slices with one slice
of margin on each side (so a value at a slice may depend on the slices next to it, as the discrete
energies of :mod:`latticedft.systems` do; the first and last slices get the one-sided value the whole
field would give them).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import xarray as xr

from .._options import option

__all__ = ["TaskMeter", "compare_blocks"]


def compare_blocks(a: xr.DataArray, b: xr.DataArray, slices: int | None = None) -> dict[str, float]:
    """:func:`latticedft.compare` of ``a`` against ``b`` over their first ``slices`` slices (default: all both
    hold), reading blocks of slices (fields opened lazily are never held whole); the RMS summed block by block.
    """
    tdim = a.dims[0]
    n = min(a.sizes[tdim], b.sizes[b.dims[0]], a.sizes[tdim] if slices is None else slices)
    step = max(1, option("task_block_bytes") // max(1, 8 * int(np.prod(a.shape[1:]))))
    worst, sum_sq, count = 0.0, 0.0, 0
    for lo in range(0, n, step):
        hi = min(n, lo + step)
        d = np.asarray(a.isel({tdim: slice(lo, hi)}).values, dtype=np.float64) - np.asarray(
            b.isel({b.dims[0]: slice(lo, hi)}).values, dtype=np.float64
        )
        worst = max(worst, float(np.abs(d).max())) if d.size else worst
        sum_sq += float(np.sum(d**2))
        count += d.size
    return {"max_error": worst, "rms_error": float(np.sqrt(sum_sq / count)) if count else float("nan"), "slices": n}


class TaskMeter:
    """Errors against ``reference`` and the values of ``invariant``, measured slice by slice."""

    def __init__(
        self,
        reference: xr.DataArray | None,
        invariant: Callable[[xr.DataArray], Any] | None,
        on_kept: Callable[[int, np.ndarray], Any] | None = None,
    ):
        self.on_kept = on_kept  # e.g. appends the kept slice to the task's part file
        self.reference = reference
        self.invariant = invariant
        self.max_error = 0.0
        self.sum_sq = 0.0
        self.count = 0
        self.compared = 0
        #: the reference's largest magnitude on the compared slices (the scale of the relative error)
        self.reference_max = 0.0
        self.values: dict[int, float] = {}  # invariant per slice
        self.tail: xr.DataArray | None = None  # the last two slices: margin of the next window
        self.t: dict[int, float] = {}
        self.attrs: dict[str, Any] = {}
        #: the invariant's failure (it is raised by the pipeline after serving, as for a whole field)
        self.error: Exception | None = None
        #: where the window's checkpoints go (``[[serve]] checkpoint``; see ``_serve._checkpoint``)
        self.checkpointer: Any = None

    #: What :meth:`state` holds: the figures measured so far (a checkpoint of the task).
    STATE = ("max_error", "sum_sq", "count", "compared", "reference_max", "values", "tail", "t", "attrs", "error")

    def state(self) -> dict[str, Any]:
        """The figures measured so far, to be put back by :meth:`restore` (a resumed task)."""
        return {k: getattr(self, k) for k in self.STATE}

    def restore(self, state: dict[str, Any]) -> None:
        """Go on from the figures of :meth:`state`."""
        for k in self.STATE:
            setattr(self, k, state[k])

    def __call__(self, index: int, values: np.ndarray) -> None:
        """A kept slice: handed on to ``on_kept`` (the blocks carry every slice for the measurements)."""
        if self.on_kept is not None:
            self.on_kept(index, values)

    def on_block(self, start: int, block: xr.DataArray) -> None:
        """Slices ``start .. start + len(block) - 1``, consecutive."""
        tdim = block.dims[0]
        n = block.sizes[tdim]
        for k, tv in enumerate(np.asarray(block[tdim].values, dtype=np.float64)):
            self.t[start + k] = float(tv)
        ref = self.reference
        if ref is not None:
            hi = min(start + n, ref.sizes[ref.dims[0]])
            if hi > start:
                part = ref.isel({ref.dims[0]: slice(start, hi)}).values  # read from its file when opened lazily
                part = np.asarray(part, dtype=np.float64)
                d = np.abs(np.asarray(block.values[: hi - start]) - part)
                if d.size:
                    self.max_error = max(self.max_error, float(d.max()))
                    self.reference_max = max(self.reference_max, float(np.abs(part).max()))
                self.sum_sq += float(np.sum(d**2))
                self.count += d.size
                self.compared = hi
        if self.invariant is not None and self.error is None:
            try:
                self._invariant_window(start, block)
            except Exception as exc:
                self.error = exc

    def _invariant_window(self, start: int, block: xr.DataArray) -> None:
        tdim = block.dims[0]
        tail = self.tail
        win = block if tail is None else xr.concat([tail, block], dim=tdim)
        wstart = start if tail is None else start - tail.sizes[tdim]
        nwin = win.sizes[tdim]
        if nwin >= 2:
            vals = self._evaluate(win)
            lo = 0 if wstart == 0 else 1
            for k in range(lo, nwin - 1):  # the last slice waits for its right neighbour
                self.values[wstart + k] = float(vals[k])
        self.tail = win.isel({tdim: slice(-2, None)})

    def _evaluate(self, win: xr.DataArray) -> np.ndarray:
        assert self.invariant is not None
        out = self.invariant(win)
        tdim = win.dims[0]
        if not isinstance(out, xr.DataArray) or out.dims != (tdim,):
            raise TypeError(f"expected a DataArray over {tdim!r}, got {type(out).__name__}")
        self.attrs = dict(out.attrs)
        return np.asarray(out.values, dtype=np.float64)

    def finish(self) -> None:
        """The last slice's invariant (from the last two slices)."""
        if self.invariant is None or self.error is not None or self.tail is None:
            return
        if self.tail.sizes[self.tail.dims[0]] >= 2:
            try:
                self.values[max(self.t)] = float(self._evaluate(self.tail)[-1])
            except Exception as exc:
                self.error = exc

    def errors(self) -> dict[str, float]:
        """``max_error``, ``rms_error`` and ``slices`` (compared), as :func:`latticedft.compare` gives them."""
        rms = float(np.sqrt(self.sum_sq / self.count)) if self.count else float("nan")
        return {"max_error": self.max_error, "rms_error": rms, "slices": self.compared}

    def invariant_series(self, tdim: str) -> xr.DataArray:
        """The invariant on every slice served, over ``tdim``."""
        idx = sorted(self.values)
        return xr.DataArray(
            np.array([self.values[i] for i in idx]),
            dims=(tdim,),
            coords={tdim: np.array([self.t[i] for i in idx])},
            name="invariant",
            attrs=self.attrs,
        )
