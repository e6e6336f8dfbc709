"""Serving an ensemble: every member stepped in one run (stacked as components), or, where every member is a
polynomial on the folded kernels, each member served alone one after another (:data:`MEMBERWISE`), the result
assembled as the stacked run's; and its calibration."""

from __future__ import annotations

import math
import warnings
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
from ._affine import affine_del
from ._field import slice_system
from ._folded import folds
from ._options import ServeOptions
from ._range import EXTRAPOLATION_TOL, assess, extrapolation
from ._result import LEFT_THE_BOX, ServeResult, box_reason, served_source

__all__ = [
    "serve_ensemble",
    "serves_alone",
    "MEMBERWISE",
    "MEMBERWISE_AFFINE",
    "calibration",
    "calibration_warning",
    "stopped_warning",
    "outside_warning",
    "CALIBRATION_MIN_WITHIN_2STD",
    "MIN_MEMBERS",
]

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


#: Serve a stack that folds (:func:`serves_alone`) member by member: every member on its own folded kernels, one
#: after another, the ensemble's result assembled from theirs (equal to the bit to the stacked run's, cheaper on
#: every lattice measured where slice-Newton serves: ``python -m benchmarks.ensemble_serve``). ``False``: always
#: the stacked run.
MEMBERWISE = True

#: Serve a stack member by member also where its members' DEL is affine (the affine recurrence serves them: the
#: stacked run's one recurrence was faster on the small lattices measured, ``benchmarks.ensemble_serve``).
MEMBERWISE_AFFINE = False


def serves_alone(ens: EnsembleLagrangian, fs: list[LatticeField], options: ServeOptions, where: torch.device) -> bool:
    """Whether :func:`serve_ensemble` serves ``ens`` on ``fs`` member by member (:data:`MEMBERWISE` on): n-D
    slice-Newton on the CPU where the stacked run would evaluate every member on its own folded kernels
    (``._stackfold``: every member a polynomial that :func:`._folded.folds` on each field's lattice), and, unless
    :data:`MEMBERWISE_AFFINE`, no member's DEL affine where ``options.affine`` lets the recurrence serve it."""
    if not MEMBERWISE or len(ens) < 2 or options.mode != "newton" or where.type != "cpu" or fs[0].ndim < 2:
        return False
    members = [ens.member(k) for k in range(len(ens))]
    if not all(folds(p, slice_system(p, f)) for f in fs for p in members):
        return False
    if MEMBERWISE_AFFINE or not options.affine:
        return True
    return not any(affine_del(p, f, slice_system(p, f)) for f in fs for p in members)


def serve_ensemble(
    ens: EnsembleLagrangian,
    fs: list[LatticeField],
    run: Run,
    batch: bool,
    box: float | None = None,
    alone: bool = False,
) -> list[ServeResult]:
    """Serve every member of ``ens`` on each field of ``fs`` in one stacked run; ``run(model, fields)`` serves.

    Each result's ``field`` is member 0's (the full-data model's) field, with ``mean``, ``std`` (over the
    members, ``ddof = 1``) and ``members``. When the stacked run stops (some member stops converging), every
    member is served alone: member 0 for ``field``, the others as far as each goes. A member that stops, or
    whose field goes non-finite, leaves the spread from that slice on: ``mean`` and ``std`` are over the members
    still finite on each slice, NaN where fewer than :data:`MIN_MEMBERS` are; the result names the members that
    stopped (``members_stopped``) with a warning. A ServeError from member 0 itself carries the results so far.
    With a ``box`` (the serve's, 1D), the stacked run stops where member 0 leaves it, and every other member
    stops where it leaves it itself, as alone: its field ends at that slice and the result names it among the
    members that stopped. ``alone`` (:func:`serves_alone`): every member served alone, one after another, in
    place of the stacked run, the results assembled as the stacked run's (:func:`_as_stacked`).
    """
    n, m = len(ens), ens.m
    labels = _labels(ens, fs[0])
    model = stacked(ens, labels)
    reasons: list[list[str]] = [[""] * n for _ in fs]
    solo: list[list[ServeResult | None]] | None = None
    failure: ServeError | None = None
    whole: list[list[ServeResult | None]] | None = None  # the members served alone, every one whole
    if alone:
        solo, failure, stopped = _alone(ens, fs, run, reasons)
        joint: list[ServeResult] = []
        if not stopped:  # as the stacked run had served
            joint, whole, solo = _as_stacked(ens, fs, solo, model.kind), solo, None
    else:
        try:
            joint = run(model, [_stack(f, n, labels) for f in fs])
        except ServeError as err:
            joint = _partial(err)
            solo, failure, _ = _alone(ens, fs, run, reasons)
    out = []
    for i, f in enumerate(fs):
        r = joint[i] if i < len(joint) else None
        own = solo[0][i] if solo is not None else None
        if whole is not None:  # the members' fields, as the stacked run's
            vals = _joined([s[i] for s in whole], _blank(n, f))
        else:
            vals = _member_values(r, n, m) if r is not None else _blank(n, f)
        if solo is not None:  # each member's own field, as far as it went
            vals = _joined([s[i] for s in solo], vals)
        elif box is not None:
            vals = vals.copy()  # not the stacked result's own values
            _boxed(vals, box, reasons[i])
        out.append(_result(ens, f, r, vals, own, reasons[i]))
    if failure is not None:
        raise ServeError(
            str(failure), result=out if batch else out[0], slice=failure.slice, residual=failure.residual
        ) from None
    return out


#: The fewest members still finite on a slice that give it a spread (a standard deviation with ``ddof = 1``).
MIN_MEMBERS = 2


def _partial(err: ServeError) -> list[ServeResult]:
    """The results a ServeError carries, as a list."""
    return err.result if isinstance(err.result, list) else [err.result]


def _blank(n: int, f: LatticeField) -> np.ndarray:
    """NaN values of ``n`` members' two slices of ``f``: ``(n, 2, *sites, m)``."""
    return np.full((n, 2, *f.values.shape[1:]), math.nan)


def _alone(
    ens: EnsembleLagrangian, fs: list[LatticeField], run: Run, reasons: list[list[str]]
) -> tuple[list[list[ServeResult | None]], ServeError | None, bool]:
    """Every member served alone on ``fs``: ``(results per member, member 0's ServeError or None, whether any
    member's serve stopped with a ServeError)``; a member's stop reason on field ``i`` goes to
    ``reasons[i][k]``."""
    out: list[list[ServeResult | None]] = []
    failure = None
    stopped = False
    for k in range(len(ens)):
        try:
            got = run(ens.member(k), fs)
        except ServeError as err:
            failure = err if k == 0 else failure
            stopped = True
            got = _partial(err)
            for i in range(len(fs)):
                done = i < len(got) and got[i] is not None and got[i].complete
                reasons[i][k] = "" if done else str(err)
        for i in range(min(len(fs), len(got))):  # stopped short without an error: it left the box
            r = got[i]
            if r is not None and not reasons[i][k] and r.reason.startswith(LEFT_THE_BOX):
                reasons[i][k] = r.reason
        out.append([got[i] if i < len(got) else None for i in range(len(fs))])
    return out, failure, stopped


def _as_stacked(
    ens: EnsembleLagrangian, fs: list[LatticeField], solo: list[list[ServeResult | None]], kind: str
) -> list[ServeResult]:
    """The results the stacked run (a model of ``kind``) gives on ``fs`` where every member served alone
    (``solo``, per member per field) went through whole: member 0's own, its field's ``source`` the stacked
    model's, its ``wall_time`` the members' together and ``sites_per_second`` over that time."""
    out = []
    for i, f in enumerate(fs):
        runs = [s[i] for s in solo]
        own = runs[0]
        assert own is not None and all(r is not None for r in runs)
        wall = sum(r.wall_time for r in runs if r is not None)
        sites = (own.slices - 2) * slice_system(ens.member(0), f).n
        rate = sites / wall if wall > 0 else math.inf
        field = own.field.copy(deep=False)
        field.attrs = {**own.field.attrs, "source": served_source(kind)}
        out.append(replace(own, field=field, wall_time=wall, sites_per_second=rate))
    return out


def _boxed(vals: np.ndarray, box: float, reasons: list[str]) -> None:
    """Every member but member 0 (whose own box test ends the stacked run) stopped where it leaves ``box`` itself,
    as served alone: the first solved slice ``s`` whose ``|psi|`` over the member's own components exceeds it is
    its last (the values after it set to NaN), and ``reasons[k]`` says so. ``vals``: ``(members, nt, m)``."""
    for k in range(1, vals.shape[0]):
        own = vals[k].reshape(vals.shape[1], -1)
        out = np.sqrt((own * own).sum(-1)) > box
        out[:2] = False  # the given slices are not tested
        if out.any():
            at = int(np.argmax(out))
            if at + 1 < vals.shape[1]:
                vals[k, at + 1 :] = math.nan
                reasons[k] = box_reason(box, at)


def _joined(results: list[ServeResult | None], like: np.ndarray) -> np.ndarray:
    """The members' own fields ``(members, nt, *sites, m)`` (NaN beyond where each stopped)."""
    nt = max([like.shape[1], *(r.field.sizes[r.field.dims[0]] for r in results if r is not None)])
    out = np.full((len(results), nt, *like.shape[2:]), math.nan)
    for k, r in enumerate(results):
        if r is not None:
            v = np.asarray(r.field.values, dtype=np.float64).reshape(r.field.shape[0], *like.shape[2:])
            out[k, : v.shape[0]] = v
    return out


def _result(
    ens: EnsembleLagrangian,
    f: LatticeField,
    joint: ServeResult | None,
    vals: np.ndarray,
    own: ServeResult | None,
    reasons: list[str],
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
    lost = _stops(full, reasons)
    mean, std = _spread(full)
    outside = _outside(ens, f, full)
    base.members_stopped, base.members_outside = lost or None, outside or None
    if outside:
        base.warnings.append(outside_warning(outside, len(ens)))
    if lost:
        base.warnings.append(stopped_warning(lost, len(ens)))
    members = xr.concat([base.field.copy(data=_layout(base.field, v)) for v in full], dim="member")
    members = members.assign_coords(member=np.arange(len(ens))).rename("members")
    mean_da = base.field.copy(data=_layout(base.field, mean))
    std_da = base.field.copy(data=_layout(base.field, std))
    name = base.field.name or "psi"
    mean_da.attrs = {**mean_da.attrs, "long_name": f"ensemble mean of {name}"}
    std_da.attrs = {**std_da.attrs, "long_name": f"ensemble standard deviation of {name}"}
    if lost:  # read by the figure, which marks where members stopped
        std_da.attrs["stopped_members"] = np.array([s["member"] for s in lost], dtype=np.int64)
        std_da.attrs["stopped_at_slice"] = np.array([s["slice"] for s in lost], dtype=np.int64)
    if outside:  # and where members left their training range
        std_da.attrs["outside_members"] = np.array([s["member"] for s in outside], dtype=np.int64)
        std_da.attrs["outside_from_slice"] = np.array([s["slice"] for s in outside], dtype=np.int64)
    mean_da.attrs.pop("source", None)
    std_da.attrs.pop("source", None)
    return replace(base, mean=mean_da, std=std_da, members=members)


def _stops(full: np.ndarray, reasons: list[str]) -> list[dict[str, Any]]:
    """The members that stop short of the last slice, or go non-finite: ``{member, slice, reason}`` each, where
    ``slice`` is the first slice the member does not hold finite (its values there and after are set to NaN)."""
    nt = full.shape[1]
    finite = np.isfinite(full.reshape(full.shape[0], nt, -1)).all(axis=2)
    out = []
    for k in range(full.shape[0]):
        if finite[k].all():
            continue
        at = int(np.argmin(finite[k]))
        full[k, at:] = math.nan
        why = reasons[k] if k < len(reasons) and reasons[k] else "its field is not finite there"
        out.append({"member": k, "slice": at, "reason": why})
    return out


def _outside(ens: EnsembleLagrangian, f: LatticeField, full: np.ndarray) -> list[dict[str, Any]]:
    """The resampled members (1 .. N - 1; member 0's range is the task's own, checked as for a single model)
    whose served field leaves their own training range (each member learned on its own data):
    ``{member, slice, feature, excess}`` each, ``slice`` the first where some feature's excess passes
    :data:`._range.EXTRAPOLATION_TOL`, ``feature`` and ``excess`` the largest excess (relative to the feature's
    training span) over the slices the member served. ``full``: the members' fields ``(members, nt, *sites, m)``,
    NaN from where each stopped (not tested there)."""
    out = []
    nt = full.shape[1]
    for k in range(1, full.shape[0]):
        finite = np.isfinite(full[k].reshape(nt, -1)).all(axis=1)
        reach = nt if finite.all() else int(np.argmin(finite))
        if reach < 2:
            continue
        values = torch.from_numpy(np.ascontiguousarray(full[k, :reach]))
        ext = extrapolation(ens.member(k), f.with_values(values))
        if ext is None:
            continue
        vals = np.asarray(ext.values, dtype=np.float64)
        beyond = np.nonzero((vals > EXTRAPOLATION_TOL).any(axis=1))[0]
        if not beyond.size:
            continue
        peak = vals.max(axis=0)
        j = int(np.argmax(peak))
        feature = str(ext["feature"].values[j])
        out.append({"member": k, "slice": int(beyond[0]), "feature": feature, "excess": float(peak[j])})
    return out


def outside_warning(outside: list[dict[str, Any]], members: int) -> str:
    """The one-line warning of members whose fields leave their own training range (``{member, slice, feature,
    excess}`` each) in an ensemble of ``members``."""
    each = "; ".join(
        f"member {s['member']} from slice {s['slice']} (by up to {s['excess']:.3g} of the training span in "
        f"{s['feature']})"
        for s in outside
    )
    return (
        f"ensemble: {len(outside)} of {members - 1} resampled members leave their own training range (tolerance "
        f"{EXTRAPOLATION_TOL:g}): {each}; their L_d is not known there, and the spread there is extrapolated"
    )


def _spread(full: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation (``ddof = 1``) over the members finite on each slice; NaN on a slice with
    fewer than :data:`MIN_MEMBERS` of them."""
    if np.isfinite(full).all():  # every member on every slice
        return full.mean(axis=0), full.std(axis=0, ddof=1)
    count = np.isfinite(full).sum(axis=0)
    few = count < MIN_MEMBERS
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices
        mean = np.nanmean(full, axis=0)
        std = np.nanstd(full, axis=0, ddof=1)
    mean[few], std[few] = math.nan, math.nan
    return mean, std


def stopped_warning(lost: list[dict[str, Any]], members: int) -> str:
    """The one-line warning of members that stopped (``{member, slice, reason}`` each) in an ensemble of
    ``members``."""
    first = min(s["slice"] for s in lost)
    left = members - len(lost)
    each = "; ".join(f"member {s['member']} at slice {s['slice']} ({s['reason']})" for s in lost)
    return (
        f"ensemble: {len(lost)} of {members} members stopped: {each}; from slice {first} on the spread is over the "
        f"{left} member(s) still served"
        + (f" (NaN: fewer than {MIN_MEMBERS})" if left < MIN_MEMBERS else "")
        + ", and a member stopping is itself a sign that the prediction is uncertain"
    )


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
