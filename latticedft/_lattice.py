"""Fields on a lattice: conversion from and to xarray, cells, interior sites.

The field layout (dims, spacing, the ``periodic`` attribute, components) is
:mod:`latticedft._layout`'s; the boundary kinds and their index rules are
:mod:`latticedft._boundary`'s. This module applies them to tensors.
"""

from __future__ import annotations

import copy
from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
import xarray as xr
from xarray.indexes import PandasIndex

from ._boundary import BoundaryKind, BoundaryKinds, axis_kinds, lattice_boundary
from ._errors import InputError
from ._layout import (
    COMPONENT_DIM,
    PERIODIC_ATTR,
    component_labels,
    coordinate_spacing,
    field_periodic,
    is_lazy,
    validate_field,
)
from ._stencil import Stencil

__all__ = [
    "LatticeField",
    "as_lattice_field",
    "as_lattice_fields",
    "to_dataarrays",
    "like_dataarray",
    "dataarray_parts",
    "gather_cells",
    "interior_slices",
    "BoundaryKinds",
]

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


def _coordinate_bytes(v: xr.Variable) -> bytes:
    """The values of a coordinate variable as bytes (an index coordinate's read from its pandas index)."""
    values = getattr(getattr(getattr(v, "_data", None), "array", None), "values", None)  # without a copy
    if not isinstance(values, np.ndarray) or values.dtype != v.dtype or values.shape != v.shape:
        values = np.asarray(v.values)
    return values.tobytes()


def _layout_key(data: xr.DataArray) -> tuple[Any, ...] | None:
    """What :func:`as_lattice_field`'s checks read of ``data`` apart from its values (dims, shape, dtype,
    name, every coordinate's values and ``periodic`` attribute), or None when it cannot be keyed."""
    try:
        coords = tuple(
            (str(n), v.dims, v.dtype.str, v.shape, _coordinate_bytes(v), repr(v.attrs.get(PERIODIC_ATTR, None)))
            for n, v in data.coords.variables.items()
        )
        key = (data.dims, data.shape, data.dtype.str, data.name, coords)
        hash(key)
    except (TypeError, ValueError):
        return None
    return key


def _like_checked(data: xr.DataArray, f0: LatticeField) -> LatticeField | None:
    """``as_lattice_field(data)`` for ``data`` laid out as the field ``f0`` came from: ``f0`` around ``data``'s
    values and attributes; None when a value is not finite (the full check then names it)."""
    values = np.asarray(data.values, dtype=np.float64)
    if not np.isfinite(values).all():
        return None
    if f0.components is None:
        values = values[..., None]
    variables = data.coords.variables
    return replace(
        f0,
        values=torch.from_numpy(np.ascontiguousarray(values)),
        coords=dict(f0.coords),
        coord_attrs={d: dict(variables[d].attrs) for d in f0.dims},
        attrs=dict(data.attrs),
    )


def as_lattice_fields(
    items: Sequence[xr.DataArray | LatticeField],
    sources: Sequence[str],
    *,
    boundary: BoundaryKinds | None = None,
    min_slices: int = 3,
) -> list[LatticeField]:
    """:func:`as_lattice_field` of every item (``sources[k]`` names item ``k`` in errors), in one pass: an
    item laid out as one already checked (the same dims, shape, dtype, name, coordinates and their
    ``periodic`` attributes) is not checked again, only its values; it gets that one's lattice description
    around its own values and attributes. The same fields, and the same first error, as one by one."""
    seen: dict[tuple[Any, ...], LatticeField] = {}
    out = []
    for data, src in zip(items, sources, strict=True):
        key = _layout_key(data) if type(data) is xr.DataArray else None
        f0 = seen.get(key) if key is not None else None
        f = _like_checked(data, f0) if f0 is not None and isinstance(data, xr.DataArray) else None
        full = _checked_key(data, key, boundary, min_slices) if f is None else None
        if full is not None:
            f = _checked_before(data, full)
        if f is None:
            f = as_lattice_field(data, source=src, boundary=boundary, min_slices=min_slices)
            if key is not None:
                seen[key] = f
            if full is not None:
                _remember(full, f)
        out.append(f)
    return out


#: The lattice descriptions (values left out) of the last layouts :func:`as_lattice_fields` checked, by
#: :func:`_checked_key`: a field laid out alike in a later call has only its values checked (serving the
#: same lattice again and again checks its coordinates once). At most :data:`CHECKED_KEPT` layouts.
_CHECKED: dict[tuple[Any, ...], LatticeField] = {}
CHECKED_KEPT = 4

#: The most bytes of coordinates a kept layout or DataArray template holds (a lattice with more builds its
#: own each time): 4 MiB, half a million sites along the axes.
KEPT_COORD_BYTES = 4 << 20


def _checked_key(
    data: Any, key: tuple[Any, ...] | None, boundary: BoundaryKinds | None, min_slices: int
) -> tuple[Any, ...] | None:
    """What :func:`as_lattice_field` reads of ``data`` and its arguments apart from the values: the layout
    (:func:`_layout_key`), every coordinate attribute the checks read, ``boundary`` (by its ``repr``) and
    ``min_slices``; None for a field not held in memory or not keyed."""
    if key is None or type(data) is not xr.DataArray or is_lazy(data):
        return None
    read = ("periodic", "axis", "standard_name")
    attrs = tuple((str(n), *(repr(v.attrs.get(a)) for a in read)) for n, v in data.coords.variables.items())
    return key, attrs, repr(boundary), min_slices


def _checked_before(data: Any, full: tuple[Any, ...]) -> LatticeField | None:
    """``as_lattice_field(data, ...)`` where a field of the same :func:`_checked_key` ``full`` was checked by
    an earlier call (its coordinates copied), else None."""
    f0 = _CHECKED.get(full)
    f = _like_checked(data, f0) if f0 is not None else None
    if f is not None:
        f.coords = {d: c.copy() for d, c in f.coords.items()}
    return f


def _remember(full: tuple[Any, ...], f: LatticeField) -> None:
    """Keep ``f``'s lattice description (without its values) under its :func:`_checked_key` ``full`` for
    :func:`_checked_before`."""
    if sum(c.nbytes for c in f.coords.values()) > KEPT_COORD_BYTES:
        return
    coords = {d: c.copy() for d, c in f.coords.items()}
    keep_last(_CHECKED, full, replace(f, values=torch.empty(0), coords=coords, coord_attrs={}, attrs={}), CHECKED_KEPT)


def keep_last(cache: dict[Any, Any], key: Any, value: Any, most: int) -> None:
    """Put ``key: value`` into ``cache``, a dict of at most ``most`` entries kept in insertion order: the
    oldest ones are dropped first."""
    while len(cache) >= most:
        del cache[next(iter(cache))]
    cache[key] = value


#: A DataArray's dims, name, coordinate variables and indexes (:func:`dataarray_parts`).
DataArrayParts = tuple[tuple[Hashable, ...], Hashable, dict[Hashable, xr.Variable], dict[Hashable, xr.Index]]


def dataarray_parts(template: xr.DataArray) -> DataArrayParts:
    """What :func:`like_dataarray` builds other DataArrays around: ``template``'s dims, name, coordinates and
    indexes (read once)."""
    return template.dims, template.name, dict(template.coords.variables), dict(template.xindexes)


def like_dataarray(
    parts: DataArrayParts,
    values: np.ndarray,
    attrs: dict[str, Any],
    coord_attrs: dict[str, dict[str, Any]] | None = None,
) -> xr.DataArray:
    """A DataArray with the dims, name, coordinates and indexes of a template (:func:`dataarray_parts`)
    around ``values`` (of its shape) and ``attrs``, built without xarray's checks (the template passed them):
    each coordinate a shallow copy with its own attributes (deep copies of ``coord_attrs[name]`` where given),
    the immutable index objects shared."""
    dims, name, variables, indexes = parts
    coords = {}
    for n, v in variables.items():
        c = v.copy(deep=False)
        if coord_attrs is not None and n in coord_attrs:
            c.attrs = copy.deepcopy(coord_attrs[n])
        coords[n] = c
    variable = xr.Variable(dims, values, attrs, fastpath=True)
    return xr.DataArray(variable, coords=coords, name=name, indexes=dict(indexes), fastpath=True)


def to_dataarrays(fields: Sequence[LatticeField]) -> list[xr.DataArray]:
    """:meth:`LatticeField.to_dataarray` of every field, built around the spatial coordinates of a template
    of its lattice (dims, spatial coordinates, components, name: :func:`like_dataarray`) and its own time
    coordinate: the template built once by :meth:`LatticeField.to_dataarray` and kept for later calls (at
    most :data:`TEMPLATES_KEPT` lattices; serving one lattice again builds its spatial coordinates and their
    indexes once). The same DataArrays, identical."""
    out = []
    timed: dict[tuple[Any, ...], DataArrayParts] = {}  # per lattice and time coordinate, in this call
    for f in fields:
        spatial = tuple(np.asarray(f.coords[d], dtype=np.float64).tobytes() for d in f.dims[1:])
        key: tuple[Any, ...] = (f.dims, f.components, f.name, tuple(f.values.shape[1:]), spatial)
        parts = _TEMPLATES.get(key)
        if parts is None:
            parts = dataarray_parts(f.to_dataarray())  # kept apart: no caller holds its variables
            if sum(len(c) for c in spatial) <= KEPT_COORD_BYTES:
                keep_last(_TEMPLATES, key, parts, TEMPLATES_KEPT)
        v = f.values.detach().cpu().numpy()
        v = np.ascontiguousarray(v[..., 0] if f.components is None else v)
        time = _time_values(f, int(v.shape[0]))
        both = (key, time.tobytes())
        if both not in timed:
            timed[both] = with_time(parts, f.dims[0], time)
        parts = timed[both]
        out.append(like_dataarray(parts, v, dict(f.attrs), {d: f.coord_attrs.get(d, {}) for d in f.dims}))
    return out


def _time_values(f: LatticeField, nt: int) -> np.ndarray:
    """The time coordinate of ``f``'s first ``nt`` slices, as :meth:`LatticeField.to_dataarray` makes it."""
    c = np.asarray(f.coords[f.dims[0]], dtype=np.float64)
    return c if len(c) == nt else c[0] + f.spacing[0] * np.arange(nt, dtype=np.float64)


def with_time(parts: DataArrayParts, tdim: str, values: np.ndarray) -> DataArrayParts:
    """``parts`` with the time coordinate ``values`` along ``tdim`` and its index, as xarray's constructor
    makes them (its attributes are set by :func:`like_dataarray`)."""
    dims, name, variables, indexes = parts
    var = xr.Variable((tdim,), values)
    index = PandasIndex.from_variables({tdim: var}, options={})
    time = index.create_variables({tdim: var})[tdim]
    variables = {n: time if n == tdim else v for n, v in variables.items()}
    return dims, name, variables, {n: index if n == tdim else i for n, i in indexes.items()}


#: The parts (:func:`dataarray_parts`) of the DataArrays :func:`to_dataarrays` built last, by lattice.
_TEMPLATES: dict[tuple[Any, ...], DataArrayParts] = {}
TEMPLATES_KEPT = 4


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
