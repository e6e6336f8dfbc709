"""Held-out serving: a model learned on the first part of each field serves the rest from its first two slices.

Selection scores its candidates this way, and the sparse fit chooses its threshold this way: a theory is judged
by what it serves beyond the slices it was learned from, not by its residual on them.
"""

from __future__ import annotations

import math

import numpy as np
import xarray as xr

from .._errors import InputError
from .._lattice import BoundaryKinds
from .._models import AbstractLagrangian
from .._serve import serve
from ._noise import denoised_start

__all__ = ["HOLD_OUT", "held_in", "held_in_slices", "held_out_score"]

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
