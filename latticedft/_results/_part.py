"""The kept slices of a task served with an output cadence, appended to ``.<task>.nc.part`` as they are served.

A task with ``every > 1`` appends each kept slice to a hidden netCDF file in the staging folder (an
unlimited time dim, one slice a chunk, synced after each slice), so that a run killed while serving leaves
the slices served so far in a readable file (until the next run clears the killed run's staging folder).
When the task is done its ``<task>.nc`` is written whole, as for ``every = 1`` (the same variables and
attributes), and the part file is removed.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from ._safety import _fault

__all__ = ["PartFile", "part_path"]


def part_path(folder: Path, name: str) -> Path:
    """``folder/.<name>.nc.part``."""
    return Path(folder) / f".{name}.nc.part"


class PartFile:
    """``.<task>.nc.part``: the variable ``variable(t, ...)`` with ``t`` unlimited and ``slice(t)``, appended."""

    def __init__(self, folder: Path, name: str, variable: str, template: xr.DataArray, every: int):
        import netCDF4

        self.path = part_path(folder, name)
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
                kind: Any = str if values.dtype.kind in "UO" else "f8"
                var = self.ds.createVariable(d, kind, (d,))
                var[:] = values.astype(object) if kind is str else values.astype(np.float64)
                var.setncatts({k: v for k, v in template[d].attrs.items() if isinstance(v, (str, int, float))})
        self.tvar = self.ds.createVariable(tdim, "f8", (tdim,))
        self.tvar.setncatts({k: v for k, v in template[tdim].attrs.items() if isinstance(v, (str, int, float))})
        self.svar = self.ds.createVariable("slice", "i8", (tdim,))
        self.svar.long_name = "time slice index"
        dims = tuple(str(d) for d in template.dims)
        self.var = self.ds.createVariable(variable, "f8", dims, chunksizes=(1, *template.shape[1:]))
        self.var.coordinates = "slice"
        self.ds.setncatts({"latticedft_every": int(every), "latticedft_complete": "false"})
        self.n = 0

    def __call__(self, index: int, values: np.ndarray) -> None:
        """Append slice ``index`` and flush it to disk."""
        self.var[self.n] = values
        self.tvar[self.n] = self.t0 + self.dt * index
        self.svar[self.n] = index
        self.n += 1
        self.ds.sync()
        _fault("slice", self.path)

    def close(self) -> None:
        if self.ds.isopen():
            self.ds.close()

    def remove(self) -> None:
        """Close and delete the part file (the task's whole file is written)."""
        self.close()
        self.path.unlink(missing_ok=True)
