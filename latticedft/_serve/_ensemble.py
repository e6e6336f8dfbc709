"""Serving an ensemble: every member stepped in one run (stacked as components), and its calibration."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import torch
import xarray as xr

from .._errors import ServeError
from .._lattice import LatticeField
from .._models import AbstractLagrangian, EnsembleLagrangian
from .._models._ensemble import stacked
from ._range import assess
from ._result import ServeResult

__all__ = ["serve_ensemble", "calibration", "calibration_warning", "CALIBRATION_MIN_WITHIN_2STD"]

#: A task whose error lies within 2 standard deviations of the ensemble on fewer than this fraction of its
#: slices gets a warning: the spread understates the error (a Gaussian error bar holds 95 %).
CALIBRATION_MIN_WITHIN_2STD = 0.8

Run = Callable[[AbstractLagrangian, list[LatticeField]], list[ServeResult]]


def _stack(f: LatticeField, members: int, labels: tuple[str, ...]) -> LatticeField:
    """``f`` repeated ``members`` times along its components (member-major)."""
    return replace(f, values=torch.cat([f.values] * members, dim=-1).contiguous(), components=labels)


def _labels(ens: EnsembleLagrangian, f: LatticeField) -> tuple[str, ...]:
    comps = f.components or ("",)
    return tuple(f"member{k}" + (f"_{c}" if c else "") for k in range(len(ens)) for c in comps)


def _member_values(r: ServeResult, members: int, m: int) -> np.ndarray:
    """``(members, nt, *sites, m)`` from a stacked result's field ``(nt, *sites, members * m)``."""
    v = np.asarray(r.field.values, dtype=np.float64)
    v = v.reshape(*v.shape[:-1], members, m)
    return np.moveaxis(v, -2, 0)


def serve_ensemble(ens: EnsembleLagrangian, fs: list[LatticeField], run: Run, batch: bool) -> list[ServeResult]:
    """Serve every member of ``ens`` on each field of ``fs`` in one stacked run; ``run(model, fields)`` serves.

    Each result's ``field`` is member 0's (the full-data model's) field, with ``mean``, ``std`` (over all
    members, ``ddof = 1``) and ``members``. When the stacked run stops (some member stops converging), member 0
    is served alone for ``field``, and the spread covers only the slices every member reached (NaN after, with
    a warning). A ServeError from member 0 itself carries the results so far.
    """
    n, m = len(ens), ens.m
    labels = _labels(ens, fs[0])
    model = stacked(ens, labels)
    stopped: ServeError | None = None
    try:
        joint = run(model, [_stack(f, n, labels) for f in fs])
    except ServeError as err:
        stopped = err
        joint = err.result if isinstance(err.result, list) else [err.result]
    solo: list[ServeResult] | None = None
    failure: ServeError | None = None
    if stopped is not None:
        try:
            solo = run(ens.member(0), fs)
        except ServeError as err:
            failure = err
            solo = err.result if isinstance(err.result, list) else [err.result]
    out = []
    for i, f in enumerate(fs):
        r = joint[i] if i < len(joint) else None
        vals = _member_values(r, n, m) if r is not None else np.full((n, 2, *f.values.shape[1:]), math.nan)
        own = solo[i] if solo is not None and i < len(solo) else None
        out.append(_result(ens, f, r, vals, own, stopped))
    if failure is not None:
        raise ServeError(
            str(failure), result=out if batch else out[0], slice=failure.slice, residual=failure.residual
        ) from None
    return out


def _result(
    ens: EnsembleLagrangian,
    f: LatticeField,
    joint: ServeResult | None,
    vals: np.ndarray,
    own: ServeResult | None,
    stopped: ServeError | None,
) -> ServeResult:
    """The result of one field: member 0's field and run, the ensemble's spread beside it."""
    if own is None:
        assert joint is not None
        lf = f.with_values(torch.from_numpy(np.ascontiguousarray(vals[0])))
        field = lf.to_dataarray()
        field.attrs = dict(joint.field.attrs)
        ext, warnings = assess(ens.member(0), lf)
        base = replace(joint, field=field, extrapolation=ext, warnings=warnings)
    else:
        base = replace(own, warnings=list(own.warnings))
    tdim = base.field.dims[0]
    nt = base.field.sizes[tdim]
    full = np.full((vals.shape[0], nt, *vals.shape[2:]), math.nan)
    reach = min(nt, vals.shape[1])
    full[:, :reach] = vals[:, :reach]
    if stopped is not None:
        base.warnings.append(
            f"ensemble: the spread covers slices 0..{reach - 1} only: the stacked members stopped there ({stopped}); "
            "a member stopping is itself a sign that the prediction is uncertain"
        )
    members = xr.concat([base.field.copy(data=_layout(base.field, v)) for v in full], dim="member")
    members = members.assign_coords(member=np.arange(len(ens))).rename("members")
    with np.errstate(invalid="ignore"):
        mean = base.field.copy(data=_layout(base.field, full.mean(axis=0)))
        std = base.field.copy(data=_layout(base.field, full.std(axis=0, ddof=1)))
    mean.attrs = {**mean.attrs, "long_name": f"ensemble mean of {base.field.name or 'psi'}"}
    std.attrs = {**std.attrs, "long_name": f"ensemble standard deviation of {base.field.name or 'psi'}"}
    mean.attrs.pop("source", None)
    std.attrs.pop("source", None)
    return replace(base, mean=mean, std=std, members=members)


def _layout(like: xr.DataArray, v: np.ndarray) -> np.ndarray:
    """Engine values ``(nt, *sites, m)`` in the layout of ``like`` (no component axis for a scalar field)."""
    return v[..., 0] if v.shape[-1] == 1 and like.ndim == v.ndim - 1 else v


def calibration(pred: xr.DataArray, std: xr.DataArray, ref: xr.DataArray) -> dict[str, Any]:
    """How well the ensemble's spread predicts the error of ``pred`` against ``ref``, slice by slice.

    Per served slice ``t`` (the two initial slices excluded), the RMS over sites and components of the error
    ``pred - ref`` and of ``std``. Returns ``within_2std`` and ``within_3std`` (fraction of slices whose error
    is at most 2 and 3 times their std), ``std_over_error`` (mean std over mean error: 1 is honest, below 1
    over-confident), ``mean_std``, ``mean_error`` and ``slices`` (the slices counted).

    >>> import numpy as np, xarray as xr
    >>> t = np.arange(6.0)
    >>> ref = xr.DataArray(np.zeros(6), dims="t", coords={"t": t})
    >>> pred = ref + [0, 0, 0.1, 0.1, 0.3, 0.1]
    >>> cal = calibration(pred, ref + 0.1, ref)
    >>> cal["within_2std"], cal["within_3std"], cal["slices"]
    (0.75, 1.0, 4)
    """
    tdim = pred.dims[0]
    n = min(pred.sizes[tdim], ref.sizes[tdim], std.sizes[tdim])
    e = (np.asarray(pred.values[:n], dtype=np.float64) - np.asarray(ref.values[:n], dtype=np.float64)).reshape(n, -1)
    s = np.asarray(std.values[:n], dtype=np.float64).reshape(n, -1)
    with np.errstate(invalid="ignore"):
        err = np.sqrt(np.mean(e**2, axis=1))
        spread = np.sqrt(np.mean(s**2, axis=1))
    keep = np.isfinite(err) & np.isfinite(spread) & (np.arange(n) >= 2)
    err, spread = err[keep], spread[keep]
    if not err.size:
        return {"slices": 0, "within_2std": None, "within_3std": None, "std_over_error": None}
    mean_err = float(err.mean())
    return {
        "slices": int(err.size),
        "within_2std": float(np.mean(err <= 2 * spread)),
        "within_3std": float(np.mean(err <= 3 * spread)),
        "std_over_error": float(spread.mean() / mean_err) if mean_err > 0 else None,
        "mean_std": float(spread.mean()),
        "mean_error": mean_err,
    }


def calibration_warning(cal: dict[str, Any]) -> str | None:
    """A one-line warning when fewer than :data:`CALIBRATION_MIN_WITHIN_2STD` of the slices lie within 2 std."""
    within = cal.get("within_2std")
    if within is None or within >= CALIBRATION_MIN_WITHIN_2STD:
        return None
    return (
        f"calibration: the error lies within 2 std of its error bar on only {100 * within:.0f} % of the slices "
        f"(expected >= {100 * CALIBRATION_MIN_WITHIN_2STD:.0f} %; std/error = {cal.get('std_over_error') or 0:.2g}): "
        "the band understates the error, which may be larger than it shows"
    )
