"""The Dirichlet strips of the slices a field's data does not hold: from ``boundary_value`` (a number, or a
function of the slice's time and the spatial coordinates), so that a field can be served past the end of
its data (``serve(..., boundary_value=0.0)``, ``[[serve]] boundary_value``)."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from .._boundary import missing_edges
from .._errors import InputError
from .._lattice import LatticeField


def edge_function(value: Any) -> Callable[..., Any]:
    """``value(t, *coords)`` for a number (a constant), a function, or a ``"module:function"`` string."""
    if callable(value):
        return value
    if isinstance(value, str):
        module, _, name = value.partition(":")
        try:
            fn = getattr(importlib.import_module(module), name, None)
        except Exception as exc:
            raise InputError.at("boundary_value", f"cannot import {value!r} ({type(exc).__name__})") from None
        if not callable(fn):
            raise InputError.at("boundary_value", f"{value!r}: module {module!r} has no function {name!r}")
        return fn
    constant = float(value)
    return lambda t, *coords: constant


def edge_slices(f: LatticeField, value: Any, lo: int, hi: int) -> torch.Tensor:
    """``(hi - lo, *spatial, m)``: slices ``lo .. hi - 1`` of ``f``'s lattice as ``boundary_value`` gives them
    (``value(t, *coords)`` on the whole lattice; serving keeps the Dirichlet sites of each)."""
    fn = edge_function(value)
    spatial = f.dims[1:]
    grids = np.meshgrid(*(np.asarray(f.coords[d], dtype=np.float64) for d in spatial), indexing="ij")
    t0, dt = float(f.coords[f.dims[0]][0]), f.spacing[0]
    shape = (*f.shape[1:], f.ncomp)
    out = np.empty((hi - lo, *shape))
    for k, i in enumerate(range(lo, hi)):
        values = np.asarray(fn(t0 + i * dt, *grids), dtype=np.float64)
        if f.components is None and values.shape == shape[:-1]:
            values = values[..., None]
        try:
            out[k] = np.broadcast_to(values, shape)
        except ValueError:
            raise InputError.at(
                "boundary_value", f"the function returned shape {values.shape} on a lattice of shape {shape}"
            ) from None
        if not np.isfinite(out[k]).all():
            raise InputError.at("boundary_value", f"not finite on slice {i} (t = {t0 + i * dt:.6g})")
    return torch.from_numpy(out)


def known_slices(f: LatticeField, data: Callable[[int, int], Any], nt: int, value: Any, lo: int, hi: int) -> Any:
    """Slices ``lo .. hi - 1``: from ``data(lo, hi)`` (the field's own slices, ``nt`` of them) where it holds
    them, from ``boundary_value`` beyond."""
    if hi <= nt or value is None:
        return data(lo, hi)
    beyond = edge_slices(f, value, max(lo, nt), hi)
    if lo >= nt:
        return beyond
    return torch.cat([torch.as_tensor(np.asarray(data(lo, nt)), dtype=torch.float64), beyond])


__all__ = ["edge_function", "edge_slices", "known_slices"]


def require_edges(f: LatticeField, nt: int, steps: int, boundary_value: Any) -> None:
    """Refuse, in one line, a field whose Dirichlet strips are needed on ``steps`` slices when its data holds
    ``nt`` (``f``'s, or its file's) and no ``boundary_value`` gives the others (the whole field's and the
    window's check)."""
    missing = missing_edges(f.boundary, f.dims, nt, steps)
    if missing and boundary_value is None:
        axis, kind = missing
        raise InputError(
            f"init: holds {nt} time slices but the {kind.title} boundary along "
            f"{axis!r} needs its strips on all {steps} slices; give the whole field, "
            "fewer slices, a boundary_value, or a periodic boundary"
        )
