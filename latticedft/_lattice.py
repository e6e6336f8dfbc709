"""Fields on a lattice: conversion from and to xarray, cells, interior sites.

The field layout (dims, spacing, the ``periodic`` attribute, components) is
:mod:`latticedft._layout`'s; the boundary kinds and their index rules are
:mod:`latticedft._boundary`'s. This module applies them to tensors.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
import xarray as xr

from ._boundary import BoundaryKind, BoundaryKinds, axis_kinds, lattice_boundary
from ._errors import InputError
from ._layout import (
    COMPONENT_DIM,
    component_labels,
    coordinate_spacing,
    field_periodic,
    validate_field,
)
from ._stencil import Stencil

__all__ = ["LatticeField", "as_lattice_field", "gather_cells", "interior_slices", "BoundaryKinds"]

#: Per lattice axis: a boundary kind's name, a :class:`BoundaryKind`, or a periodic flag.
AxisBoundaries = Sequence[str | bool | BoundaryKind]


@dataclass
class LatticeField:
    """A field on a lattice as the engine sees it.

    ``values`` has shape ``(N_0, ..., N_{n-1}, m)`` (float64, time first, the
    component axis last even for scalars); ``spacing`` and ``boundary`` have
    one entry per lattice axis (``boundary`` the kind names of
    :mod:`latticedft._boundary`: ``"open"`` for time, then ``"dirichlet"`` or
    ``"periodic"``; ``periodic`` gives the flags). ``dims``, ``coords``,
    ``coord_attrs`` and ``attrs`` keep the original DataArray's names,
    coordinates and attributes for the way back.
    """

    values: torch.Tensor
    spacing: tuple[float, ...]
    boundary: tuple[str, ...]
    dims: tuple[str, ...]
    components: tuple[str, ...] | None
    name: str = "psi"
    coords: dict[str, np.ndarray] = field(default_factory=dict)
    attrs: dict[str, Any] = field(default_factory=dict)

    @property
    def periodic(self) -> tuple[bool, ...]:
        """Per lattice axis: does it wrap around."""
        return tuple(k.wraps for k in axis_kinds(self.boundary))

    @property
    def ndim(self) -> int:
        return len(self.dims)

    @property
    def ncomp(self) -> int:
        return int(self.values.shape[-1])

    @property
    def shape(self) -> tuple[int, ...]:
        """Lattice shape (without leading batch dims and the component axis)."""
        return tuple(self.values.shape[self.batch : -1])

    def with_values(self, values: torch.Tensor, t0: float | None = None) -> LatticeField:
        """The same lattice description around new values (time length may differ)."""
        coords = dict(self.coords)
        nt = values.shape[0]
        tdim = self.dims[0]
        start = coords[tdim][0] if t0 is None else t0
        coords[tdim] = start + self.spacing[0] * np.arange(nt, dtype=np.float64)
        return replace(self, values=values, coords=coords)

    def to_dataarray(self, values: torch.Tensor | np.ndarray | None = None, name: str | None = None) -> xr.DataArray:
        """Back to the field layout (``psi(t, ..., x[, component])``)."""
        v = self.values if values is None else values
        v = v.detach().cpu().numpy() if isinstance(v, torch.Tensor) else np.asarray(v)
        nt = v.shape[0]
        coords: dict[str, Any] = {}
        for d in self.dims:
            c = self.coords[d]
            if d == self.dims[0] and len(c) != nt:
                c = c[0] + self.spacing[0] * np.arange(nt, dtype=np.float64)
            coords[d] = (d, np.asarray(c, dtype=np.float64), self.coord_attrs.get(d, {}))
        dims = list(self.dims)
        if self.components is None:
            v = v[..., 0]
        else:
            dims.append(COMPONENT_DIM)
            coords[COMPONENT_DIM] = list(self.components)
        return xr.DataArray(
            np.ascontiguousarray(v), dims=dims, coords=coords, name=name or self.name, attrs=dict(self.attrs)
        )

    coord_attrs: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: Leading batch dims of ``values``: fields of one shape stacked for training (never coupled).
    batch: int = 0


def as_lattice_field(
    data: xr.DataArray | LatticeField,
    *,
    source: str | None = None,
    boundary: BoundaryKinds | None = None,
    min_slices: int = 3,
) -> LatticeField:
    """Validate a DataArray in the field layout and convert it to a :class:`LatticeField`.

    ``boundary`` (a kind for every spatial axis or a dict axis -> kind)
    overrides the coordinates' ``periodic`` attributes.
    """
    if isinstance(data, LatticeField):
        return data
    if not isinstance(data, xr.DataArray):
        raise InputError(f"{source or 'data'}: expected an xarray.DataArray, got {type(data).__name__}")
    src = source or (f"field {data.name!r}" if data.name else "field")
    validate_field(data, source=src)
    has_comp = data.dims[-1] == COMPONENT_DIM
    dims = tuple(str(d) for d in (data.dims[:-1] if has_comp else data.dims))
    if len(dims) < 1:
        raise InputError(f"{src}: needs at least the time dimension")
    nt = data.sizes[dims[0]]
    if nt < min_slices:
        raise InputError(f"{src}: has {nt} time slices along {dims[0]!r}; at least {min_slices} are needed")
    spacing = tuple(coordinate_spacing(data[d].values) for d in dims)
    components = component_labels(data) if has_comp else None
    values = np.asarray(data.values, dtype=np.float64)
    if not has_comp:
        values = values[..., None]
    return LatticeField(
        values=torch.from_numpy(np.ascontiguousarray(values)),
        spacing=spacing,
        boundary=lattice_boundary(field_periodic(data, src), boundary, dims, src),
        dims=dims,
        components=components,
        name=str(data.name or "psi"),
        coords={d: np.asarray(data[d].values, dtype=np.float64) for d in dims},
        coord_attrs={d: dict(data[d].attrs) for d in dims},
        attrs=dict(data.attrs),
    )


def gather_cells(psi: torch.Tensor, stencil: Stencil, boundary: AxisBoundaries, batch: int = 0) -> torch.Tensor:
    """Stack the stencil's sites of every cell: ``(*batch, *cells, K, ...)``.

    The lattice axes of ``psi`` follow ``batch`` leading batch axes; any axes
    after them (components, ...) are carried along. ``boundary`` gives each
    lattice axis's kind (names, kinds or periodic flags): an axis with edges
    holds ``N_k - width_k`` cells, a periodic axis ``N_k`` cells and wraps
    (:meth:`latticedft._boundary.BoundaryKind.take`). Differentiable in ``psi``.
    """
    n = stencil.ndim
    kinds = axis_kinds(boundary)
    shape = psi.shape[batch : batch + n]
    lo, width = stencil.lo, stencil.width
    parts = []
    for off in stencil.offsets:
        v = psi
        for k in range(n):
            v = kinds[k].take(v, batch + k, int(off[k] - lo[k]), int(shape[k]), int(width[k]))
        parts.append(v)
    return torch.stack(parts, dim=batch + n)


def interior_slices(shape: tuple[int, ...], stencil: Stencil, boundary: AxisBoundaries) -> tuple[slice, ...]:
    """Sites ``y`` where every cell ``y - s_a`` exists (the sites that carry a DEL equation)."""
    return tuple(
        k.interior(int(nk), int(stencil.width[i])) for i, (nk, k) in enumerate(zip(shape, axis_kinds(boundary)))
    )
