"""XDMF/HDF5 time series of lattice fields, written with meshio: ``[export] formats = ["xdmf"]``.

Two files per task, whatever the number of time steps: ``<task>.xdmf`` (a small
XML index, XDMF 3: the lattice once, then one entry per written time step with
its time) and ``<task>.h5`` (the arrays). XDMF readers open the ``.xdmf``:
ParaView (its temporal collection is the block ``TimeSeries_meshio``; the
block ``mesh`` is the bare lattice), VisIt, VTK/pyvista;
:func:`read_xdmf` and ``meshio.xdmf.TimeSeriesReader`` read it back. Two files
instead of one per frame suit large lattices and long runs.

The mesh is the spatial lattice: a line of points (1+1D, cells ``line``), a
grid (2+1D, ``quad``) or a block (3+1D, ``hexahedron``), with VTK x along the
last lattice dim as in :mod:`latticedft.io.vtk`; a 1D field ``psi(t)`` lives
on one point (cell ``vertex``). Each time step carries the field and the
arrays beside it (``psi_ref``, ``psi_err``) as point data in double
precision, NaN where the task stopped early. A vector field is written one
scalar array per component, ``<name>_<label>`` (``psi_x``, ``psi_y``).

>>> import tempfile, numpy as np, xarray as xr
>>> t, x = np.linspace(0, 1, 3), np.linspace(0, 2, 5)
>>> da = xr.DataArray(np.outer(t, x), dims=["t", "x"], coords={"t": t, "x": x}, name="psi")
>>> with tempfile.TemporaryDirectory() as d:
...     files = write_xdmf(d, "wave", da)
...     times, arrays = read_xdmf(files[0])
>>> [p.name for p in files], times.tolist(), arrays["psi"].shape
(['wave.xdmf', 'wave.h5'], [0.0, 0.5, 1.0], (3, 5))
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import xarray as xr

from latticedft._errors import InputError
from latticedft.io.exporters import Exporter, ExportTask
from latticedft.io.fields import COMPONENT_DIM
from latticedft.io.vtk import _checked_field, _frame_indices, _point_arrays

__all__ = ["write_xdmf", "read_xdmf", "XdmfExporter"]

_CELLS = {0: "vertex", 1: "line", 2: "quad", 3: "hexahedron"}


class XdmfExporter(Exporter):
    name = "xdmf"
    summary = "<task>.xdmf + <task>.h5: one XDMF/HDF5 time series (ParaView, VisIt), at most max_frames steps"

    def write(self, task: ExportTask) -> list[Path]:
        return write_xdmf(task.folder, task.name, task.field, task.extra, max_frames=task.max_frames)


def _lattice_mesh(coords: list[np.ndarray]) -> tuple[np.ndarray, str, np.ndarray]:
    """Points (x fastest, C order of the lattice dims), cell type and cells of the spatial lattice."""
    n = len(coords)
    if n == 0:
        return np.zeros((1, 3)), "vertex", np.zeros((1, 1), dtype=np.int64)
    grids = np.meshgrid(*coords, indexing="ij")  # lattice order: (z,) (y,) x
    xyz = [g.ravel() for g in reversed(grids)] + [np.zeros(grids[0].size)] * (3 - n)
    points = np.column_stack(xyz).astype(np.float64)
    idx = np.arange(points.shape[0], dtype=np.int64).reshape([c.size for c in coords])
    if n == 1:
        cells = np.column_stack([idx[:-1], idx[1:]])
    elif n == 2:
        cells = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], axis=-1).reshape(-1, 4)
    else:
        lo = [idx[:-1, :-1, :-1], idx[:-1, :-1, 1:], idx[:-1, 1:, 1:], idx[:-1, 1:, :-1]]
        hi = [idx[1:, :-1, :-1], idx[1:, :-1, 1:], idx[1:, 1:, 1:], idx[1:, 1:, :-1]]
        cells = np.stack(lo + hi, axis=-1).reshape(-1, 8)
    return points, _CELLS[n], cells


def _writer(path: Path):
    """meshio's time-series writer with two fixes (meshio 5.3): the ``.h5`` lies beside the ``.xdmf``
    (not in the working directory), and a ``Polyline`` topology states ``NodesPerElement="2"`` (without it
    ParaView 5.11's XDMF 3 reader aborts)."""
    import h5py
    import meshio

    class _Writer(meshio.xdmf.TimeSeriesWriter):
        def __enter__(self):
            self.h5_filename = str(self.filename.with_suffix(".h5"))
            self.h5_file = h5py.File(self.h5_filename, "w")
            return self

        def cells(self, cells, grid):
            super().cells(cells, grid)
            for topo in grid.iter("Topology"):
                if topo.get("TopologyType") == "Polyline":
                    topo.set("NodesPerElement", "2")

    return _Writer(path)


def write_xdmf(
    folder: str | os.PathLike[str],
    stem: str,
    field: xr.DataArray,
    extra: Mapping[str, xr.DataArray] | None = None,
    *,
    max_frames: int | None = None,
) -> list[Path]:
    """Write ``<stem>.xdmf`` and ``<stem>.h5``: the field (and arrays beside it) as one time series.

    Parameters
    ----------
    folder
        Output folder (created if missing).
    stem
        Base name of the two files, e.g. the serving task's name.
    field
        A lattice field (``psi(t)``, ``psi(t, x)`` ... ``psi(t, z, y, x)``,
        optionally with a trailing ``component`` dim); stored under
        ``field.name`` (``"psi"`` if unnamed). NaN values are allowed.
    extra
        More arrays on the same lattice, e.g. ``{"psi_ref": ref, "psi_err": err}``.
    max_frames
        Write at most this many time steps, evenly spread (first and last
        kept); None writes every step.

    Returns
    -------
    list of pathlib.Path
        ``[<stem>.xdmf, <stem>.h5]``; both are replaced atomically.

    Raises
    ------
    InputError
        A field that breaks the layout, more than 3 spatial dims, or extra
        arrays on another lattice.
    """
    name, field, ldims = _checked_field(stem, field, max_frames)
    if len(ldims) > 4:
        raise InputError(f"field {name!r}: {len(ldims) - 1} spatial dims {ldims[1:]}; XDMF export supports at most 3")
    arrays = _point_arrays(name, field, ldims, extra)
    labels = (
        (
            [str(c) for c in field.coords[COMPONENT_DIM].values]
            if COMPONENT_DIM in field.coords
            else [str(i) for i in range(field.sizes[COMPONENT_DIM])]
        )
        if COMPONENT_DIM in field.dims
        else None
    )
    columns: dict[str, np.ndarray] = {}  # array name -> values (nt, n_points)
    nt = field.sizes[ldims[0]]
    for key, vals in arrays.items():
        flat = vals.reshape(nt, -1) if labels is None else vals.reshape(nt, -1, len(labels))
        parts = {key: flat} if labels is None else {f"{key}_{lab}": flat[..., k] for k, lab in enumerate(labels)}
        for part, v in parts.items():
            if part in columns:
                raise InputError(f"array {part!r}: name clashes with another array (component labels {labels})")
            columns[part] = v
    times = np.asarray(field.coords[ldims[0]].values, dtype=np.float64)
    coords = [np.asarray(field.coords[d].values, dtype=np.float64) for d in ldims[1:]]
    points, cell_type, cells = _lattice_mesh(coords)

    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / f".{stem}.xdmf-{uuid.uuid4().hex[:12]}"
    tmp.mkdir()
    try:
        with _writer(tmp / f"{stem}.xdmf") as w:
            w.write_points_cells(points, [(cell_type, cells)])
            for i in _frame_indices(nt, max_frames):
                w.write_data(float(times[i]), point_data={k: np.ascontiguousarray(v[i]) for k, v in columns.items()})
        written = []
        for suffix in (".h5", ".xdmf"):  # the index last: it names the arrays file
            target = out / f"{stem}{suffix}"
            os.replace(tmp / target.name, target)
            written.append(target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return written[::-1]


def read_xdmf(path: str | os.PathLike[str]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Read a time series written by :func:`write_xdmf`: ``(times, {name: values (steps, points)})``.

    Values are in the point order of the mesh (x fastest); reshape them to the
    lattice with the field's sizes.
    """
    import meshio

    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: file not found; expected an XDMF time series")
    times: list[float] = []
    steps: list[dict[str, np.ndarray]] = []
    try:
        with meshio.xdmf.TimeSeriesReader(p) as reader:
            reader.read_points_cells()
            for k in range(reader.num_steps):
                t, point_data, _ = reader.read_data(k)
                times.append(float(t))
                steps.append({key: np.asarray(v, dtype=np.float64) for key, v in point_data.items()})
    except (OSError, ValueError, KeyError, meshio.ReadError) as exc:
        raise InputError(f"{p}: not a readable XDMF time series ({type(exc).__name__}: {exc})") from None
    names = list(steps[0]) if steps else []
    return np.array(times), {key: np.stack([s[key] for s in steps]) for key in names}
