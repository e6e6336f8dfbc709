"""What serving reports: the result record, the error metrics against a reference, the progress bar."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
import xarray as xr
from tqdm.auto import tqdm

from .._errors import InputError
from ._range import extrapolation_summary


@dataclass
class ServeResult:
    """A served field and how serving went."""

    field: xr.DataArray
    complete: bool
    reason: str
    slices: int
    newton_iterations: int
    max_newton_iterations: int
    wall_time: float
    sites_per_second: float
    max_residual: float
    mode: str
    #: how the slices were solved: "newton", "sweep", "affine" (a quadratic L_d: the DEL's affine recurrence,
    #: one factorised solve per slice, checked afterwards) or "affine+newton" (Newton from the first slice
    #: that failed that check)
    solver: str = "newton"
    #: a failed member of a 1D batch: ``(slice, residual)`` where it failed (``None`` otherwise)
    fail_at: tuple[int, float] | None = dataclasses.field(default=None, repr=False, compare=False)
    #: ``extrapolation(t, feature)``: per slice, how far the served cells lie outside the model's training
    #: range, per input feature, relative to the feature's training span (0 inside; None when the model
    #: keeps no range). See ``extrapolation_summary()``.
    extrapolation: xr.DataArray | None = None
    #: One-line warnings about the served field (it leaves the training range ...); empty when none.
    warnings: list[str] = dataclasses.field(default_factory=list)

    def extrapolation_summary(self) -> dict[str, Any] | None:
        """The largest excess per feature and the first slice beyond the tolerance (None without a range)."""
        return extrapolation_summary(self.extrapolation)

    def to_dict(self) -> dict[str, Any]:
        """The numbers of the result (not the field): what ``summary.json`` records of a task."""
        out = {
            k: getattr(self, k)
            for k in (
                "complete",
                "reason",
                "slices",
                "newton_iterations",
                "max_newton_iterations",
                "wall_time",
                "sites_per_second",
                "max_residual",
                "mode",
                "solver",
            )
        }
        out["extrapolation"] = self.extrapolation_summary()
        out["warnings"] = list(self.warnings)
        return out


def compare(pred: xr.DataArray, ref: xr.DataArray) -> dict[str, float]:
    """Max and RMS error of ``pred`` against ``ref`` over the time slices both hold.

    >>> import numpy as np, xarray as xr
    >>> a = xr.DataArray(np.zeros(4), dims="t", coords={"t": np.arange(4.0)})
    >>> compare(a, a + 0.5)
    {'max_error': 0.5, 'rms_error': 0.5, 'slices': 4}
    """
    for name, arr in (("pred", pred), ("ref", ref)):
        if not isinstance(arr, xr.DataArray):
            raise InputError.at(name, f"expected an xarray.DataArray (time first), got {type(arr).__name__}")
        if not arr.dims:
            raise InputError.at(name, "expected a field with a time dim, got a scalar DataArray")
    tdim = pred.dims[0]
    if ref.dims[0] != tdim:
        raise InputError.at("ref", f"its first dim {ref.dims[0]!r} is not pred's time dim {tdim!r}")
    n = min(pred.sizes[tdim], ref.sizes[tdim])
    if pred.shape[1:] != ref.shape[1:]:
        raise InputError(f"compare: shapes {pred.shape} and {ref.shape} differ beyond the time axis")
    d = pred.values[:n] - ref.values[:n]
    return {"max_error": float(np.abs(d).max()), "rms_error": float(np.sqrt(np.mean(d**2))), "slices": int(n)}


def _bar(total: int, desc: str, progress: bool | None):
    """A progress bar over ``total`` slices; ``progress=None`` shows it only on a terminal."""
    return tqdm(total=total, desc=desc, disable=None if progress is None else not progress, leave=False)
