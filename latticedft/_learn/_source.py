"""Training data read a slab of time slices at a time: fields in memory, lazy DataArrays, field files.

A :class:`FieldSource` is one training field: its lattice (dims, spacing, boundary, components, shape) known
up front, its values read on demand for a range of time slices. In-memory DataArrays are converted once
(a view of their values, as before); lazy ones (opened from files without loading, or dask-backed) and
paths of field files are read slab by slab, so a training set larger than memory can be learned from.

:func:`pieces` cuts the sources into :class:`Piece` s of at most a given number of sites; a piece owns the
DEL equations (sites) and the cells anchored on its core time slices and is read with the stencil's overlap
(``width`` slices before and after), so that pieces together give every equation and every cell of the
data exactly once.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import xarray as xr

from .._errors import InputError
from .._lattice import BoundaryKinds, LatticeField, as_lattice_field, interior_slices
from .._layout import COMPONENT_DIM, check_coordinate, is_lazy, lattice_dims
from .._stencil import Stencil

__all__ = ["FieldSource", "Piece", "as_sources", "check_alike", "pieces", "is_lazy"]

Reader = Callable[[int, int], torch.Tensor]


@dataclass(frozen=True)
class FieldSource:
    """One training field, or a window of its time slices.

    ``lattice`` describes the field (its ``values`` are the whole field when it is in memory, else its first
    slices only); ``reader`` (lazy fields) reads the values of time slices ``[a, b)`` of the whole field;
    ``start`` and ``nt`` select the window ``[start, start + nt)`` of it that this source stands for.
    ``home`` is the rank that reads every piece of it under a process group (``None``: its chunks are dealt
    out to the processes in turn, see :func:`latticedft._learn._stream.TrainingData.my_chunks`).
    """

    lattice: LatticeField
    nt: int
    label: str
    reader: Reader | None = None
    start: int = 0
    home: int | None = None

    @property
    def lazy(self) -> bool:
        return self.reader is not None

    @property
    def shape(self) -> tuple[int, ...]:
        """Lattice shape: time slices, then the spatial sites."""
        return (self.nt, *self.lattice.shape[1:])

    def values(self, a: int, b: int) -> torch.Tensor:
        """Values ``(b - a, *spatial, m)`` of time slices ``[a, b)`` of this source."""
        a, b = self.start + a, self.start + b
        if self.reader is None:
            return self.lattice.values[a:b]
        return self.reader(a, b)

    def slab(self, a: int, b: int) -> LatticeField:
        """Time slices ``[a, b)`` as a lattice field of their own (time is an open axis)."""
        return replace(self.lattice, values=self.values(a, b))

    def load(self) -> LatticeField:
        """The whole source in memory."""
        if self.reader is None and self.start == 0 and self.nt == self.lattice.shape[0]:
            return self.lattice
        return self.slab(0, self.nt)

    def window(self, a: int, b: int) -> FieldSource:
        """Time slices ``[a, b)`` of this source, as a source."""
        return replace(self, start=self.start + a, nt=b - a)

    def n_sites(self, stencil: Stencil) -> int:
        """Sites carrying a DEL equation."""
        inner = interior_slices(self.shape, stencil, self.lattice.boundary)
        return int(np.prod([len(range(*s.indices(n))) for s, n in zip(inner, self.shape)]))


def _open(path: Path) -> xr.Dataset:
    if not path.exists():
        raise InputError(f"{path}: file not found; expected a netCDF field file")
    if path.is_dir():
        raise InputError(f"{path}: is a folder; expected a netCDF field file")
    try:
        return xr.open_dataset(path, engine="netcdf4", decode_times=False, decode_timedelta=False)
    except Exception as exc:  # the library raises OSError, ValueError, ... for bad files
        raise InputError(f"{path}: not a readable netCDF file ({type(exc).__name__})") from None


def _variable(ds: xr.Dataset, path: Path) -> str:
    """The field of a field file: the variable ``psi``, or the file's only data variable."""
    names = [str(v) for v in ds.data_vars]
    if "psi" in names:
        return "psi"
    if len(names) == 1:
        return names[0]
    raise InputError(f"{path}: no variable 'psi' and not exactly one data variable; variables present: {names!r}")


def _checked_slab(v: Any, dims: tuple[Any, ...], a: int, label: str) -> torch.Tensor:
    """Values of time slices ``a, a + 1, ...`` as float64 ``(slices, *spatial, m)``, refusing NaN and inf."""
    v = np.asarray(v, dtype=np.float64)
    bad = ~np.isfinite(v)
    if bad.any():
        first = list(np.unravel_index(int(np.argmax(bad.reshape(-1))), bad.shape))
        first[0] += a
        where = ", ".join(f"{d}={int(i)}" for d, i in zip(dims, first))
        raise InputError(
            f"{label}: field holds {int(bad.sum())} NaN/inf value(s) in time slices {a}..{a + v.shape[0] - 1}, "
            f"first at ({where}); expected finite values"
        )
    if dims[-1] != COMPONENT_DIM:
        v = v[..., None]
    return torch.from_numpy(np.ascontiguousarray(v))


def _array_reader(da: xr.DataArray, tdim: str, label: str) -> Reader:
    """Slabs of a lazy DataArray the caller holds (its file stays open through the caller's object)."""
    return lambda a, b: _checked_slab(da.isel({tdim: slice(a, b)}).values, da.dims, a, label)


def _file_reader(path: Path, name: str, tdim: str, label: str) -> Reader:
    """Slabs of a field file, opened for each read and closed again: nothing is held between reads, so a
    training set of many files costs no memory per file beyond its description."""

    def read(a: int, b: int) -> torch.Tensor:
        with _open(path) as ds:
            da = ds[name]
            return _checked_slab(da.isel({tdim: slice(a, b)}).values, da.dims, a, label)

    return read


#: One lattice description shared by the lazy sources that have the same one (many files of one shape).
_Key = tuple[Any, ...]


def _lazy_source(
    da: xr.DataArray, label: str, boundary: BoundaryKinds | None, reader: Reader, shared: dict[_Key, LatticeField]
) -> FieldSource:
    """A source that reads slab by slab: its lattice checked on the coordinates and the first slices, and
    kept without values (``shared`` holds one description per distinct lattice)."""
    dims = lattice_dims(da)
    if not dims:
        raise InputError(f"{label}: field has no lattice dims; expected e.g. psi(t), psi(t, x)")
    tdim = dims[0]
    nt = int(da.sizes[tdim])
    head = as_lattice_field(da.isel({tdim: slice(0, min(nt, 3))}).load(), source=label, boundary=boundary)
    check_coordinate(da, tdim, label)  # the whole time axis; the head checked the spatial ones
    key = (head.values.shape[1:], head.spacing, head.boundary, head.dims, head.components, head.name)
    if key not in shared:
        shared[key] = replace(head, values=head.values[:0].clone(), coords={}, coord_attrs={}, attrs={})
    return FieldSource(shared[key], nt, label, reader=reader)


def as_sources(data: Any, boundary: BoundaryKinds | None) -> list[FieldSource]:
    """One field or a list of fields (DataArrays, lazy or not, lattice fields, or paths of field files), as
    sources of one lattice spacing and component layout."""
    items = list(data) if isinstance(data, (list, tuple)) else [data]
    if not items:
        raise InputError("data: no training fields given")
    out = []
    shared: dict[_Key, LatticeField] = {}
    for i, d in enumerate(items):
        label = "data" if len(items) == 1 else f"data[{i}]"
        if isinstance(d, (str, os.PathLike)):
            path = Path(d)
            with _open(path) as ds:
                name = _variable(ds, path)
                tdim = str(ds[name].dims[0]) if ds[name].dims else ""
                out.append(
                    _lazy_source(ds[name], str(path), boundary, _file_reader(path, name, tdim, str(path)), shared)
                )
            continue
        if isinstance(d, xr.DataArray) and "source_file" in d.attrs:
            label = str(d.attrs["source_file"])
        if isinstance(d, xr.DataArray) and is_lazy(d):
            tdim = str(d.dims[0]) if d.dims else ""
            out.append(_lazy_source(d, label, boundary, _array_reader(d, tdim, label), shared))
        else:
            f = as_lattice_field(d, source=None if len(items) == 1 and label == "data" else label, boundary=boundary)
            out.append(FieldSource(f, f.shape[0], label))
    check_alike([s.lattice for s in out])
    return out


def check_alike(fields: list[LatticeField]) -> None:
    """Refuse fields that differ in lattice dims, components or spacing from the first."""
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


@dataclass(frozen=True)
class Piece:
    """Time slices ``[t0, t1)`` of source ``source``: the sites and the cells anchored there are its own."""

    source: int
    t0: int
    t1: int

    def read(self, sources: list[FieldSource], stencil: Stencil) -> tuple[LatticeField, int]:
        """(the slab of values the piece needs, the number of its leading cell slices that are not its own).

        The slab adds the stencil's time width ``w`` of slices on either side (within the field). Its interior
        sites are then exactly the piece's own; its cells start ``skip`` slices before the piece's first.
        """
        src = sources[self.source]
        w = int(stencil.width[0])
        a, b = max(0, self.t0 - w), min(src.nt, self.t1 + w)
        return src.slab(a, b), self.t0 - a


def pieces(sources: list[FieldSource], stencil: Stencil, budget: int) -> list[list[Piece]]:
    """The sources cut into pieces of about ``budget`` lattice sites (``budget <= 0``: whole fields), packed in
    order into chunks of at most ``budget`` sites (a field larger than it is cut along time); a chunk holds
    sources of one ``home`` only."""
    chunks: list[list[Piece]] = []
    current: list[Piece] = []
    size = 0
    w = int(stencil.width[0])
    for i, src in enumerate(sources):
        per_slice = int(np.prod(src.shape[1:], dtype=np.int64)) if len(src.shape) > 1 else 1
        whole = budget <= 0 or src.nt * per_slice <= budget
        step = src.nt if whole else max(1, budget // per_slice - 2 * w)
        for t0 in range(0, src.nt, step):
            t1 = min(src.nt, t0 + step)
            n = (min(src.nt, t1 + w) - max(0, t0 - w)) * per_slice
            if current and (budget > 0 and size + n > budget or sources[current[-1].source].home != src.home):
                chunks.append(current)
                current, size = [], 0
            current.append(Piece(i, t0, t1))
            size += n
    if current:
        chunks.append(current)
    return chunks
