"""What serving reports: the result record, the error metrics against a reference, the progress bar."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import xarray as xr

from .._errors import InputError
from .._progress import progress_bar
from ._range import extrapolation_summary

#: How a 1D trajectory's reason begins when it stopped leaving the serve's box.
LEFT_THE_BOX = "left the box"


def box_reason(box: float, at: int) -> str:
    """The reason of a 1D trajectory (or an ensemble member) whose slice ``at`` left the serve's ``box``."""
    return f"{LEFT_THE_BOX} |psi| <= {box:g} at slice {at}"


def served_source(kind: str) -> str:
    """The ``source`` attribute of a field served by a model of ``kind``."""
    return f"latticedft.serve: predicted from the first two slices by a {kind} L_d"


#: The figures of a serving run that :meth:`ServeResult.to_dict` starts with, in their order (then the
#: extrapolation summary and the warnings).
RUN_KEYS = (
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
    "device",
    "slice_solver",
)


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
    #: the linear solver of n-D slice-Newton's steps: "sitewise", "krylov" or "lu" ("sitewise+krylov" and the
    #: like when ``solver="auto"`` chose differently on different slices); None when no slice-Newton step was
    #: taken (1D, the sweep, or the affine recurrence throughout). An ensemble's run figures (the iterations,
    #: ``max_residual``, ``solver`` and this) are member 0's own, as member 0 served alone reports them.
    slice_solver: str | None = None
    #: a failed member of a 1D batch: ``(slice, residual)`` where it failed (``None`` otherwise)
    fail_at: tuple[int, float] | None = dataclasses.field(default=None, repr=False, compare=False)
    #: ``extrapolation(t, feature)``: per slice, how far the served cells lie outside the model's training
    #: range, per input feature, relative to the feature's training span (0 inside; None when the model
    #: keeps no range). See ``extrapolation_summary()``.
    extrapolation: xr.DataArray | None = None
    #: One-line warnings about the served field (it leaves the training range ...); empty when none.
    warnings: list[str] = dataclasses.field(default_factory=list)
    #: where the model was evaluated: ``"cpu"`` or ``"cuda:N (GPU name)"`` (``serve(device=...)``)
    device: str = "cpu"
    #: An ensemble (:class:`latticedft.EnsembleLagrangian`) served: the mean and standard deviation over its
    #: members, in ``field``'s layout (``field`` is member 0's, the full-data model's), and every member's
    #: field along a leading ``member`` dim; None for a single model.
    mean: xr.DataArray | None = dataclasses.field(default=None, repr=False)
    std: xr.DataArray | None = dataclasses.field(default=None, repr=False)
    members: xr.DataArray | None = dataclasses.field(default=None, repr=False)
    #: An ensemble's members that stopped (or went non-finite) before the last slice: ``{"member", "slice",
    #: "reason"}`` each, ``slice`` the first one the member does not hold; None when every member served it all.
    members_stopped: list[dict[str, Any]] | None = None
    #: An ensemble's members whose fields leave their own training range: ``{"member", "slice", "feature",
    #: "excess"}`` each, ``slice`` the first beyond the tolerance; None when none does.
    members_outside: list[dict[str, Any]] | None = None

    def extrapolation_summary(self) -> dict[str, Any] | None:
        """The largest excess per feature and the first slice beyond the tolerance (None without a range)."""
        return extrapolation_summary(self.extrapolation)

    def to_dict(self) -> dict[str, Any]:
        """The numbers of the result (not the field): what ``summary.json`` records of a task."""
        out = {k: getattr(self, k) for k in RUN_KEYS}
        out["extrapolation"] = self.extrapolation_summary()
        out["warnings"] = list(self.warnings)
        if self.members is not None:
            out["ensemble_members"] = int(self.members.sizes["member"])
            out["members_stopped"] = list(self.members_stopped or [])
            out["members_outside"] = list(self.members_outside or [])
        return out

    def to_dataset(self) -> xr.Dataset:
        """The served field as a Dataset: ``psi`` (the field's name), and for an ensemble ``psi_mean`` and
        ``psi_std`` beside it."""
        name = str(self.field.name or "psi")
        out = {name: self.field.rename(name)}
        if self.mean is not None and self.std is not None:
            out[f"{name}_mean"] = self.mean.rename(f"{name}_mean")
            out[f"{name}_std"] = self.std.rename(f"{name}_std")
        return xr.Dataset(out)


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


def error_vs_time(pred: xr.DataArray, ref: xr.DataArray) -> xr.DataArray:
    """The error of ``pred`` against ``ref`` slice by slice: ``error(t, metric)`` with ``metric = ["max", "rms"]``,
    the max and RMS of ``|pred - ref|`` over each time slice (sites and components), on the slices both hold.

    ``compare(pred, ref)`` is its maximum over ``t`` (``max``) and the RMS over the whole field. Plot it with
    ``err.sel(metric="max").plot()``.

    >>> import numpy as np, xarray as xr
    >>> t = np.arange(3.0)
    >>> a = xr.DataArray(np.zeros((3, 2)), dims=("t", "x"), coords={"t": t, "x": [0.0, 1.0]})
    >>> b = a + xr.DataArray([[0.0, 0.0], [3.0, 4.0], [0.0, 1.0]], dims=("t", "x"))
    >>> err = error_vs_time(a, b)
    >>> err.sel(metric="max").values.tolist(), err.sel(metric="rms").values.round(4).tolist()
    ([0.0, 4.0, 1.0], [0.0, 3.5355, 0.7071])
    """
    tdim = pred.dims[0]
    n = min(pred.sizes[tdim], ref.sizes[tdim])
    if pred.shape[1:] != ref.shape[1:]:
        raise InputError(f"error_vs_time: shapes {pred.shape} and {ref.shape} differ beyond the time axis")
    d = np.abs(np.asarray(pred.values[:n], dtype=np.float64) - np.asarray(ref.values[:n], dtype=np.float64))
    d = d.reshape(n, -1)
    values = np.stack([d.max(axis=1), np.sqrt(np.mean(d**2, axis=1))], axis=-1)
    return xr.DataArray(
        values,
        dims=(tdim, "metric"),
        coords={tdim: pred[tdim].values[:n], "metric": ["max", "rms"]},
        name="error",
        attrs={"long_name": "error against the reference, per time slice", "units": pred.attrs.get("units", "1")},
    )


def invariant_vs_time(field: xr.DataArray, invariant: Callable[[xr.DataArray], Any]) -> xr.DataArray:
    """``invariant(field)`` (e.g. ``latticedft.systems.wave_energy``) as a DataArray over ``t``, with its
    relative drift ``max |I - I_0| / |I_0|`` (absolute when ``I_0 = 0``) in ``attrs["relative_drift"]`` —
    the figure a case reports as ``invariant_drift``.

    >>> import numpy as np, xarray as xr
    >>> f = xr.DataArray(np.ones((3, 2)), dims=("t", "x"), coords={"t": np.arange(3.0)})
    >>> e = invariant_vs_time(f, lambda psi: (psi**2).sum("x") * xr.DataArray([1.0, 1.01, 0.99], dims="t"))
    >>> round(e.attrs["relative_drift"], 6)
    0.01
    """
    tdim = field.dims[0]
    out = invariant(field)
    if not isinstance(out, xr.DataArray) or out.dims != (tdim,):
        raise InputError(
            f"invariant: expected a function returning a DataArray over {tdim!r}, got "
            f"{type(out).__name__}{' with dims ' + str(out.dims) if isinstance(out, xr.DataArray) else ''}"
        )
    values = np.asarray(out.values, dtype=np.float64)
    finite = values[np.isfinite(values)]
    drift = float("nan")
    if finite.size:
        dev = float(np.max(np.abs(finite - finite[0])))
        drift = dev / abs(float(finite[0])) if finite[0] != 0 else dev
    out = out.copy()
    out.attrs["relative_drift"] = drift
    return out


def _bar(total: int, desc: str, progress: bool | None) -> Any:
    """A progress bar over ``total`` slices; ``progress=None`` shows it on a terminal and in Jupyter only."""
    return progress_bar(total, desc, progress)
