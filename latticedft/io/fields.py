"""Field files: read, validate and write lattice fields as netCDF (docs/design.md, "Field files").

A field is a :class:`xarray.DataArray` (default name ``psi``) whose dims are the
lattice dims in CF order -- time first, then the spatial dims with x last:
``psi(t)``, ``psi(t, x)``, ``psi(t, y, x)`` -- plus an optional trailing dim
``component`` with string labels for vector fields (Kepler:
``psi(t, component)``, ``component = ["x", "y"]``). Every lattice dim has a
numeric, uniformly spaced, strictly increasing coordinate from which the
spacings are read. A lattice coordinate may carry the attribute
``periodic = "true"`` or ``"false"``.

Every problem with user data raises :class:`latticedft._errors.InputError`
with a one-line message that names the file (or ``source``) and what was
expected.

Examples
--------
>>> import numpy as np, xarray as xr
>>> t = np.arange(4) * 0.5
>>> da = xr.DataArray(np.sin(t), dims=["t"], coords={"t": t}, name="psi")
>>> field_spacing(validate_field(da))
(0.5,)
>>> lattice_dims(da)
('t',)
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import uuid
from collections.abc import Hashable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from latticedft._errors import InputError

__all__ = [
    "COMPONENT_DIM",
    "read_field",
    "validate_field",
    "write_field",
    "field_spacing",
    "field_periodic",
    "lattice_dims",
]

#: Name of the optional trailing dim holding the components of a vector field.
COMPONENT_DIM = "component"

# Relative tolerance on the deviation of a coordinate's steps from uniform.
_UNIFORM_RTOL = 1e-6


def _one_line(text: object, limit: int = 200) -> str:
    """Collapse an arbitrary message (e.g. a library exception) to one short line."""
    s = " ".join(str(text).split())
    return s if len(s) <= limit else s[: limit - 3] + "..."


def lattice_dims(da: xr.DataArray) -> tuple[str, ...]:
    """Return the lattice dims of ``da`` (all dims except ``component``), time first.

    >>> import xarray as xr, numpy as np
    >>> lattice_dims(xr.DataArray(np.zeros((3, 2)), dims=["t", "component"]))
    ('t',)
    """
    return tuple(str(d) for d in da.dims if d != COMPONENT_DIM)


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


def field_spacing(da: xr.DataArray, source: str = "<array>") -> tuple[float, ...]:
    """Lattice spacing along each lattice dim, time first.

    The spacing is ``(c[-1] - c[0]) / (n - 1)`` of the dim's coordinate ``c``
    (the most accurate estimate for a uniform coordinate).

    >>> import xarray as xr, numpy as np
    >>> da = xr.DataArray(np.zeros((3, 5)), dims=["t", "x"],
    ...                   coords={"t": [0.0, 0.1, 0.2], "x": np.linspace(0, 1, 5)})
    >>> field_spacing(da)
    (0.1, 0.25)
    """
    out = []
    for dim in lattice_dims(da):
        c = _coord_values(da, dim, source).astype(np.float64)
        if c.size < 2:
            raise InputError(f"{source}: dim '{dim}' has {c.size} site(s); expected at least 2")
        out.append(float((c[-1] - c[0]) / (c.size - 1)))
    return tuple(out)


def field_periodic(da: xr.DataArray, source: str = "<array>") -> tuple[bool | None, ...]:
    """The ``periodic`` attribute of each lattice coordinate, time first.

    ``None`` where the attribute is absent. Accepts ``"true"``/``"false"``
    (any case), booleans and 0/1.

    >>> import xarray as xr, numpy as np
    >>> da = xr.DataArray(np.zeros((2, 3)), dims=["t", "x"],
    ...                   coords={"t": [0.0, 1.0], "x": [0.0, 1.0, 2.0]})
    >>> da.x.attrs["periodic"] = "true"
    >>> field_periodic(da)
    (None, True)
    """
    out: list[bool | None] = []
    for dim in lattice_dims(da):
        if dim not in da.coords or "periodic" not in da.coords[dim].attrs:
            out.append(None)
            continue
        value = da.coords[dim].attrs["periodic"]
        if isinstance(value, np.ndarray) and value.size == 1:
            value = value.item()
        if isinstance(value, (bool, np.bool_)):
            out.append(bool(value))
        elif isinstance(value, (int, np.integer)) and int(value) in (0, 1):
            out.append(bool(value))
        elif isinstance(value, str) and value.strip().lower() in ("true", "false"):
            out.append(value.strip().lower() == "true")
        else:
            raise InputError(
                f"{source}: attribute 'periodic' of coordinate '{dim}' is {value!r}; "
                f"expected \"true\" or \"false\""
            )
    return tuple(out)


def _check_coordinate(da: xr.DataArray, dim: str, source: str) -> None:
    c = _coord_values(da, dim, source)
    if c.size < 2:
        raise InputError(f"{source}: dim '{dim}' has {c.size} site(s); expected at least 2")
    c = c.astype(np.float64)
    if not np.all(np.isfinite(c)):
        raise InputError(f"{source}: coordinate '{dim}' holds NaN or inf; expected finite values")
    steps = np.diff(c)
    lo, hi = float(steps.min()), float(steps.max())
    if lo <= 0.0:
        raise InputError(
            f"{source}: coordinate '{dim}' is not strictly increasing "
            f"(spacing ranges from {lo:.6g} to {hi:.6g}); expected uniform increasing values"
        )
    h = (c[-1] - c[0]) / (c.size - 1)
    # Tolerate round-off of the stored dtype (e.g. float32 coordinates).
    dtype = da.coords[dim].dtype
    eps = np.finfo(dtype if np.issubdtype(dtype, np.floating) else np.float64).eps
    tol = max(_UNIFORM_RTOL * h, 8 * eps * float(np.abs(c).max()))
    if hi - lo > tol:
        raise InputError(
            f"{source}: coordinate '{dim}' is not uniformly spaced "
            f"(spacing ranges from {lo:.6g} to {hi:.6g}); expected a uniform lattice"
        )


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
            f"{source}: dim '{COMPONENT_DIM}' has no coordinate; expected string labels "
            f"such as ['x', 'y']"
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
            f"{source}: component labels do not match: expected "
            f"{[str(c) for c in components]!r}, found {found!r}"
        )


def validate_field(
    da: xr.DataArray,
    source: str = "<array>",
    *,
    components: Sequence[str] | None = None,
    allow_nan: bool = False,
) -> xr.DataArray:
    """Check that ``da`` follows the field-file layout (docs/design.md).

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
    >>> import numpy as np, xarray as xr
    >>> da = xr.DataArray([0.0, np.nan, 1.0], dims=["t"], coords={"t": [0.0, 1.0, 2.0]})
    >>> validate_field(da, "a.nc")
    Traceback (most recent call last):
    ...
    latticedft._errors.InputError: a.nc: field holds 1 NaN/inf value(s), first at (t=1); expected finite values
    """
    if not isinstance(da, xr.DataArray):
        raise InputError(f"{source}: expected an xarray.DataArray, got {type(da).__name__}")
    _check_components(da, source, components)
    what = "field" if da.name is None else f"field {da.name!r}"
    dims = lattice_dims(da)
    if not dims:
        raise InputError(
            f"{source}: {what} has no lattice dims; expected e.g. psi(t), psi(t, x)"
        )
    for dim in dims:
        _check_coordinate(da, dim, source)
    if not (np.issubdtype(da.dtype, np.floating) or np.issubdtype(da.dtype, np.integer)) \
            or da.dtype == bool:
        raise InputError(f"{source}: {what} has dtype {da.dtype}; expected real numbers")
    if da.dtype != np.float64:
        da = da.astype(np.float64)
    if not allow_nan:
        bad = ~np.isfinite(da.values)
        n_bad = int(bad.sum())
        if n_bad:
            first = np.unravel_index(int(np.argmax(bad.reshape(-1))), bad.shape)
            where = ", ".join(f"{d}={int(i)}" for d, i in zip(da.dims, first))
            raise InputError(
                f"{source}: {what} holds {n_bad} NaN/inf value(s), "
                f"first at ({where}); expected finite values"
            )
    field_periodic(da, source)
    return da


def read_field(
    path: str | os.PathLike[str],
    variable: str = "psi",
    *,
    components: Sequence[str] | None = None,
    allow_nan: bool = False,
) -> xr.DataArray:
    """Read and validate one field from a netCDF file.

    The file is opened with xarray's netCDF4 engine (times are not decoded:
    lattice coordinates stay numbers), loaded into memory as float64 and
    closed before returning.

    Parameters
    ----------
    path
        The netCDF file.
    variable
        Name of the data variable holding the field.
    components
        Expected labels of the ``component`` dim (e.g. ``["x", "y"]``).
    allow_nan
        Accept NaN/inf values (e.g. reloading a prediction that stopped early).

    Raises
    ------
    InputError
        Missing or unreadable file, missing variable, or a field that breaks
        the layout (see :func:`validate_field`); the message is one line.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: file not found; expected a netCDF field file")
    if p.is_dir():
        raise InputError(f"{p}: is a folder; expected a netCDF field file")
    try:
        ds = xr.open_dataset(p, engine="netcdf4", decode_times=False, decode_timedelta=False)
    except Exception as exc:  # the library raises OSError, ValueError, ... for bad files
        raise InputError(
            f"{p}: not a readable netCDF file ({type(exc).__name__}: {_one_line(exc, 120)})"
        ) from None
    with ds:
        if variable not in ds.data_vars:
            present = sorted(str(v) for v in ds.data_vars)
            raise InputError(
                f"{p}: no variable {variable!r}; variables present: {present!r}"
            )
        try:
            da = ds[variable].load()
        except Exception as exc:
            raise InputError(
                f"{p}: cannot read variable {variable!r} "
                f"({type(exc).__name__}: {_one_line(exc, 120)})"
            ) from None
    da = validate_field(da, str(p), components=components, allow_nan=allow_nan)
    return da.copy(deep=False)


# ----------------------------------------------------------------------------- writing


def _safe_attr(value: Any) -> Any:
    """Turn an attribute value into something netCDF can store (a string or a number)."""
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if value is None:
        return "none"
    if isinstance(value, (str, int, float, np.integer, np.floating)):
        return value
    if isinstance(value, np.ndarray) and value.ndim <= 1 and value.dtype != bool and (
        np.issubdtype(value.dtype, np.integer) or np.issubdtype(value.dtype, np.floating)
    ):
        return value
    if isinstance(value, (list, tuple, dict, np.ndarray)):
        if isinstance(value, np.ndarray):
            value = value.tolist()
        return json.dumps(value, default=str)
    return str(value)


def _safe_attrs(attrs: Mapping[Hashable, Any]) -> dict[str, Any]:
    return {str(k): _safe_attr(v) for k, v in attrs.items()}


def _package_version() -> str:
    try:
        from importlib.metadata import version

        return version("latticedft")
    except Exception:
        return "unknown"


def _default_axes(ds: xr.Dataset) -> None:
    """Add CF ``axis`` attributes (T, X, Y, Z) to lattice coordinates lacking one."""
    for var in ds.data_vars.values():
        dims = lattice_dims(var)
        if not dims or len(dims) > 4:
            continue
        names = dict(zip(reversed(dims[1:]), ("X", "Y", "Z")))
        names[dims[0]] = "T"
        for dim, axis in names.items():
            if dim in ds.coords and "axis" not in ds.coords[dim].attrs:
                ds.coords[dim].attrs["axis"] = axis


def write_field(
    path: str | os.PathLike[str],
    fields: Mapping[str, xr.DataArray] | xr.Dataset,
    *,
    attrs: Mapping[str, Any] | None = None,
    history: str | None = None,
    compress: bool = True,
) -> Path:
    """Write fields to a CF-style netCDF file, atomically.

    Parameters
    ----------
    path
        Target file; its folder must exist.
    fields
        Data variables by name (e.g. ``{"psi": pred, "psi_ref": ref,
        "psi_err": pred - ref}``, sharing coordinates), or a Dataset.
    attrs
        Global attributes to add (override those of a Dataset input). Values
        that netCDF cannot store (bools, None, lists, dicts) become strings.
    history
        A line appended, as ``"<ISO time>: <history>"``, to the ``history``
        attribute of the input (Dataset attrs, or ``attrs["history"]``).
    compress
        zlib-compress the data variables.

    Returns
    -------
    pathlib.Path
        The file written.

    Notes
    -----
    Sets ``Conventions = "CF-1.8"``, ``source`` (unless given), CF ``axis``
    on lattice coordinates lacking one, and ``_FillValue: None`` on
    coordinates. The file is written to a temporary file in the same folder
    and renamed over ``path``; on any error the temporary file is removed and
    an existing ``path`` is left untouched.

    Examples
    --------
    >>> import tempfile, numpy as np, xarray as xr
    >>> t = np.linspace(0.0, 1.0, 5)
    >>> da = xr.DataArray(t**2, dims=["t"], coords={"t": t})
    >>> with tempfile.TemporaryDirectory() as d:
    ...     p = write_field(f"{d}/f.nc", {"psi": da}, history="made by a doctest")
    ...     back = read_field(p)
    >>> bool((back == da).all())
    True
    """
    target = Path(path)
    folder = target.parent if str(target.parent) else Path(".")
    if not folder.is_dir():
        raise InputError(f"{target}: folder {folder} does not exist; expected an existing folder")

    if isinstance(fields, xr.Dataset):
        ds = fields.copy(deep=False)
    else:
        if not fields:
            raise InputError(f"{target}: no fields to write; expected at least one DataArray")
        arrays = {str(k): v for k, v in fields.items()}
        try:
            aligned = xr.align(*arrays.values(), join="exact")
        except ValueError as exc:
            raise InputError(
                f"{target}: fields {list(arrays)} do not share coordinates ({_one_line(exc, 120)})"
            ) from None
        ds = xr.Dataset(dict(zip(arrays, aligned)))
    ds = ds.drop_encoding()

    # Attributes: copy so that the caller's objects are not modified.
    ds.attrs = dict(ds.attrs)
    for name in ds.variables:
        ds[name].attrs = dict(ds[name].attrs)
    if attrs:
        ds.attrs.update(attrs)
    ds.attrs["Conventions"] = "CF-1.8"
    ds.attrs.setdefault("source", f"latticedft {_package_version()}")
    if history:
        stamp = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        line = f"{stamp}: {_one_line(history, 10_000)}"
        old = ds.attrs.get("history")
        ds.attrs["history"] = f"{old}\n{line}" if old not in (None, "") else line
    _default_axes(ds)
    ds.attrs = _safe_attrs(ds.attrs)
    for name in ds.variables:
        ds[name].attrs = _safe_attrs(ds[name].attrs)

    encoding: dict[str, dict[str, Any]] = {}
    for name, var in ds.data_vars.items():
        enc: dict[str, Any] = {}
        if compress and (np.issubdtype(var.dtype, np.number)):
            enc.update(zlib=True, complevel=4, shuffle=True)
        encoding[str(name)] = enc
    for name in ds.coords:
        encoding[str(name)] = {"_FillValue": None}

    tmp = folder / f".{target.name}.{uuid.uuid4().hex[:12]}.tmp"
    try:
        ds.to_netcdf(tmp, engine="netcdf4", format="NETCDF4", encoding=encoding)
        os.replace(tmp, target)
    except BaseException:
        try:
            tmp.unlink()
        except FileNotFoundError:
            pass
        raise
    return target
