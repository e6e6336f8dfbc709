"""Field files: read, validate and write lattice fields as netCDF.

A field is a :class:`xarray.DataArray` (default name ``psi``) whose dims are the
lattice dims in CF order -- time first, then the spatial dims with x last:
``psi(t)``, ``psi(t, x)``, ``psi(t, y, x)`` -- plus an optional trailing dim
``component`` with string labels for vector fields (Kepler:
``psi(t, component)``, ``component = ["x", "y"]``). Every lattice dim has a
numeric, uniformly spaced, strictly increasing coordinate from which the
spacings are read. A lattice coordinate may carry the attribute
``periodic = "true"`` or ``"false"``.

The layout itself (its dims, spacing, periodic attribute and checks) belongs
to :mod:`latticedft._layout`; :data:`COMPONENT_DIM`, :func:`lattice_dims`,
:func:`field_spacing`, :func:`field_periodic` and :func:`validate_field` are
re-exported from there.

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

import contextlib
import datetime as _dt
import json
import os
import uuid
from collections.abc import Hashable, Mapping, Sequence
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from latticedft._errors import InputError
from latticedft._layout import (
    COMPONENT_DIM,
    field_periodic,
    field_spacing,
    lattice_dims,
    validate_field,
)

__all__ = [
    "COMPONENT_DIM",
    "read_field",
    "validate_field",
    "write_field",
    "field_spacing",
    "field_periodic",
    "lattice_dims",
]


def _one_line(text: object, limit: int = 200) -> str:
    """Collapse an arbitrary message (e.g. a library exception) to one short line."""
    s = " ".join(str(text).split())
    return s if len(s) <= limit else s[: limit - 3] + "..."


def _path(path: object, name: str) -> Path:
    """``path`` as a Path, or an InputError naming the argument ``name``."""
    if not isinstance(path, (str, os.PathLike)):
        raise InputError.at(name, f"expected a file path, got {type(path).__name__}")
    return Path(path)


def read_field(
    path: str | os.PathLike[str],
    variable: str = "psi",
    *,
    components: Sequence[str] | None = None,
    allow_nan: bool = False,
    lazy: bool = False,
) -> xr.DataArray:
    """Read and validate one field from a netCDF file.

    The file is opened with xarray's netCDF4 engine (times are not decoded:
    lattice coordinates stay numbers), loaded into memory as float64 and
    closed before returning. With ``lazy=True`` the values stay in the file
    (opened until the DataArray is dropped, in the file's own dtype) and are
    read where the DataArray is indexed; the NaN/inf check reads them in
    blocks of slices.

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
    lazy
        Leave the values in the file (read slice by slice where indexed).

    Raises
    ------
    InputError
        Missing or unreadable file, missing variable, or a field that breaks
        the layout (see :func:`validate_field`); the message is one line.
    """
    p = _path(path, "path")
    if not isinstance(variable, str):
        raise InputError.at("variable", f"expected the name of a data variable, got {variable!r}")
    if components is not None and (
        isinstance(components, str)
        or not isinstance(components, Sequence)
        or not all(isinstance(c, str) for c in components)
    ):
        raise InputError.at("components", f"expected a list of component labels or None, got {components!r}")
    if not p.exists():
        raise InputError(f"{p}: file not found; expected a netCDF field file")
    if p.is_dir():
        raise InputError(f"{p}: is a folder; expected a netCDF field file")
    try:
        ds = xr.open_dataset(p, engine="netcdf4", decode_times=False, decode_timedelta=False)
    except Exception as exc:  # the library raises OSError, ValueError, ... for bad files
        raise InputError(f"{p}: not a readable netCDF file ({type(exc).__name__}: {_one_line(exc, 120)})") from None
    if lazy:
        try:
            da = validate_field(_variable(ds, p, variable, lazy), str(p), components=components, allow_nan=allow_nan)
        except InputError:
            ds.close()
            raise
        except Exception as exc:  # a block of values that cannot be read
            ds.close()
            raise InputError(
                f"{p}: cannot read variable {variable!r} ({type(exc).__name__}: {_one_line(exc, 120)})"
            ) from None
        return da.copy(deep=False)
    with ds:
        da = _variable(ds, p, variable, lazy)
    da = validate_field(da, str(p), components=components, allow_nan=allow_nan)
    return da.copy(deep=False)


def _variable(ds: xr.Dataset, p: Path, variable: str, lazy: bool) -> xr.DataArray:
    """``ds[variable]``, loaded unless ``lazy`` (its values read where it is indexed)."""
    if variable not in ds.data_vars:
        present = sorted(str(v) for v in ds.data_vars)
        raise InputError(f"{p}: no variable {variable!r}; variables present: {present!r}")
    if lazy:
        return ds[variable]
    try:
        return ds[variable].load()
    except Exception as exc:
        raise InputError(
            f"{p}: cannot read variable {variable!r} ({type(exc).__name__}: {_one_line(exc, 120)})"
        ) from None


# ----------------------------------------------------------------------------- writing


def _safe_attr(value: Any) -> Any:
    """Turn an attribute value into something netCDF can store (a string or a number)."""
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if value is None:
        return "none"
    if isinstance(value, (str, int, float, np.integer, np.floating)):
        return value
    if (
        isinstance(value, np.ndarray)
        and value.ndim <= 1
        and value.dtype != bool
        and (np.issubdtype(value.dtype, np.integer) or np.issubdtype(value.dtype, np.floating))
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


def prepared_dataset(
    fields: Mapping[str, xr.DataArray] | xr.Dataset,
    attrs: Mapping[str, Any] | None,
    history: str | None,
    compress: bool = True,
    where: str = "fields",
) -> tuple[xr.Dataset, dict[str, dict[str, Any]]]:
    """The Dataset :func:`write_field` writes, with its encoding: the fields aligned, the global attributes
    (``Conventions``, ``source``, ``history``), CF axes and netCDF-safe attributes; ``where`` names the target
    in errors."""
    if isinstance(fields, xr.Dataset):
        ds = fields.copy(deep=False)
    else:
        if not fields:
            raise InputError(f"{where}: no fields to write; expected at least one DataArray")
        if not isinstance(fields, Mapping):
            raise InputError.at(
                "fields", f"expected a mapping name -> DataArray or a Dataset, got {type(fields).__name__}"
            )
        arrays = {str(k): v for k, v in fields.items()}
        bad = [k for k, v in arrays.items() if not isinstance(v, xr.DataArray)]
        if bad:
            raise InputError.at(
                "fields", f"{bad[0]!r}: expected an xarray.DataArray, got {type(arrays[bad[0]]).__name__}"
            )
        try:
            aligned = xr.align(*arrays.values(), join="exact")
        except ValueError as exc:
            raise InputError(
                f"{where}: fields {list(arrays)} do not share coordinates ({_one_line(exc, 120)})"
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
        stamp = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
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

    return ds, encoding


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
    target = _path(path, "path")
    if attrs is not None and not isinstance(attrs, Mapping):
        raise InputError.at("attrs", f"expected a mapping of attribute names to values, got {type(attrs).__name__}")
    if history is not None and not isinstance(history, str):
        raise InputError.at("history", f"expected a string, got {type(history).__name__}")
    folder = target.parent if str(target.parent) else Path(".")
    if not folder.is_dir():
        raise InputError(f"{target}: folder {folder} does not exist; expected an existing folder")

    ds, encoding = prepared_dataset(fields, attrs, history, compress, str(target))

    tmp = folder / f".{target.name}.{uuid.uuid4().hex[:12]}.tmp"
    try:
        ds.to_netcdf(tmp, engine="netcdf4", format="NETCDF4", encoding=encoding)
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    return target
