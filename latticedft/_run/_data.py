"""A case's fields read and checked: :func:`check_case` (nothing is written).

Bad input raises :class:`latticedft.InputError` or :class:`latticedft.ConfigError` naming the key or file at
fault, before anything is written.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import netCDF4
import xarray as xr

from .._boundary import missing_edges
from .._case import Case, ServeTask, load_invariant
from .._errors import ConfigError, InputError, LatticeDFTError
from .._lattice import as_lattice_field
from .._layout import component_labels, field_spacing, is_lazy, lattice_dims
from .._models import SparseLagrangian
from .._procenv import env_rank, env_world
from ..io.fields import read_field
from ._charges import check_charges

__all__ = ["CaseData", "TaskData", "as_case_error", "check_case"]


@dataclass
class TaskData:
    """What one serving task needs: the initial field, its reference and baseline."""

    task: ServeTask
    init: xr.DataArray
    reference: xr.DataArray | None
    baseline: xr.DataArray | None
    slices: int
    invariant: Callable[[xr.DataArray], Any] | None = None


@dataclass
class CaseData:
    """Every field a case reads, validated."""

    train: list[xr.DataArray]
    tasks: list[TaskData]
    dims: tuple[str, ...]
    spacing: tuple[float, ...]
    components: tuple[str, ...] | None

    def summary_lines(self, case: Case) -> list[str]:
        lines = [
            f"case {case.name}: lattice dims {self.dims}, spacing "
            f"{tuple(float(f'{h:.6g}') for h in self.spacing)}"
            + (f", components {list(self.components)}" if self.components else "")
        ]
        opts = ", ".join(f"{k}={v!r}" for k, v in case.model.options.items())
        lines.append(
            f"model: {case.model.kind}({opts})" + (f", stencil {case.model.stencil}" if case.model.stencil else "")
        )
        for path, da in zip(case.train.data, self.train):
            lines.append(f"train: {_rel(path, case.root)} {dict(da.sizes)}")
        for td in self.tasks:
            t = td.task
            lines.append(
                f"serve {t.name}: from {_rel(t.source, case.root)} {dict(td.init.sizes)}, "
                f"{td.slices} slices, boundary {t.boundary or 'from file/dirichlet'}, mode {t.options.mode}"
                + (", reference" if td.reference is not None else ", no reference")
                + (", baseline" if td.baseline is not None else "")
                + (f", charges {list(t.charges)}" if t.charges else "")
                + t.cadence.describe()
                + (f" (warning: {t.label}.steps is deprecated: write {t.label}.slices)" if t.deprecated_steps else "")
            )
        return lines


def _rel(path: Path, root: Path) -> str:
    try:
        return str(path.relative_to(root))
    except ValueError:
        return str(path)


def _same_spacing(a: tuple[float, ...], b: tuple[float, ...]) -> bool:
    return len(a) == len(b) and all(math.isclose(x, y, rel_tol=1e-6) for x, y in zip(a, b))


def _read(path: Path, case: Case, components: tuple[str, ...] | None, lazy: bool = False) -> xr.DataArray:
    """A field of the case, validated; ``lazy``: its values left in the file (a task with ``every > 1``)."""
    return read_field(path, case.field.variable, components=list(components) if components else None, lazy=lazy)


def as_case_error(exc: LatticeDFTError, key: str) -> ConfigError:
    """An error about a keyword argument (``exc.key``) as an error about the case key ``key`` that set it."""
    return ConfigError(f"case.toml: {key}: {exc.problem}", key=key, problem=exc.problem)


def _check_library(case: Case, n: int, m: int) -> None:
    """A sparse model's library expanded on the data's lattice (``n`` axes, ``m`` components), before any
    training: a term that does not fit it is one line naming ``model.library``."""
    if case.model.kind != SparseLagrangian.kind:
        return
    model = case.model.build(n)
    if isinstance(model, SparseLagrangian) and model.library is not None:
        try:
            model.library.expand(n, m)
        except InputError as exc:
            raise as_case_error(exc, "model.library") from None


def check_case(case: Case) -> CaseData:
    """Read and validate every field of the case (nothing is written)."""
    comps = case.field.components
    train: list[xr.DataArray] = []
    dims: tuple[str, ...] = ()
    spacing: tuple[float, ...] = ()
    rank, size = _process()
    for i, path in enumerate(case.train.data):
        da = _read(path, case, comps) if i % size == rank else _read_other(path, case, comps)
        if comps is None:
            comps = component_labels(da)
            if comps is None and train:
                pass
        if not train:
            dims, spacing = lattice_dims(da), field_spacing(da, str(path))
            first = path
        else:
            if lattice_dims(da) != dims:
                raise InputError(f"{path}: lattice dims {lattice_dims(da)} differ from {dims} of {first}")
            if not _same_spacing(field_spacing(da, str(path)), spacing):
                raise InputError(f"{path}: spacing {field_spacing(da, str(path))} differs from {spacing} of {first}")
        try:  # a field left in its file: its values were checked in blocks, its lattice on the first slices
            as_lattice_field(_head(da) if is_lazy(da) else da, source=str(path), boundary=case.train.boundary)
        except InputError as exc:
            if exc.key == "boundary":
                raise as_case_error(exc, "train.boundary") from None
            raise
        train.append(da)
    if comps is None and any(component_labels(d) is not None for d in train):  # pragma: no cover - caught above
        raise InputError("train.data: some files have components and some do not")
    _check_library(case, len(dims), len(comps) if comps else 1)
    tasks = [_check_task(case, t, dims, spacing, comps) for t in case.serve]
    return CaseData(train=train, tasks=tasks, dims=dims, spacing=spacing, components=comps)


def _process() -> tuple[int, int]:
    """(rank, number of processes) of the command (``--workers`` or ``torchrun``): from the environment, as
    the case is read before the processes join their group."""
    return env_rank(), env_world()


def _read_other(path: Path, case: Case, components: tuple[str, ...] | None) -> xr.DataArray:
    """A training file that another process holds (several processes: each holds its share): opened lazily,
    its values checked in blocks of slices, with no chunk cache, so that none of its values stays in this
    process (a file written by :func:`latticedft.io.write_field` is one compressed chunk: a cache would keep
    it whole, decompressed, while the file is open)."""
    size, nelems, preemption = netCDF4.get_chunk_cache()
    netCDF4.set_chunk_cache(0, nelems, preemption)  # for the files opened now
    try:
        return _read(path, case, components, lazy=True)
    finally:
        netCDF4.set_chunk_cache(size, nelems, preemption)


def _head(da: xr.DataArray) -> xr.DataArray:
    """The first three time slices of a lazily read field, in memory (what :func:`as_lattice_field` checks
    beyond the coordinates and values, which :func:`read_field` checked)."""
    return da.isel({da.dims[0]: slice(0, 3)}).compute()


def _check_task(
    case: Case, t: ServeTask, dims: tuple[str, ...], spacing: tuple[float, ...], comps: tuple[str, ...] | None
) -> TaskData:
    # served slice by slice, or split over processes (each reads its slab): the files are read where needed
    lazy = (t.cadence.thins or _process()[1] > 1) and len(dims) > 1
    init = _read(t.source, case, comps, lazy)
    if lattice_dims(init) != dims:
        raise InputError(
            f"{t.source}: lattice dims {lattice_dims(init)} differ from the training data's {dims} ({t.label}.from)"
        )
    if not _same_spacing(field_spacing(init, str(t.source)), spacing):
        raise InputError(
            f"{t.source}: spacing {field_spacing(init, str(t.source))} differs from the training "
            f"data's {spacing}; a learned L_d serves on the lattice it was learned on"
        )
    nt = init.sizes[dims[0]]
    if nt < 2:
        raise InputError(f"{t.source}: holds {nt} time slice(s); expected at least the first two")
    slices = t.slices if t.slices is not None else nt
    key = f"{t.label}.{'steps' if t.deprecated_steps else 'slices'}"
    try:
        head = init.isel({dims[0]: slice(0, 2)}).compute() if lazy else init  # the boundary needs no values
        f = as_lattice_field(head, source=str(t.source), boundary=t.boundary, min_slices=2)
    except InputError as exc:
        if exc.key == "boundary":
            raise as_case_error(exc, f"{t.label}.boundary") from None
        raise
    check_charges(t.charges, f, f"{t.label}.charges")
    if t.cadence.thins and t.charges:
        raise ConfigError(
            f"case.toml: {t.label}.every: the Noether charges ({t.label}.charges) are measured on the whole "
            "served field; give every = 1 or no charges",
            key=f"{t.label}.every",
        )
    if t.cadence.thins and case.train.learn.get("ensemble"):
        raise ConfigError(
            f"case.toml: {t.label}.every: an ensemble (train.ensemble) is served whole, every member on every "
            "slice; give every = 1 or no ensemble",
            key=f"{t.label}.every",
        )
    missing = missing_edges(f.boundary, f.dims, nt, slices)
    if missing and t.options.boundary_value is None:
        axis, kind = missing
        raise ConfigError(
            f"case.toml: {key}: {slices} slices need the {kind.title} strips along "
            f"{axis!r} on every slice, but {t.source.name} holds {nt}; give the whole field, "
            f"fewer slices or {t.label}.boundary_value",
            key=key,
        )
    if t.options.box is not None and len(dims) != 1:
        raise ConfigError(f"case.toml: {t.label}.box: stopping at a box is for 1D trajectories only")
    ref: xr.DataArray | None
    if t.reference is not None:
        ref = _read(t.reference, case, comps, lazy)
        if ref.shape[1:] != init.shape[1:] or lattice_dims(ref) != dims:
            raise InputError(
                f"{t.reference}: shape {dict(ref.sizes)} does not match {t.source.name} "
                f"{dict(init.sizes)} beyond time ({t.label}.reference)"
            )
    else:
        ref = init if nt > 2 else None
    base = None
    if t.baseline is not None:
        base = _read(t.baseline, case, comps, lazy)
        if base.shape[1:] != init.shape[1:] or lattice_dims(base) != dims:
            raise InputError(
                f"{t.baseline}: shape {dict(base.sizes)} does not match {t.source.name} "
                f"{dict(init.sizes)} beyond time ({t.label}.baseline)"
            )
        if ref is None:
            raise ConfigError(f"case.toml: {t.label}.baseline: a baseline needs a reference to be scored against")
    inv = None
    if t.invariant is not None:
        try:
            inv = load_invariant(t.invariant, case.root)
        except ConfigError as exc:
            raise ConfigError(f"case.toml: {t.label}.{exc}") from None
    return TaskData(task=_edges_loaded(case, t), init=init, reference=ref, baseline=base, slices=slices, invariant=inv)


def _edges_loaded(case: Case, t: ServeTask) -> ServeTask:
    """``t`` with its ``boundary_value = "module:function"`` imported (modules in the case folder are found)."""
    spec = t.options.boundary_value
    if not isinstance(spec, str):
        return t
    try:
        fn = load_invariant(spec, case.root, what="boundary_value")
    except ConfigError as exc:
        raise ConfigError(f"case.toml: {t.label}.{exc}", key=f"{t.label}.boundary_value") from None
    return dataclasses.replace(t, options=t.options.replace(boundary_value=fn))
