"""Training data: fields checked against each other and against the model, and their sizes and scales."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import torch
import xarray as xr

from .._action import check_model_lattice, second_time_difference
from .._errors import InputError
from .._lattice import BoundaryKinds, LatticeField, as_lattice_field, gather_cells, interior_slices
from .._models import AbstractLagrangian
from ._source import check_alike

__all__ = [
    "as_fields",
    "check_model_lattice",
    "n_sites",
    "kinetic_sums",
    "kinetic_scale",
    "stacked",
    "split_point",
    "time_split",
    "site_sums",
]


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
    check_alike(fields)
    return fields


def n_sites(f: LatticeField, model: AbstractLagrangian) -> int:
    """Interior sites of ``f``: those carrying a DEL equation."""
    inner = interior_slices(f.shape, model.stencil, f.boundary)
    return int(np.prod([len(range(*s.indices(n))) for s, n in zip(inner, f.shape)]))


def kinetic_sums(f: LatticeField, model: AbstractLagrangian, mbar: torch.Tensor | None) -> tuple[float, int]:
    """(sum of squares, number of sites) of ``prod(h) M d2psi`` over the interior sites of ``f``
    (``M = -I / h_0^2`` when ``mbar`` is ``None``)."""
    h = model.spacing
    d2 = second_time_difference(f, model.stencil)
    mat = -torch.eye(f.ncomp, dtype=d2.dtype) / h[0] ** 2 if mbar is None else mbar
    v = math.prod(h) * torch.einsum("ij,...j->...i", mat, d2)
    return float((v**2).sum()), d2[..., 0].numel()


def kinetic_scale(fields: list[LatticeField], model: AbstractLagrangian, mbar: torch.Tensor | None) -> float:
    """rms over interior sites of the M-weighted second time difference, ``prod(h) M d2psi``
    (``M = -I / h_0^2`` when ``mbar`` is ``None``): the size a DEL residual is measured against."""
    total, count = 0.0, 0
    for f in fields:
        s, n = kinetic_sums(f, model, mbar)
        total += s
        count += n
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


def split_point(nt: int) -> int | None:
    """Where a single field's time slices are split for ``ridge="auto"``: after 70 % of them (``None`` when
    either part would have under 3 slices)."""
    cut = int(round(0.7 * nt))
    if cut < 3 or nt - cut < 3:
        return None
    return cut


def time_split(f: LatticeField) -> tuple[LatticeField, LatticeField] | None:
    """The first 70 % of the time slices and the rest (``None`` when either part is under 3 slices)."""
    cut = split_point(f.shape[0])
    if cut is None:
        return None
    return f.with_values(f.values[:cut]), f.with_values(f.values[cut:])


def site_sums(model: AbstractLagrangian, f: LatticeField, d: torch.Tensor) -> torch.Tensor:
    """``prod(h) sum_a d[y - s_a, a]`` on the interior sites ``y`` of ``f``: per-cell derivatives ``d``
    (``(*cells, K, ...)``, one entry per stencil point) added onto the sites they belong to (the adjoint of
    the cell gather). With ``d = dL/dx`` it is the DEL residual; with the basis functions' derivatives, the
    rows of the exact solve's residual matrix. Returns ``(*interior sites, ...)``."""
    st = model.stencil
    shape = f.shape
    nsite = math.prod(shape)
    where = gather_cells(torch.arange(nsite).reshape(*shape, 1), st, f.boundary).reshape(-1, st.size)
    k = where.shape[1]
    rest = d.shape[len(shape) + 1 :]
    dd = d.reshape(-1, k, math.prod(rest))
    sites = torch.zeros(nsite, dd.shape[-1], dtype=d.dtype)
    for a in range(k):
        sites.index_add_(0, where[:, a], dd[:, a])
    sites = (math.prod(model.spacing) * sites).reshape(*shape, *rest)
    return sites[interior_slices(shape, st, f.boundary)]
