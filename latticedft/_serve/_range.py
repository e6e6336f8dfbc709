"""How far a served field leaves the range the model was trained on.

``learn`` records, per input feature of the stencil (the stencil mean and the difference along each
axis, per component: :meth:`AbstractLagrangian.mean_and_differences`), the minimum and maximum over the
training cells (:meth:`AbstractLagrangian.trained_range`). Serving measures, per time slice, how far its
cells lie outside that range: per feature the largest excess beyond the minimum or maximum, in units of
the feature's training span (0 inside). A learned ``L_d`` is only known where it was trained; beyond
``EXTRAPOLATION_TOL`` of the span a served field carries a warning.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
import xarray as xr

from .._lattice import LatticeField, dataarray_parts, gather_cells, keep_last, like_dataarray, with_time
from .._models import AbstractLagrangian
from .._options import option

__all__ = [
    "EXTRAPOLATION_TOL",
    "feature_labels",
    "extrapolation",
    "extrapolation_summary",
    "extrapolation_warning",
]

#: A served field whose cells leave the training range of a feature by more than this fraction of the
#: feature's training span is reported (a warning; the field is still served).
EXTRAPOLATION_TOL = 0.05


def feature_labels(model: AbstractLagrangian, dims: tuple[str, ...], components: tuple[str, ...] | None) -> list[str]:
    """Names of the features, in the order of ``trained_range()[0].reshape(-1)``: ``mean``, ``d_t``,
    ``d_x`` ... (the difference along each lattice dim), each per component (``mean[x]``) for vector fields."""
    names = ["mean", *[f"d_{d}" for d in dims]]
    if components is None:
        return names
    return [f"{name}[{c}]" for name in names for c in components]


def _excess(model: AbstractLagrangian, rng: torch.Tensor, f: LatticeField, values: torch.Tensor) -> np.ndarray:
    """``(slices - 1, features)``: per anchor slice, the largest excess of its cells beyond the range."""
    lo, hi = rng[0], rng[1]
    span = hi - lo
    span = torch.maximum(span, 1e-12 * torch.maximum(lo.abs(), hi.abs())).clamp_min(1e-300)
    nt = values.shape[0]
    nsite = max(int(np.prod(values.shape[1:-1])), 1)
    width = max(2, min(nt, option("range_sites_per_pass") // nsite + 1))
    out = np.zeros((nt - 1, lo.numel()))
    j = 0
    while j < nt - 1:
        hi_j = min(j + width, nt)
        cells = gather_cells(values[j:hi_j], model.stencil, f.boundary)
        feats = model.mean_and_differences(cells)  # (slices, *cells, n + 1, m)
        ex = torch.maximum(lo - feats, feats - hi).clamp_min(0.0) / span
        ex = torch.nan_to_num(ex, nan=math.inf)  # a non-finite value lies outside any range
        out[j : hi_j - 1] = ex.reshape(ex.shape[0], -1, lo.numel()).amax(1).numpy()
        j = hi_j - 1
    return out


def extrapolation(model: AbstractLagrangian, f: LatticeField, compiled: Any = None) -> xr.DataArray | None:
    """``extrapolation(t, feature)`` of field ``f`` against ``model``'s training range (None without one).

    Per time slice, the largest excess beyond the training range of the cells that hold the slice, per
    feature, relative to the feature's training span: 0 inside the range, 0.5 half a span outside.
    ``compiled(model, values)``: the excess per anchor slice in one compiled pass (``None``: not here).
    """
    rng = model.trained_range()
    nt = f.shape[0]
    if rng is None or nt < 2 or tuple(rng.shape[1:]) != (f.ndim + 1, f.ncomp):
        return None
    per_anchor = None if compiled is None else compiled(model, f.values.detach())
    if per_anchor is None:
        per_anchor = _excess(model, rng.to(torch.float64), f, f.values.detach())
    return _extrapolation_array(model, f, per_anchor)


def _extrapolation_array(
    model: AbstractLagrangian, f: LatticeField, per_anchor: np.ndarray, shared: dict | None = None
) -> xr.DataArray:
    """:func:`extrapolation` from the excess per anchor slice ``(slices - 1, features)``. ``shared``: the
    coordinates already built for other members of a batch, by time axis (reused, not rebuilt)."""
    nt = f.shape[0]
    per_slice = np.zeros((nt, per_anchor.shape[1]))
    per_slice[:-1] = per_anchor  # the cells anchored on a slice ...
    per_slice[1:] = np.maximum(per_slice[1:], per_anchor)  # ... and those anchored on the one before
    tdim = f.dims[0]
    t = np.asarray(f.coords[tdim], dtype=np.float64)
    if t.size != nt:
        t = t[0] + f.spacing[0] * np.arange(nt, dtype=np.float64)
    attrs = {
        "long_name": "excess of the stencil inputs beyond the training range, relative to its span",
        "tolerance": EXTRAPOLATION_TOL,
    }
    key = (tdim, t.tobytes(), f.dims, f.components)
    parts = None if shared is None else shared.get(key)
    if parts is not None:  # built around the coordinates of a member already recorded
        return like_dataarray(parts, per_slice, attrs)
    kept = _KEPT.get(key[2:]) if shared is None else None
    if kept is not None:  # the feature coordinate of an earlier field's, its own time coordinate
        return like_dataarray(with_time(kept, tdim, t), per_slice, attrs)
    coords = xr.Coordinates({tdim: t, "feature": feature_labels(model, f.dims, f.components)})
    out = xr.DataArray(per_slice, dims=(tdim, "feature"), coords=coords, name="extrapolation", attrs=attrs)
    if shared is not None:
        shared[key] = dataarray_parts(out)
    elif nt <= 1 << 16:  # a long time axis is not kept
        keep_last(_KEPT, key[2:], dataarray_parts(out), 4)
    return out


#: An extrapolation array's coordinates per lattice dims and components, the last few (:func:`_extrapolation_array`
#: builds later arrays around them with their own time coordinate, as :func:`.._lattice.to_dataarrays` does).
_KEPT: dict[tuple[Any, ...], Any] = {}


def extrapolation_summary(ext: xr.DataArray | None) -> dict[str, Any] | None:
    """``{"max": {feature: value}, "first_slice": k or None, "tolerance": ...}``: the largest excess per
    feature and the first time slice (index) where some feature's excess passes :data:`EXTRAPOLATION_TOL`."""
    if ext is None:
        return None
    vals = np.asarray(ext.values, dtype=np.float64)
    outside = np.nonzero((vals > EXTRAPOLATION_TOL).any(axis=1))[0]
    return {
        "max": {str(k): float(v) for k, v in zip(ext["feature"].values, vals.max(axis=0))},
        "first_slice": int(outside[0]) if outside.size else None,
        "tolerance": EXTRAPOLATION_TOL,
    }


def extrapolation_warning(ext: xr.DataArray | None) -> str | None:
    """A one-line warning when ``ext`` passes :data:`EXTRAPOLATION_TOL` somewhere, else None."""
    if ext is None:
        return None
    vals = np.asarray(ext.values, dtype=np.float64)
    outside = np.nonzero((vals > EXTRAPOLATION_TOL).any(axis=1))[0]
    if not outside.size:
        return None
    peak = vals.max(axis=0)
    k = int(np.argmax(peak))
    return (
        f"extrapolation: the served field leaves the training range from slice {int(outside[0])} on, by up to "
        f"{peak[k]:.3g} of the training span in {ext['feature'].values[k]} (tolerance {EXTRAPOLATION_TOL:g}); "
        "the learned L_d is not known there"
    )


def assess(model: AbstractLagrangian, f: LatticeField, compiled: Any = None) -> tuple[xr.DataArray | None, list[str]]:
    """``(extrapolation, warnings)`` of a served field ``f``: what a ``ServeResult`` reports of its range
    (``compiled``: as :func:`extrapolation`'s)."""
    ext = extrapolation(model, f, compiled)
    warning = extrapolation_warning(ext)
    return ext, [warning] if warning else []


def assess_batch(
    model: AbstractLagrangian, fields: list[LatticeField], values: torch.Tensor
) -> list[tuple[xr.DataArray | None, list[str]]]:
    """:func:`assess` of every member of a batch of 1D fields, their excess computed in one pass over the
    batch's values ``(members, slices, m)`` (member ``k`` holds ``fields[k].shape[0]`` of those slices)."""
    rng = model.trained_range()
    f0 = fields[0]
    if rng is None or tuple(rng.shape[1:]) != (f0.ndim + 1, f0.ncomp) or values.shape[1] < 2:
        return [assess(model, f) for f in fields]
    rng = rng.to(torch.float64)
    lo, hi = rng[0], rng[1]
    span = torch.maximum(hi - lo, 1e-12 * torch.maximum(lo.abs(), hi.abs())).clamp_min(1e-300)  # as _excess
    feats = model.mean_and_differences(gather_cells(values, model.stencil, f0.boundary, batch=1))
    ex = torch.nan_to_num(torch.maximum(lo - feats, feats - hi).clamp_min(0.0) / span, nan=math.inf)
    per_anchor = ex.reshape(ex.shape[0], ex.shape[1], lo.numel()).numpy()
    out = []
    shared: dict = {}  # members of one length and start share their coordinates
    outside = np.asarray((per_anchor > EXTRAPOLATION_TOL).any(axis=2))  # (members, anchors): where a warning may be due
    for k, f in enumerate(fields):
        ext = _extrapolation_array(model, f, per_anchor[k, : f.shape[0] - 1], shared) if f.shape[0] >= 2 else None
        warning = extrapolation_warning(ext) if ext is not None and outside[k, : f.shape[0] - 1].any() else None
        out.append((ext, [warning] if warning else []))
    return out
