"""The kept slices of a task served with an output cadence, appended to ``.<task>.nc.part`` as they are served.

A task with ``every > 1`` appends each kept slice to a hidden netCDF file in the staging folder (an
unlimited time dim, one slice a chunk, synced after each slice), so that a run killed while serving leaves
the slices served so far in a readable file (until the next run clears the killed run's staging folder).
The case pipeline creates the file (:func:`latticedft._run.serve_task`); when the task is done,
:func:`complete_part` adds the task's other variables and attributes to it (the same variables and
attributes as a ``<task>.nc`` written whole, as for ``every = 1``) and renames it to ``<task>.nc``: each
kept slice is written once.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from ._atomic import fault

__all__ = ["PartFile", "complete_part", "part_path"]


def part_path(folder: Path, name: str) -> Path:
    """``folder/.<name>.nc.part``."""
    return Path(folder) / f".{name}.nc.part"


def _labels(nc: Any, dim: str, values: np.ndarray) -> Any:
    """The coordinate ``dim`` of string labels as ``write_field`` writes it: a CF character array
    (``dim, string<n>``, UTF-8)."""
    import netCDF4

    encoded = [str(v).encode("utf-8") for v in values.tolist()]
    width = max([1, *map(len, encoded)])
    if f"string{width}" not in nc.dimensions:
        nc.createDimension(f"string{width}", width)
    var = nc.createVariable(dim, "S1", (dim, f"string{width}"))
    var.set_auto_chartostring(False)
    var[:] = netCDF4.stringtochar(np.array(encoded, dtype=f"S{width}"))
    var.setncattr("_Encoding", "utf-8")
    return var


class PartFile:
    """``.<task>.nc.part``: the variable ``variable(t, ...)`` with ``t`` unlimited and ``slice(t)``, appended."""

    def __init__(self, folder: Path, name: str, variable: str, template: xr.DataArray, every: int):
        import netCDF4

        self.path = part_path(folder, name)
        self.variable = variable
        self.ds = netCDF4.Dataset(self.path, "w", format="NETCDF4")
        tdim = str(template.dims[0])
        t = np.asarray(template[tdim].values, dtype=np.float64)
        self.t0, self.dt = float(t[0]), float(t[1] - t[0])
        self.ds.createDimension(tdim, None)
        for d in template.dims[1:]:
            d = str(d)
            self.ds.createDimension(d, template.sizes[d])
            if d in template.coords:
                values = np.asarray(template[d].values)
                if values.dtype.kind in "UO":
                    var = _labels(self.ds, d, values)
                else:
                    var = self.ds.createVariable(d, "f8", (d,))
                    var[:] = values.astype(np.float64)
                var.setncatts({k: v for k, v in template[d].attrs.items() if isinstance(v, (str, int, float))})
        self.tvar = self.ds.createVariable(tdim, "f8", (tdim,))
        self.tvar.setncatts({k: v for k, v in template[tdim].attrs.items() if isinstance(v, (str, int, float))})
        self.svar = self.ds.createVariable("slice", "i8", (tdim,))
        self.svar.long_name = "time slice index"
        dims = tuple(str(d) for d in template.dims)
        self.var = self.ds.createVariable(  # compressed and filled as write_field writes a field
            variable,
            "f8",
            dims,
            chunksizes=(1, *template.shape[1:]),
            zlib=True,
            complevel=4,
            shuffle=True,
            fill_value=np.nan,
        )
        self.var.coordinates = "slice"
        self.ds.setncatts({"latticedft_every": int(every), "latticedft_complete": "false"})
        self.n = 0

    @classmethod
    def reopen(cls, folder: Path, name: str, variable: str, template: xr.DataArray, rows: int) -> PartFile:
        """The part file a killed run left, opened to append after its first ``rows`` slices (the slices it
        holds beyond them are written again, with the same values). OSError when it cannot be read, ValueError
        when it holds fewer slices."""
        import netCDF4

        self = cls.__new__(cls)
        self.path, self.variable = part_path(folder, name), variable
        self.ds = netCDF4.Dataset(self.path, "a")
        tdim = str(template.dims[0])
        t = np.asarray(template[tdim].values, dtype=np.float64)
        self.t0, self.dt = float(t[0]), float(t[1] - t[0])
        self.tvar, self.svar, self.var = (self.ds.variables[k] for k in (tdim, "slice", variable))
        held = self.ds.dimensions[tdim].size
        if held < rows:
            self.close()
            raise ValueError(f"holds {held} slices, the checkpoint {rows}")
        self.n = rows
        return self

    def rows(self) -> np.ndarray:
        """The slices appended so far (the first :attr:`n`), as written."""
        self.var.set_auto_mask(False)
        return np.asarray(self.var[: self.n], dtype=np.float64)

    def __call__(self, index: int, values: np.ndarray) -> None:
        """Append slice ``index`` and flush it to disk."""
        self.var[self.n] = values
        self.tvar[self.n] = self.t0 + self.dt * index
        self.svar[self.n] = index
        self.n += 1
        self.ds.sync()
        fault("slice", self.path)

    def close(self) -> None:
        if self.ds.isopen():
            self.ds.close()

    def remove(self) -> None:
        """Close and delete the part file."""
        self.close()
        self.path.unlink(missing_ok=True)


def complete_part(
    part: Path, target: Path, ds: xr.Dataset, encoding: Mapping[str, Mapping[str, Any]], variable: str
) -> Path:
    """Turn the closed part file ``part`` into ``target``: the file :func:`latticedft.io.write_field` would
    write for ``ds`` (prepared by :func:`latticedft.io.fields.prepared_dataset`, with its ``encoding``).

    ``ds[variable]``'s values are in the file already (the kept slices, appended as they were served): only
    the slices it lacks (the last slice of a task that stopped between two kept ones) are written, and its
    attributes. Every other variable, coordinate and attribute of ``ds`` is written as ``write_field`` writes
    it, and attributes the part file held beyond those of ``ds`` are removed. Then ``part`` is renamed to
    ``target``.
    """
    import netCDF4

    field = ds[variable]
    tdim = str(field.dims[0])
    with netCDF4.Dataset(part, "a") as nc:
        held = nc.variables["slice"][:].filled(-1) if nc.dimensions[tdim].size else np.empty(0, np.int64)
        want = np.asarray(field["slice"].values, dtype=np.int64)
        n = len(held)
        if n > len(want) or not np.array_equal(held, want[:n]):  # not the kept slices: written whole
            n = 0
        if n < len(want):
            nc.variables[variable][n:] = np.asarray(field.values[n:], dtype=np.float64)
        for name in [None, *nc.variables]:  # ds's attributes replace the part file's
            holder = nc if name is None else nc.variables[name]
            for key in holder.ncattrs():
                if key != "_FillValue":
                    holder.delncattr(key)
        coords = " ".join(str(c) for c in field.coords if c not in field.dims)
        nc.variables[variable].setncatts({**field.attrs, **({"coordinates": coords} if coords else {})})
    rest = ds.drop_vars(variable)
    rest.to_netcdf(part, mode="a", engine="netcdf4", encoding={k: dict(v) for k, v in encoding.items() if k in rest})
    os.replace(part, target)
    return target
