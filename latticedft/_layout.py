"""The field layout: how a lattice field is laid out as an :class:`xarray.DataArray`.

This module is the one owner of the layout; the engine (``_lattice``), the
field files (:mod:`latticedft.io.fields`) and the canonical systems use it.

A field is a DataArray (default name ``psi``) whose dims are the lattice dims
in CF order -- time first, then the spatial dims with x last: ``psi(t)``,
``psi(t, x)``, ``psi(t, y, x)`` -- plus an optional trailing dim
:data:`COMPONENT_DIM` (``"component"``) with string labels for vector fields
(Kepler: ``psi(t, component)``, ``component = ["x", "y"]``).

* Every lattice dim has a numeric, uniformly spaced, strictly increasing
  coordinate; the lattice spacing along it is :func:`coordinate_spacing`
  (the first step, ``c[1] - c[0]``), checked uniform by
  :func:`check_coordinate`.
* A lattice coordinate may carry the attribute :data:`PERIODIC_ATTR`
  (``periodic``), ``"true"`` or ``"false"``: read by :func:`parse_periodic`,
  written by :func:`periodic_attr`.

Every problem with user data raises :class:`latticedft._errors.InputError`
with a one-line message that names the ``source`` and what was expected.

>>> import numpy as np, xarray as xr
>>> da = xr.DataArray(np.zeros((3, 2)), dims=["t", "component"],
...                   coords={"t": [0.0, 0.5, 1.0], "component": ["x", "y"]})
>>> lattice_dims(da), field_spacing(da), component_labels(da)
(('t',), (0.5,), ('x', 'y'))
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import xarray as xr

from ._errors import InputError
from ._options import option

__all__ = [
    "COMPONENT_DIM",
    "is_lazy",
    "PERIODIC_ATTR",
    "lattice_dims",
    "component_labels",
    "coordinate_spacing",
    "field_spacing",
    "check_coordinate",
    "SLICE_COORD",
    "parse_periodic",
    "axis_periodic",
    "field_periodic",
    "periodic_attr",
    "validate_field",
]

#: Name of the optional trailing dim holding the components of a vector field.
COMPONENT_DIM = "component"
#: Name of the coordinate attribute that marks a periodic lattice axis.
PERIODIC_ATTR = "periodic"

# Relative tolerance on the deviation of a coordinate's steps from uniform.
_UNIFORM_RTOL = 1e-6
_PERIODIC_TEXT = {"true": True, "false": False}


# -- dims and components -------------------------------------------------------------------------------------
def lattice_dims(da: xr.DataArray) -> tuple[str, ...]:
    """The lattice dims of ``da`` (all dims except ``component``), time first.

    >>> lattice_dims(xr.DataArray(np.zeros((3, 2)), dims=["t", "component"]))
    ('t',)
    """
    return tuple(str(d) for d in da.dims if d != COMPONENT_DIM)


def component_labels(da: xr.DataArray) -> tuple[str, ...] | None:
    """The labels of the ``component`` dim (None for a scalar field)."""
    if COMPONENT_DIM not in da.dims:
        return None
    return tuple(str(c) for c in np.asarray(da.coords[COMPONENT_DIM].values).tolist())


# -- coordinates and spacing ---------------------------------------------------------------------------------
def _coord_values(da: xr.DataArray, dim: str, source: str) -> np.ndarray:
    if dim not in da.coords:
        raise InputError(
            f"{source}: lattice dim '{dim}' has no coordinate variable; "
            f"expected a numeric, uniformly spaced coordinate '{dim}'"
        )
    values = np.asarray(da.coords[dim].values)
    if values.dtype == bool or not (
        np.issubdtype(values.dtype, np.integer) or np.issubdtype(values.dtype, np.floating)
    ):
        raise InputError(
            f"{source}: coordinate '{dim}' has dtype {values.dtype}; expected numeric "
            f"values (decoded times or strings are not lattice coordinates)"
        )
    return values


def coordinate_spacing(coord: Any) -> float:
    """The lattice spacing of a uniform coordinate: its first step ``c[1] - c[0]``.

    The one formula of the package (the engine's lattice, the field files and
    every served figure use it); the coordinate's uniformity is checked by
    :func:`check_coordinate`.

    >>> coordinate_spacing([0.0, 0.25, 0.5])
    0.25
    """
    c = np.asarray(coord)
    return float(c[1] - c[0])


def field_spacing(da: xr.DataArray, source: str = "<array>") -> tuple[float, ...]:
    """Lattice spacing along each lattice dim of ``da``, time first (see :func:`coordinate_spacing`).

    >>> da = xr.DataArray(np.zeros((3, 5)), dims=["t", "x"],
    ...                   coords={"t": [0.0, 0.1, 0.2], "x": np.linspace(0, 1, 5)})
    >>> field_spacing(da)
    (0.1, 0.25)
    """
    out = []
    for dim in lattice_dims(da):
        c = _coord_values(da, dim, source)
        if c.size < 2:
            raise InputError(f"{source}: dim '{dim}' has {c.size} site(s); expected at least 2")
        out.append(coordinate_spacing(c))
    return tuple(out)


#: The coordinate along time of a field that keeps some of the slices served (``serve(every=k)``): the
#: index of each kept slice; the time coordinate is uniform per slice index.
SLICE_COORD = "slice"


def check_coordinate(da: xr.DataArray, dim: str, source: str) -> None:
    """Check that the coordinate of lattice dim ``dim`` is numeric, finite, uniform and increasing.

    Uniform means that its steps agree to a relative ``1e-6`` of the spacing
    (or to the round-off of the stored dtype, e.g. float32 coordinates).
    """
    c = _coord_values(da, dim, source)
    if c.size < 2:
        raise InputError(f"{source}: dim '{dim}' has {c.size} site(s); expected at least 2")
    c = c.astype(np.float64)
    if not np.all(np.isfinite(c)):
        raise InputError(f"{source}: coordinate '{dim}' holds NaN or inf; expected finite values")
    steps = np.diff(c) / _slice_steps(da, dim, source)
    lo, hi = float(steps.min()), float(steps.max())
    if lo <= 0.0:
        raise InputError(
            f"{source}: coordinate '{dim}' is not strictly increasing "
            f"(spacing ranges from {lo:.6g} to {hi:.6g}); expected uniform increasing values"
        )
    h = float(steps.mean())
    # Tolerate round-off of the stored dtype (e.g. float32 coordinates).
    dtype = da.coords[dim].dtype
    eps = np.finfo(dtype if np.issubdtype(dtype, np.floating) else np.float64).eps
    tol = max(_UNIFORM_RTOL * h, 8 * eps * float(np.abs(c).max()))
    if hi - lo > tol:
        raise InputError(
            f"{source}: coordinate '{dim}' is not uniformly spaced "
            f"(spacing ranges from {lo:.6g} to {hi:.6g}); expected a uniform lattice"
        )


def _slice_steps(da: xr.DataArray, dim: str, source: str) -> np.ndarray:
    """The steps of the lattice index along ``dim``: 1, or for the time slices kept of a field served with an
    output cadence the steps of its ``slice`` coordinate (the coordinate is then uniform per slice index)."""
    n = da.sizes[dim]
    if SLICE_COORD not in da.coords or da.coords[SLICE_COORD].dims != (dim,):
        return np.ones(max(n - 1, 0))
    idx = np.asarray(da.coords[SLICE_COORD].values)
    if not np.issubdtype(idx.dtype, np.integer) or idx.size < 2 or np.any(np.diff(idx) <= 0):
        raise InputError(
            f"{source}: coordinate '{SLICE_COORD}' along '{dim}' is not a strictly increasing integer "
            "index; expected the kept time slices' indices"
        )
    return np.diff(idx).astype(np.float64)


# -- the periodic attribute ----------------------------------------------------------------------------------
def parse_periodic(value: Any, dim: str = "?", source: str = "<array>") -> bool:
    """The value of a ``periodic`` attribute as a bool.

    Accepts ``"true"``/``"false"`` (any case, surrounding blanks ignored),
    booleans and the integers 0/1 (also as one-element arrays, as netCDF
    may return them); anything else raises a one-line :class:`InputError`.

    >>> parse_periodic(" True "), parse_periodic(0)
    (True, False)
    """
    if isinstance(value, np.ndarray) and value.size == 1:
        value = value.item()
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)) and int(value) in (0, 1):
        return bool(value)
    if isinstance(value, str) and value.strip().lower() in _PERIODIC_TEXT:
        return _PERIODIC_TEXT[value.strip().lower()]
    raise InputError(
        f"{source}: attribute '{PERIODIC_ATTR}' of coordinate '{dim}' is {value!r}; expected \"true\" or \"false\""
    )


def periodic_attr(periodic: bool) -> str:
    """The ``periodic`` attribute value that marks a lattice axis as periodic (or not).

    >>> periodic_attr(True), parse_periodic(periodic_attr(True))
    ('true', True)
    """
    return "true" if periodic else "false"


def axis_periodic(da: xr.DataArray, dim: str, source: str = "<array>") -> bool:
    """Whether the coordinate of ``dim`` is marked periodic (False where the attribute is absent).

    >>> da = xr.DataArray(np.zeros(3), dims=["x"], coords={"x": [0.0, 1.0, 2.0]})
    >>> axis_periodic(da, "x"), axis_periodic(da.assign_coords(x=da.x.assign_attrs(periodic="True")), "x")
    (False, True)
    """
    if dim not in da.coords or PERIODIC_ATTR not in da.coords[dim].attrs:
        return False
    return parse_periodic(da.coords[dim].attrs[PERIODIC_ATTR], dim, source)


def field_periodic(da: xr.DataArray, source: str = "<array>") -> tuple[bool | None, ...]:
    """The ``periodic`` attribute of each lattice coordinate of ``da``, time first; ``None`` where absent.

    >>> da = xr.DataArray(np.zeros((2, 3)), dims=["t", "x"],
    ...                   coords={"t": [0.0, 1.0], "x": [0.0, 1.0, 2.0]})
    >>> da.x.attrs["periodic"] = "true"
    >>> field_periodic(da)
    (None, True)
    """
    out: list[bool | None] = []
    for dim in lattice_dims(da):
        if dim not in da.coords or PERIODIC_ATTR not in da.coords[dim].attrs:
            out.append(None)
        else:
            out.append(parse_periodic(da.coords[dim].attrs[PERIODIC_ATTR], dim, source))
    return tuple(out)


# -- the whole layout ----------------------------------------------------------------------------------------
def _check_components(da: xr.DataArray, source: str, components: Sequence[str] | None) -> None:
    dims = [str(d) for d in da.dims]
    if COMPONENT_DIM not in dims:
        if components is not None:
            raise InputError(
                f"{source}: {'field' if da.name is None else f'field {da.name!r}'} has no "
                f"'{COMPONENT_DIM}' dim; "
                f"expected components {list(components)!r}"
            )
        return
    if dims[-1] != COMPONENT_DIM:
        raise InputError(
            f"{source}: dim '{COMPONENT_DIM}' is at position {dims.index(COMPONENT_DIM)} of "
            f"{tuple(dims)}; expected it last"
        )
    if COMPONENT_DIM not in da.coords:
        raise InputError(
            f"{source}: dim '{COMPONENT_DIM}' has no coordinate; expected string labels such as ['x', 'y']"
        )
    labels = np.asarray(da.coords[COMPONENT_DIM].values)
    if not all(isinstance(v, (str, np.str_)) for v in labels.tolist()):
        raise InputError(
            f"{source}: coordinate '{COMPONENT_DIM}' has dtype {labels.dtype}; expected "
            f"string labels such as ['x', 'y']"
        )
    found = [str(v) for v in labels.tolist()]
    if components is not None and found != [str(c) for c in components]:
        raise InputError(
            f"{source}: component labels do not match: expected {[str(c) for c in components]!r}, found {found!r}"
        )


def _site_text(da: xr.DataArray, index: tuple[Any, ...]) -> str:
    """A site as its array index and, apart, its coordinates: ``index t=2, x=3 (t = 0.1, x = 0.75)``
    (a component by its label)."""
    idx = ", ".join(f"{d}={int(i)}" for d, i in zip(da.dims, index))
    coords = []
    for d, i in zip(da.dims, index):
        if d in da.coords and da[d].ndim == 1:
            v = da[d].values[int(i)]
            coords.append(f"{d} = {float(v):.6g}" if np.issubdtype(np.asarray(v).dtype, np.number) else f"{d} = {v}")
    return f"index {idx}" + (f" ({', '.join(coords)})" if coords else "")


def _non_finite_block(values: np.ndarray, t0: int) -> tuple[int, tuple[int, ...]]:
    """The count of NaN/inf values in ``values`` (slices from ``t0`` on) and the index of the first."""
    bad = ~np.isfinite(values)
    n_bad = int(bad.sum())
    if not n_bad:
        return 0, ()
    first = [int(i) for i in np.unravel_index(int(np.argmax(bad.reshape(-1))), bad.shape)]
    if first:
        first[0] += t0
    return n_bad, tuple(first)


def _non_finite(da: xr.DataArray) -> tuple[int, tuple[int, ...]]:
    """:func:`_non_finite_block` of a lazily opened field, read in blocks of slices (never whole)."""
    tdim, nt = da.dims[0], da.shape[0]
    step = max(1, option("scan_bytes") // max(1, math.prod(da.shape[1:]) * da.dtype.itemsize))
    total, first = 0, ()  # type: tuple[int, tuple[int, ...]]
    for a in range(0, nt, step):
        n, at = _non_finite_block(np.asarray(da.isel({tdim: slice(a, a + step)}).values), a)
        if n and not total:
            first = at
        total += n
    return total, first


_TIME_NAMES = ("t", "time")


def _check_time_first(da: xr.DataArray, dims: tuple[str, ...], source: str) -> None:
    """The time dim comes first: a dim named ``t`` or ``time``, or whose coordinate says ``axis: T`` or
    ``standard_name: time``, anywhere else is an error (``field.transpose("x", "t")`` would serve x as time)."""
    for dim in dims[1:]:
        attrs = da.coords[dim].attrs if dim in da.coords else {}
        if dim.lower() in _TIME_NAMES or attrs.get("axis") == "T" or attrs.get("standard_name") == "time":
            raise InputError(
                f"{source}: the time dim '{dim}' is in place {dims.index(dim) + 1} of the dims {dims}; "
                f"expected time first and x last (da.transpose('{dim}', ...))"
            )


def validate_field(
    da: xr.DataArray,
    source: str = "<array>",
    *,
    components: Sequence[str] | None = None,
    allow_nan: bool = False,
) -> xr.DataArray:
    """Check that ``da`` follows the field layout (see the module docstring).

    Parameters
    ----------
    da
        The field.
    source
        What to call it in error messages (a file name, a config key ...).
    components
        Expected labels of the ``component`` dim, or None for no check
        (a scalar field then passes too).
    allow_nan
        Accept NaN/inf values (e.g. a prediction that stopped early).

    Returns
    -------
    xarray.DataArray
        ``da`` with float64 values (the same object when already float64).

    Raises
    ------
    InputError
        With a one-line message naming ``source`` and what was expected.

    Examples
    --------
    >>> da = xr.DataArray([0.0, np.nan, 1.0], dims=["t"], coords={"t": [0.0, 1.0, 2.0]})
    >>> try:
    ...     validate_field(da, "a.nc")
    ... except InputError as err:
    ...     print(err)
    a.nc: field holds 1 NaN/inf value(s), the first at index t=1 (t = 1); expected finite values
    """
    if not isinstance(da, xr.DataArray):
        raise InputError(f"{source}: expected an xarray.DataArray, got {type(da).__name__}")
    _check_components(da, source, components)
    what = "field" if da.name is None else f"field {da.name!r}"
    dims = lattice_dims(da)
    if not dims:
        raise InputError(f"{source}: {what} has no lattice dims; expected e.g. psi(t), psi(t, x)")
    _check_time_first(da, dims, source)
    for dim in dims:
        check_coordinate(da, dim, source)
    if not (np.issubdtype(da.dtype, np.floating) or np.issubdtype(da.dtype, np.integer)) or da.dtype == bool:
        raise InputError(f"{source}: {what} has dtype {da.dtype}; expected real numbers")
    # a file opened lazily (or dask-backed): its values are read in blocks of slices
    lazy = da.chunks is not None or not getattr(da.variable, "_in_memory", True)
    if da.dtype != np.float64 and not lazy:
        da = da.astype(np.float64)
    if not allow_nan:
        n_bad, first = _non_finite(da) if lazy else _non_finite_block(da.values, 0)
        if n_bad:
            raise InputError(
                f"{source}: {what} holds {n_bad} NaN/inf value(s), the first at {_site_text(da, first)}; "
                "expected finite values"
            )
    field_periodic(da, source)
    return da


def is_lazy(da: xr.DataArray) -> bool:
    """True for a DataArray whose values are not in memory (dask-backed, or opened from a file unloaded)."""
    return da.chunks is not None or not bool(getattr(da.variable, "_in_memory", True))
