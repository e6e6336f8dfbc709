"""Fields on a lattice: conversion from and to xarray, cells, interior sites."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
import xarray as xr

from ._errors import InputError
from ._stencil import Stencil

__all__ = ["LatticeField", "as_lattice_field", "gather_cells", "interior_slices", "BoundaryKinds"]

COMPONENT = "component"
BoundaryKinds = str | dict[str, str]
_TRUE = {"true", "1", "yes", "periodic"}


@dataclass
class LatticeField:
    """A field on a lattice as the engine sees it.

    ``values`` has shape ``(N_0, ..., N_{n-1}, m)`` (float64, time first, the
    component axis last even for scalars); ``spacing`` and ``periodic`` have one
    entry per lattice axis. ``template`` keeps the original DataArray's names,
    coordinates and attributes for the way back.
    """

    values: torch.Tensor
    spacing: tuple[float, ...]
    periodic: tuple[bool, ...]
    dims: tuple[str, ...]
    components: tuple[str, ...] | None
    name: str = "psi"
    coords: dict[str, np.ndarray] = field(default_factory=dict)
    attrs: dict[str, Any] = field(default_factory=dict)

    @property
    def ndim(self) -> int:
        return len(self.dims)

    @property
    def ncomp(self) -> int:
        return int(self.values.shape[-1])

    @property
    def shape(self) -> tuple[int, ...]:
        """Lattice shape (without leading batch dims and the component axis)."""
        return tuple(self.values.shape[self.batch:-1])

    def with_values(self, values: torch.Tensor, t0: float | None = None) -> LatticeField:
        """The same lattice description around new values (time length may differ)."""
        coords = dict(self.coords)
        nt = values.shape[0]
        tdim = self.dims[0]
        start = coords[tdim][0] if t0 is None else t0
        coords[tdim] = start + self.spacing[0] * np.arange(nt, dtype=np.float64)
        return replace(self, values=values, coords=coords)

    def to_dataarray(self, values: torch.Tensor | np.ndarray | None = None, name: str | None = None) -> xr.DataArray:
        """Back to the field-file layout of docs/design.md (``psi(t, ..., x[, component])``)."""
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
            dims.append(COMPONENT)
            coords[COMPONENT] = list(self.components)
        return xr.DataArray(np.ascontiguousarray(v), dims=dims, coords=coords, name=name or self.name,
                            attrs=dict(self.attrs))

    coord_attrs: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: Leading batch dims of ``values``: fields of one shape stacked for training (never coupled).
    batch: int = 0


def _periodic_flags(da: xr.DataArray, dims: tuple[str, ...], boundary: BoundaryKinds | None,
                    source: str) -> tuple[bool, ...]:
    flags = []
    for i, d in enumerate(dims):
        attr = str(da[d].attrs.get("periodic", "false")).strip().lower() in _TRUE if d in da.coords else False
        flags.append(attr)
    if boundary is not None:
        kinds = _boundary_dict(boundary, dims, source)
        flags = [False] + [kinds[d] == "periodic" for d in dims[1:]]
    if flags and flags[0]:
        raise InputError(f"{source}: the time axis {dims[0]!r} cannot be periodic")
    return tuple(flags)


def _boundary_dict(boundary: BoundaryKinds, dims: tuple[str, ...], source: str) -> dict[str, str]:
    valid = ("dirichlet", "periodic")
    spatial = dims[1:]
    if isinstance(boundary, str):
        kinds = {d: boundary for d in spatial}
    elif isinstance(boundary, dict):
        unknown = [k for k in boundary if k not in spatial]
        if unknown:
            raise InputError(f"boundary: unknown axis {unknown[0]!r}; the spatial axes of {source} are {list(spatial)}")
        kinds = {d: boundary.get(d, "dirichlet") for d in spatial}
    else:
        raise InputError(f"boundary: expected 'dirichlet', 'periodic' or a table axis -> kind, got {boundary!r}")
    for d, k in kinds.items():
        if k not in valid:
            raise InputError(f"boundary: axis {d!r} has kind {k!r}; expected one of {list(valid)}")
    return kinds


def as_lattice_field(data: xr.DataArray | LatticeField, *, source: str | None = None,
                     boundary: BoundaryKinds | None = None, min_slices: int = 3) -> LatticeField:
    """Validate a DataArray in the field-file layout (docs/design.md) and convert it to a :class:`LatticeField`."""
    if isinstance(data, LatticeField):
        return data
    if not isinstance(data, xr.DataArray):
        raise InputError(f"{source or 'data'}: expected an xarray.DataArray, got {type(data).__name__}")
    from .io.fields import validate_field

    src = source or (data.name and f"field {data.name!r}") or "field"
    validate_field(data, source=src)
    has_comp = data.dims[-1] == COMPONENT
    dims = tuple(str(d) for d in (data.dims[:-1] if has_comp else data.dims))
    if len(dims) < 1:
        raise InputError(f"{src}: needs at least the time dimension")
    nt = data.sizes[dims[0]]
    if nt < min_slices:
        raise InputError(f"{src}: has {nt} time slices along {dims[0]!r}; at least {min_slices} are needed")
    spacing = tuple(float(data[d].values[1] - data[d].values[0]) for d in dims)
    components = tuple(str(c) for c in data[COMPONENT].values) if has_comp else None
    values = np.asarray(data.values, dtype=np.float64)
    if not has_comp:
        values = values[..., None]
    return LatticeField(
        values=torch.from_numpy(np.ascontiguousarray(values)),
        spacing=spacing,
        periodic=_periodic_flags(data, dims, boundary, src),
        dims=dims,
        components=components,
        name=str(data.name or "psi"),
        coords={d: np.asarray(data[d].values, dtype=np.float64) for d in dims},
        coord_attrs={d: dict(data[d].attrs) for d in dims},
        attrs=dict(data.attrs),
    )


def gather_cells(psi: torch.Tensor, stencil: Stencil, periodic: tuple[bool, ...], batch: int = 0) -> torch.Tensor:
    """Stack the stencil's sites of every cell: ``(*batch, *cells, K, ...)``.

    The lattice axes of ``psi`` follow ``batch`` leading batch axes; any axes
    after them (components, ...) are carried along. Non-periodic axis ``k``
    holds ``N_k - width_k`` cells; a periodic axis holds ``N_k`` cells and
    wraps. Differentiable in ``psi``.
    """
    n = stencil.ndim
    shape = psi.shape[batch:batch + n]
    lo, width = stencil.lo, stencil.width
    parts = []
    for off in stencil.offsets:
        v = psi
        index: list[slice] = [slice(None)] * batch
        for k in range(n):
            start = off[k] - lo[k]
            if periodic[k]:
                if start:
                    v = torch.roll(v, shifts=-int(start), dims=batch + k)
                index.append(slice(None))
            else:
                index.append(slice(int(start), int(start + shape[k] - width[k])))
        parts.append(v[tuple(index)])
    return torch.stack(parts, dim=batch + n)


def interior_slices(shape: tuple[int, ...], stencil: Stencil, periodic: tuple[bool, ...]) -> tuple[slice, ...]:
    """Sites ``y`` where every cell ``y - s_a`` exists (the sites that carry a DEL equation)."""
    out = []
    for k, nk in enumerate(shape):
        w = int(stencil.width[k])
        out.append(slice(None) if periodic[k] else slice(w, nk - w))
    return tuple(out)
