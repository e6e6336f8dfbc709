"""Training data: fields checked against each other and against the model, and their sizes and scales."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import torch
import xarray as xr

from .._action import second_time_difference
from .._errors import InputError
from .._lattice import BoundaryKinds, LatticeField, as_lattice_field, interior_slices
from .._models import AbstractLagrangian

__all__ = ["as_fields", "check_model_lattice", "n_sites", "kinetic_scale", "stacked", "time_split"]


def as_fields(data: Any, boundary: BoundaryKinds | None) -> list[LatticeField]:
    """One DataArray or a list of them, as lattice fields of one lattice spacing and component layout."""
    items = list(data) if isinstance(data, (list, tuple)) else [data]
    if not items:
        raise InputError("data: no training fields given")
    fields = []
    for i, d in enumerate(items):
        src = None if len(items) == 1 else f"data[{i}]"
        if isinstance(d, xr.DataArray) and "source_file" in d.attrs:
            src = str(d.attrs["source_file"])
        fields.append(as_lattice_field(d, source=src, boundary=boundary))
    ref = fields[0]
    for i, f in enumerate(fields[1:], 1):
        name = f"data[{i}]"
        if f.ndim != ref.ndim:
            raise InputError(f"{name}: has {f.ndim} lattice dims {f.dims}; data[0] has {ref.ndim} {ref.dims}")
        if f.components != ref.components:
            raise InputError(
                f"{name}: component labels {list(f.components or [])} differ from data[0]'s "
                f"{list(ref.components or [])}"
            )
        if f.ncomp != ref.ncomp:
            raise InputError(f"{name}: has {f.ncomp} components; data[0] has {ref.ncomp}")
        for k, (a, b) in enumerate(zip(f.spacing, ref.spacing)):
            if not math.isclose(a, b, rel_tol=1e-6):
                raise InputError(
                    f"{name}: spacing along {f.dims[k]!r} is {a:.6g}; data[0] has {b:.6g} "
                    "(a discrete theory belongs to one lattice spacing)"
                )
    return fields


def check_model_lattice(model: AbstractLagrangian, f: LatticeField, what: str) -> None:
    """Refuse a field whose lattice (dims, components, spacing) is not the one the model is bound to."""
    if model.has_stencil and model.stencil.ndim != f.ndim:
        raise InputError(f"{what}: has {f.ndim} lattice dims but the model's stencil has {model.stencil.ndim}")
    if model.bound:
        if model.m != f.ncomp:
            raise InputError(f"{what}: has {f.ncomp} component(s) but the model was learned with {model.m}")
        if model.components and f.components and tuple(model.components) != tuple(f.components):
            raise InputError(
                f"{what}: component labels {list(f.components)} differ from the model's {list(model.components)}"
            )
        for k, (a, b) in enumerate(zip(f.spacing, model.spacing)):
            if not math.isclose(a, b, rel_tol=1e-6):
                raise InputError(
                    f"{what}: spacing along {f.dims[k]!r} is {a:.6g} but the model was learned at "
                    f"{b:.6g} (a discrete theory belongs to its lattice)"
                )


def n_sites(f: LatticeField, model: AbstractLagrangian) -> int:
    """Interior sites of ``f``: those carrying a DEL equation."""
    inner = interior_slices(f.shape, model.stencil, f.boundary)
    return int(np.prod([len(range(*s.indices(n))) for s, n in zip(inner, f.shape)]))


def kinetic_scale(fields: list[LatticeField], model: AbstractLagrangian, mbar: torch.Tensor | None) -> float:
    """rms over interior sites of the M-weighted second time difference, ``prod(h) M d2psi``
    (``M = -I / h_0^2`` when ``mbar`` is ``None``): the size a DEL residual is measured against."""
    h = model.spacing
    total, count = 0.0, 0
    for f in fields:
        d2 = second_time_difference(f, model.stencil)
        mat = -torch.eye(f.ncomp, dtype=d2.dtype) / h[0] ** 2 if mbar is None else mbar
        v = math.prod(h) * torch.einsum("ij,...j->...i", mat, d2)
        total += float((v**2).sum())
        count += d2[..., 0].numel()
    return math.sqrt(total / max(count, 1))


def stacked(fields: list[LatticeField]) -> list[LatticeField]:
    """Fields of one shape and periodicity stacked along a batch axis: one pass instead of one per field."""
    groups: dict[tuple, list[LatticeField]] = {}
    for f in fields:
        groups.setdefault((f.shape, f.boundary), []).append(f)
    return [
        g[0] if len(g) == 1 else replace(g[0], values=torch.stack([f.values for f in g]), batch=1)
        for g in groups.values()
    ]


def time_split(f: LatticeField) -> tuple[LatticeField, LatticeField] | None:
    """The first 70 % of the time slices and the rest (``None`` when either part is under 3 slices)."""
    nt = f.shape[0]
    cut = int(round(0.7 * nt))
    if cut < 3 or nt - cut < 3:
        return None
    return f.with_values(f.values[:cut]), f.with_values(f.values[cut:])
