"""Field construction and the checks shared by every family of canonical systems.

Every generator of :mod:`latticedft.systems` returns its field as an
:class:`xarray.DataArray` in the field layout of latticedft:

* name ``"psi"``; dims time first, then spatial dims with ``x`` last
  (``("t",)``, ``("t", "x")``, ``("t", "y", "x")``); vector fields add a
  trailing ``"component"`` dim with string labels (Kepler: ``["x", "y"]``);
* every lattice dim has a float64, uniformly spaced coordinate
  (``t = t0 + i*dt``) with attributes ``units``, ``long_name`` and ``axis``;
  periodic axes also carry ``periodic = "true"`` and ``period``;
* the values are float64 and C-contiguous; the DataArray carries
  ``long_name``, ``units`` and ``source`` (how it was made).

:func:`make_field` builds a DataArray in this layout from plain arrays. The
reference ODE solutions (:func:`_solve`) use :func:`scipy.integrate.solve_ivp`
with the 8th-order Dormand–Prince method (DOP853), ``rtol = atol = 1e-12``
(:data:`ODE_RTOL`, :data:`ODE_ATOL`), sampled at the lattice times through
``t_eval`` (the method's dense output).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import xarray as xr
from numpy.typing import ArrayLike, NDArray

from latticedft._errors import InputError
from latticedft._layout import COMPONENT_DIM

__all__ = ["ODE_ATOL", "ODE_RTOL", "make_field"]

#: Relative tolerance of every reference ODE solve (DOP853).
ODE_RTOL = 1e-12
#: Absolute tolerance of every reference ODE solve (DOP853).
ODE_ATOL = 1e-12

_FloatArray = NDArray[np.float64]

# ----------------------------------------------------------------------------
# Field construction
# ----------------------------------------------------------------------------

_DIM_DEFAULTS: dict[str, tuple[str, str]] = {
    "t": ("time", "T"),
    "x": ("x", "X"),
    "y": ("y", "Y"),
    "z": ("z", "Z"),
}


def _per_dim(value: float | Sequence[float], ndim: int, arg: str) -> list[float]:
    """Broadcast a scalar or check a per-dim sequence of floats."""
    if np.ndim(value) == 0:
        out = [float(value)] * ndim  # type: ignore[arg-type]
    else:
        out = [float(v) for v in value]  # type: ignore[union-attr]
        if len(out) != ndim:
            raise InputError(f"{arg}: expected a number or {ndim} numbers (one per lattice dim), got {len(out)}")
    if not all(math.isfinite(v) for v in out):
        raise InputError(f"{arg}: expected finite numbers, got {out}")
    return out


def _uniform_spacing(coord: ArrayLike, dim: str) -> float:
    """Spacing of a uniformly spaced, increasing 1-D coordinate (InputError otherwise)."""
    c = np.asarray(coord, dtype=np.float64)
    if c.ndim != 1 or c.size < 2:
        raise InputError(f"coordinate {dim!r}: need a 1-D coordinate with at least 2 values to read a spacing")
    h = (c[-1] - c[0]) / (c.size - 1)
    if not np.isfinite(h) or h <= 0:
        raise InputError(f"coordinate {dim!r}: expected increasing finite values")
    dev = np.max(np.abs(c - (c[0] + h * np.arange(c.size))))
    if dev > 1e-9 * h + 8 * np.finfo(np.float64).eps * np.max(np.abs(c)):
        raise InputError(f"coordinate {dim!r}: not uniformly spaced (deviation {dev:.3g} for spacing {h:.6g})")
    return float(h)


def make_field(
    values: ArrayLike,
    dims: Sequence[str],
    *,
    spacing: float | Sequence[float] | None = None,
    origin: float | Sequence[float] = 0.0,
    coords: Mapping[str, ArrayLike] | None = None,
    components: Sequence[str] | None = None,
    name: str = "psi",
    attrs: Mapping[str, Any] | None = None,
    coord_attrs: Mapping[str, Mapping[str, Any]] | None = None,
) -> xr.DataArray:
    """Build a field DataArray in the field layout (see the module docstring).

    Parameters
    ----------
    values
        Real array of shape ``lattice_shape`` (scalar field) or
        ``lattice_shape + (len(components),)`` (vector field).
    dims
        Names of the lattice dims, time first and ``x`` last, e.g.
        ``("t", "x")``. Do not list ``"component"``: it is added when
        `components` is given.
    spacing
        Lattice spacing, one number for every dim or one per dim; the
        coordinate of dim ``k`` is ``origin[k] + i * spacing[k]``.
    origin
        First coordinate value, one number or one per dim.
    coords
        Explicit coordinates ``{dim: 1-D array}``; each must be uniformly
        spaced and increasing. They take precedence over `spacing` for the
        dims they name; every other dim needs `spacing`.
    components
        String labels of the vector components (e.g. ``["x", "y"]``).
    name
        Variable name (default ``"psi"``).
    attrs
        Attributes of the DataArray (``long_name``, ``units``, ``source`` ...;
        strings or numbers). ``long_name`` defaults to `name`.
    coord_attrs
        Per-dim coordinate attributes, merged over the defaults
        (``units = "1"``, ``long_name`` "time"/"x"/"y", ``axis`` "T"/"X"/"Y").

    Returns
    -------
    xarray.DataArray
        float64, C-contiguous values with float64 coordinates.

    Raises
    ------
    InputError
        On a shape, dims, spacing or coordinate that does not fit.

    Examples
    --------
    >>> import numpy as np
    >>> f = make_field(np.zeros((3, 4)), ("t", "x"), spacing=(0.1, 0.25))
    >>> f.dims, f["x"].values.tolist(), f["t"].attrs["axis"]
    (('t', 'x'), [0.0, 0.25, 0.5, 0.75], 'T')
    >>> orbit = make_field(np.ones((5, 2)), ("t",), spacing=0.05, components=["x", "y"])
    >>> orbit.dims, orbit["component"].values.tolist()
    (('t', 'component'), ['x', 'y'])
    """
    dims = tuple(dims)
    arr = _field_values(values, dims, components)
    out_coords = _lattice_coords(arr.shape, dims, spacing, origin, coords, coord_attrs)
    all_dims = dims
    if components is not None:
        all_dims = dims + (COMPONENT_DIM,)
        out_coords[COMPONENT_DIM] = xr.Variable(
            (COMPONENT_DIM,), np.array(list(components), dtype=str), attrs={"long_name": "vector component"}
        )
    da_attrs = {"long_name": name}
    da_attrs.update(attrs or {})
    return xr.DataArray(arr, dims=all_dims, coords=out_coords, name=name, attrs=da_attrs)


def _field_values(values: ArrayLike, dims: tuple[str, ...], components: Sequence[str] | None) -> _FloatArray:
    """Check `dims` and `components` against `values`; the values as a float64, C-contiguous array."""
    if len(dims) == 0 or len(set(dims)) != len(dims) or not all(isinstance(d, str) for d in dims):
        raise InputError(f"dims: expected distinct dim names, got {dims!r}")
    if COMPONENT_DIM in dims:
        raise InputError(f"dims: do not list {COMPONENT_DIM!r}; pass components=[...] instead")
    arr = np.asarray(values)
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr) or arr.dtype == np.bool_:
        raise InputError(f"values: expected real numbers, got dtype {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    ncomp = 0 if components is None else len(components)
    expected_ndim = len(dims) + (1 if components is not None else 0)
    if arr.ndim != expected_ndim:
        raise InputError(
            f"values: expected {expected_ndim} dims for dims={dims!r}"
            f"{' plus component' if components is not None else ''}, got shape {arr.shape}"
        )
    if components is not None and (
        ncomp == 0 or arr.shape[-1] != ncomp or not all(isinstance(s, str) for s in components)
    ):
        raise InputError(f"components: expected {arr.shape[-1]} string labels, got {list(components)!r}")
    if not np.all(np.isfinite(arr)):
        raise InputError("values: contains NaN or infinity")
    return arr


def _lattice_coords(
    shape: tuple[int, ...],
    dims: tuple[str, ...],
    spacing: float | Sequence[float] | None,
    origin: float | Sequence[float],
    coords: Mapping[str, ArrayLike] | None,
    coord_attrs: Mapping[str, Mapping[str, Any]] | None,
) -> dict[str, Any]:
    """The coordinate variables of the lattice dims, from explicit `coords` or `origin` + `spacing`."""
    coords = dict(coords or {})
    unknown = set(coords) - set(dims)
    if unknown:
        raise InputError(f"coords: {sorted(unknown)} are not among dims {dims!r}")
    origins = _per_dim(origin, len(dims), "origin")
    spacings = None if spacing is None else _per_dim(spacing, len(dims), "spacing")
    if spacings is not None and any(h <= 0 for h in spacings):
        raise InputError(f"spacing: expected positive numbers, got {spacings}")
    coord_attrs = dict(coord_attrs or {})
    out_coords: dict[str, Any] = {}
    for k, d in enumerate(dims):
        n = shape[k]
        if d in coords:
            c = np.asarray(coords[d], dtype=np.float64)
            if c.shape != (n,):
                raise InputError(f"coords[{d!r}]: expected {n} values, got shape {c.shape}")
            if n >= 2:
                _uniform_spacing(c, d)
        elif spacings is not None:
            c = origins[k] + spacings[k] * np.arange(n, dtype=np.float64)
        else:
            raise InputError(f"spacing: needed for dim {d!r} (or give coords[{d!r}])")
        long_name, axis = _DIM_DEFAULTS.get(d, (d, ""))
        ca: dict[str, Any] = {"units": "1", "long_name": long_name}
        if axis:
            ca["axis"] = axis
        ca.update(coord_attrs.get(d, {}))
        out_coords[d] = xr.Variable((d,), np.ascontiguousarray(c), attrs=ca)
    return out_coords


def _time_attrs(units: str = "1") -> dict[str, Any]:
    """Default attributes of a ``t`` coordinate in `units`."""
    return {"units": units, "long_name": "time", "axis": "T"}


# ----------------------------------------------------------------------------
# Argument checks and the reference ODE solve
# ----------------------------------------------------------------------------


def _check_lattice_1d(n: int, dt: float, n_name: str = "n") -> None:
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 2:
        raise InputError(f"{n_name}: expected an integer >= 2, got {n!r}")
    if not (isinstance(dt, (int, float, np.floating)) and math.isfinite(dt) and dt > 0):
        raise InputError(f"dt: expected a positive finite number, got {dt!r}")


def _check_finite(value: float, arg: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{arg}: expected a number, got {value!r}") from None
    if not math.isfinite(v):
        raise InputError(f"{arg}: expected a finite number, got {value!r}")
    return v


def _solve(
    rhs: Callable[[float, _FloatArray], Any], y0: Sequence[float], t: _FloatArray, events: Any = None, what: str = "ODE"
) -> Any:
    from scipy.integrate import solve_ivp  # imported here: scipy.integrate takes ~0.5 s to import

    sol = solve_ivp(
        rhs,
        (float(t[0]), float(t[-1])),
        np.asarray(y0, dtype=np.float64),
        method="DOP853",
        t_eval=t,
        rtol=ODE_RTOL,
        atol=ODE_ATOL,
        events=events,
    )
    if sol.status == -1:
        raise InputError(f"initial data: the {what} solve failed ({sol.message})")
    return sol


def _check_positive(value: float, arg: str) -> float:
    v = _check_finite(value, arg)
    if v <= 0:
        raise InputError(f"{arg}: expected a positive number, got {value!r}")
    return v


def _check_count(value: int, arg: str, minimum: int) -> int:
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < minimum:
        raise InputError(f"{arg}: expected an integer >= {minimum}, got {value!r}")
    return int(value)


def _as_real_array(a: ArrayLike, arg: str) -> _FloatArray:
    arr = np.asarray(a.values if isinstance(a, xr.DataArray) else a)
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr) or arr.dtype == np.bool_:
        raise InputError(f"{arg}: expected real numbers, got dtype {arr.dtype}")
    arr = np.asarray(arr, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{arg}: contains NaN or infinity")
    return arr
