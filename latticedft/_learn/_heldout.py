"""Held-out serving: a model learned on the first part of each field serves the rest from its first two slices.

Selection scores its candidates this way, and the sparse fit chooses its threshold this way: a theory is judged
by what it serves beyond the slices it was learned from, not by its residual on them. The sparse fit serves its
supports' tails a few slices at a time (:class:`SupportServing` on :class:`Tails`), so that a support stops as soon
as its error passes the bound it must meet.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from typing import Any, overload

import numpy as np
import torch
import xarray as xr

from .._contract import NumpyForms
from .._errors import InputError, LatticeDFTError
from .._lattice import BoundaryKinds, LatticeField, as_lattice_fields
from .._models import AbstractLagrangian, SparseLagrangian
from .._serve import serve
from .._serve._fast1d import numpy_derivatives_of
from .._serve._onedim import WindowServing
from .._serve._options import ServeOptions
from ._noise import denoised_start

__all__ = ["FIRST_CHUNK", "HOLD_OUT", "SupportServing", "Tails", "held_in", "held_in_slices", "held_out_score"]

#: The share of each field's time slices held out.
HOLD_OUT = 0.3


def held_in(fields: list[xr.DataArray], hold_out: float) -> list[xr.DataArray]:
    """The first ``1 - hold_out`` of every field's slices (at least 3, and at least one slice held out)."""
    keep = held_in_slices([f.sizes[f.dims[0]] for f in fields], hold_out)
    return [f.isel({f.dims[0]: slice(0, k)}) for f, k in zip(fields, keep)]


def held_in_slices(slices: list[int], hold_out: float) -> list[int]:
    """How many of each field's ``slices`` :func:`held_in` keeps."""
    out = []
    for i, nt in enumerate(slices):
        keep = max(3, int(round(nt * (1.0 - hold_out))))
        if keep >= nt:
            raise InputError.at(
                "data", f"field {i} holds {nt} time slices; selection needs at least 4 (3 to learn from, 1 held out)"
            )
        out.append(keep)
    return out


def held_out_score(
    model: AbstractLagrangian,
    fields: list[xr.DataArray],
    boundary: BoundaryKinds | None,
    served: list[np.ndarray] | None = None,
) -> float:
    """The largest served error over the largest magnitude, field by field; ``ServeError`` when one stops.
    A candidate whose training corrected noisy data serves from denoised initial slices, as a case's task
    with ``start = "auto"`` would. ``served``: a list that receives every field's served values (float64, the
    slices served), as :func:`latticedft._calibrate.calibrate` serves them."""
    noise = (model.report_.noise if model.report_ is not None else None) or {}
    denoise = noise.get("method", "none") != "none"
    worst = 0.0
    for f in fields:
        start = denoised_start(model, f) if denoise else f
        result = serve(model, start, boundary=boundary, progress=False)
        pred = np.asarray(result.field.values)
        if served is not None:
            served.append(np.asarray(pred, dtype=np.float64))
        ref = np.asarray(f.values)[: pred.shape[0]]
        err = float(np.max(np.abs(pred - ref))) / max(float(np.max(np.abs(ref))), np.finfo(float).tiny)
        worst = max(worst, err if math.isfinite(err) else math.inf)
    return worst


#: Held-out serving advances this many slices at first, then twice as many each time (:class:`SupportServing`).
FIRST_CHUNK = 4


class Tails(Sequence[xr.DataArray]):
    """The held-out tails of the unbatched fields ``single``, each from its slice ``starts[k]`` on: their lattice
    fields (:meth:`fields`, the time axis sliced), and as DataArrays (each field's, sliced) made when first read,
    which only serving by :func:`serve` does (n-D tails, a denoised start): 1D tails are served from their
    lattice fields alone."""

    def __init__(self, single: list[LatticeField], starts: list[int]):
        self._single, self._starts = single, starts
        self._arrays: list[xr.DataArray] | None = None

    def __len__(self) -> int:
        return len(self._single)

    @overload
    def __getitem__(self, i: int) -> xr.DataArray: ...
    @overload
    def __getitem__(self, i: slice) -> Sequence[xr.DataArray]: ...
    def __getitem__(self, i: int | slice) -> xr.DataArray | Sequence[xr.DataArray]:
        if self._arrays is None:
            whole = [f.to_dataarray() for f in self._single]
            self._arrays = [w.isel({w.dims[0]: slice(k, None)}) for w, k in zip(whole, self._starts)]
        return self._arrays[i]

    def fields(self) -> list[LatticeField]:
        """The tails' lattice fields."""
        out = []
        for f, k in zip(self._single, self._starts):
            t = f.dims[0]
            out.append(replace(f, values=f.values[k:], coords={**f.coords, t: f.coords[t][k:]}))
        return out


class SupportServing:
    """One support's held-out serving of every tail, advanced a few slices at a time from the last two slices
    served, so that it stops as soon as its error passes a bound (Newton's method restarted on each chunk, so
    the slices agree with serving a tail in one call to within Newton's tolerance). ``error``: the largest
    relative error so far (:func:`latticedft._learn._heldout.held_out_score`'s measure; ``inf`` once serving
    stops). ``shared``: where the tails' lattice fields and the batch serving 1D tails (:class:`WindowServing`)
    are kept for the other supports serving the same tails."""

    def __init__(
        self,
        theta: np.ndarray,
        tails: Sequence[xr.DataArray],
        boundary: BoundaryKinds | None,
        shared: dict[str, Any] | None = None,
    ):
        self.theta, self.tails, self.boundary = theta, tails, boundary
        self._shared = {} if shared is None else shared
        self.error = 0.0
        self.started = False
        self._field = 0
        self._served: np.ndarray | None = None
        self._chunk = FIRST_CHUNK
        # 1D tails: served by the numpy loop without building serve's results (:class:`WindowServing`), from
        # the numpy closed forms of the support being served (None: by the public serve)
        self._fields: list[LatticeField] | None = None
        self._forms: NumpyForms | None = None

    @property
    def finished(self) -> bool:
        """Every tail served, or serving stopped."""
        return self._field >= len(self.tails) or not math.isfinite(self.error)

    def advance(self, model: SparseLagrangian, bound: float) -> float:
        """Serve on until the error passes ``bound`` or every tail is served; the error so far."""
        if self.finished or self.error > bound:
            return self.error
        self.started = True
        with torch.no_grad():
            model.coef.copy_(torch.from_numpy(self.theta))
        noise = (model.report_.noise if model.report_ is not None else None) or {}
        if noise.get("method", "none") != "none":  # a denoised start: the tails served whole
            try:
                self.error = held_out_score(model, list(self.tails), self.boundary)
            except LatticeDFTError:
                self.error = math.inf
            self._field = len(self.tails)
            return self.error
        self._forms = self._numpy_forms(model)
        while not self.finished and self.error <= bound:
            self._chunk_on(model)
        return self.error

    def _numpy_forms(self, model: SparseLagrangian) -> NumpyForms | None:
        """The model's numpy closed forms where every tail is 1D (with their lattice fields), else None."""
        if self._fields is None:
            if "fields" not in self._shared and isinstance(self.tails, Tails):
                self._shared["fields"] = self.tails.fields()
            elif "fields" not in self._shared:
                names = [f"tails[{k}]" for k in range(len(self.tails))]
                self._shared["fields"] = as_lattice_fields(self.tails, names, boundary=self.boundary, min_slices=2)
            self._fields = self._shared["fields"]
        return numpy_derivatives_of(model) if all(f.ndim == 1 for f in self._fields) else None

    def _window(self, model: SparseLagrangian) -> WindowServing:
        """What serves a window of a 1D tail: one batch for every support serving the same tails, restarted on
        each window (:class:`latticedft._serve._onedim.WindowServing`) instead of built again."""
        if "window" not in self._shared:
            self._shared["window"] = WindowServing(model, ServeOptions.from_keywords(None, progress=False))
        window: WindowServing = self._shared["window"]
        return window

    def _serve_window(self, model: SparseLagrangian, i0: int, start: np.ndarray) -> np.ndarray | None:
        """Slices ``i0, ...`` of the current tail served from the first two of ``start`` (the tail's slices from
        ``i0`` on, in its layout), or None where serving stopped: for 1D tails by :class:`WindowServing` (what
        :func:`serve` serves, without building its results), else by :func:`serve`."""
        try:
            if self._forms is None:
                tail = self.tails[self._field]
                window = tail.isel({tail.dims[0]: slice(i0, i0 + start.shape[0])})
                out = serve(model, window.copy(data=start), boundary=self.boundary, progress=False)
                return np.asarray(out.field.values)
            assert self._fields is not None
            f = self._fields[self._field]
            values = torch.from_numpy(start.reshape(start.shape[0], f.ncomp))
            t0 = float(f.coords[f.dims[0]][i0])
            served, failed = self._window(model)(f.with_values(values, t0), self._forms)
        except LatticeDFTError:
            return None
        return None if failed else served.reshape((served.shape[0], *start.shape[1:]))

    def _reference(self) -> np.ndarray:
        """The current tail's values: its lattice field's (slices, ..., components) where 1D tails are served by
        the numpy loop (the same numbers), else the DataArray's (the layout :func:`serve` takes)."""
        if self._forms is not None:
            assert self._fields is not None
            return self._fields[self._field].values.detach().numpy()
        return np.asarray(self.tails[self._field].values)

    def _chunk_on(self, model: SparseLagrangian) -> None:
        """Serve the next chunk of the current tail."""
        ref = self._reference()
        served = ref[:2] if self._served is None else self._served
        i0, nt = served.shape[0] - 2, ref.shape[0]
        start = ref[i0 : min(nt, i0 + 2 + self._chunk)].copy()
        start[:2] = served[-2:]
        out = self._serve_window(model, i0, start)
        if out is None:
            self.error = math.inf
            return
        new = out[2:]
        scale = max(float(np.max(np.abs(ref))), np.finfo(float).tiny)
        if new.size:
            err = float(np.max(np.abs(new - ref[i0 + 2 : i0 + 2 + new.shape[0]]))) / scale
            self.error = max(self.error, err if math.isfinite(err) else math.inf)
        self._served = np.concatenate([served, new])
        self._chunk *= 2
        if self._served.shape[0] >= nt or new.shape[0] < start.shape[0] - 2:
            self._field, self._served, self._chunk = self._field + 1, None, FIRST_CHUNK
