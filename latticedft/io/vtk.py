"""ParaView export of lattice fields: the ``paraview`` export format of a run.

pyvista writes the VTK XML frames; the ``.pvd`` collection that lists them
with their time values is a few lines of XML written here. Every frame
carries a one-value field-data array ``TimeValue``. Layouts:

* ``psi(t, x)``, ``psi(t, y, x)``, ``psi(t, z, y, x)`` (optionally with a
  trailing ``component`` dim): one RectilinearGrid ``stem_NNNN.vtr`` per
  written time step and ``stem.pvd``; for 1+1D also ``stem_spacetime.vtr``,
  one 2-D grid with x along VTK x and t along VTK y.
* ``psi(t)`` and ``psi(t, component)`` (time series, orbits): polylines.
  ``stem.vtp`` holds the whole curve; ``stem.pvd`` lists frames
  ``stem_NNNN.vtp`` whose frame for step ``i`` is the curve up to step ``i``.
  A vector field with 2 or 3 components is drawn in its own space (points
  ``(x, y[, z])``); a scalar one as the graph ``(t, psi, 0)``.

This is the default ParaView export: plain VTK XML files that every ParaView
version reads. The XDMF/HDF5 time series (two files per task whatever the
number of frames) is the separate format ``xdmf`` (:mod:`latticedft.io.xdmf`).
"""

from __future__ import annotations

import os
import uuid
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
import pyvista as pv
import xarray as xr

from latticedft._atomic import write_text_atomic
from latticedft._errors import InputError
from latticedft.io.exporters import Exporter, ExportTask
from latticedft.io.fields import COMPONENT_DIM, lattice_dims, validate_field
from latticedft.io.pvview import write_view_script

__all__ = ["write_paraview", "read_pvd", "write_pvd", "DEFAULT_MAX_POLYLINE_FRAMES", "ParaViewExporter"]

#: Frames written for a polyline time series when ``max_frames`` is None.
#: Frame ``i`` holds ``i + 1`` points, so the total size grows like frames x steps.
DEFAULT_MAX_POLYLINE_FRAMES = 500


# ----------------------------------------------------------------------------- .pvd


def write_pvd(path: str | os.PathLike[str], entries: Sequence[tuple[float, str | os.PathLike[str]]]) -> Path:
    """Write a ParaView collection file listing ``(time, file)`` entries.

    File names are stored relative to the ``.pvd``'s folder when they lie
    inside it. The file is written atomically (temporary file, then rename).

    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     p = write_pvd(f"{d}/a.pvd", [(0.0, f"{d}/a_0000.vtr"), (0.5, f"{d}/a_0001.vtr")])
    ...     [(t, f.name) for t, f in read_pvd(p)]
    [(0.0, 'a_0000.vtr'), (0.5, 'a_0001.vtr')]
    """
    target = Path(path)
    lines = [
        '<?xml version="1.0"?>',
        '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
        "  <Collection>",
    ]
    for t, f in entries:
        f = Path(f)
        try:
            rel = f.resolve().relative_to(target.parent.resolve()).as_posix()
        except ValueError:
            rel = f.as_posix()
        lines.append(f'    <DataSet timestep="{float(t)!r}" group="" part="0" file={quoteattr(rel)}/>')
    lines += ["  </Collection>", "</VTKFile>", ""]
    write_text_atomic(target, "\n".join(lines))
    return target


def read_pvd(path: str | os.PathLike[str]) -> list[tuple[float, Path]]:
    """Read a ``.pvd`` collection: ``[(time, absolute file path), ...]`` in file order.

    Raises
    ------
    InputError
        Missing file, malformed XML, or a ``DataSet`` entry without
        ``timestep``/``file``.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: file not found; expected a ParaView .pvd collection")
    try:
        root = ET.parse(p).getroot()
    except ET.ParseError as exc:
        raise InputError(f"{p}: not valid XML ({exc}); expected a ParaView .pvd collection") from None
    coll = root.find("Collection")
    if root.tag != "VTKFile" or coll is None:
        raise InputError(f"{p}: no VTKFile/Collection element; expected a ParaView .pvd collection")
    out = []
    for i, ds in enumerate(coll.findall("DataSet")):
        try:
            t = float(ds.attrib.get("timestep", "0"))
            f = ds.attrib["file"]
        except (KeyError, ValueError):
            raise InputError(f"{p}: DataSet entry {i} lacks a numeric 'timestep' or a 'file' attribute") from None
        out.append((t, (p.parent / f).resolve()))
    return out


def _save(mesh: pv.DataSet, target: Path) -> Path:
    """Save a pyvista mesh atomically (pyvista infers the writer from the suffix)."""
    tmp = target.parent / f".{target.stem}.{uuid.uuid4().hex[:12]}{target.suffix}"
    try:
        mesh.save(tmp, binary=True)
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return target


# ----------------------------------------------------------------------------- helpers


def _frame_indices(nt: int, max_frames: int | None, default: int | None = None) -> np.ndarray:
    """Time indices to write: all, or at most ``max_frames`` evenly spread (first and last kept)."""
    limit = default if max_frames is None else max_frames
    if limit is None or limit >= nt:
        return np.arange(nt)
    if limit == 1:
        return np.array([nt - 1])
    return np.unique(np.round(np.linspace(0, nt - 1, limit)).astype(int))


def _point_values(da: xr.DataArray, order: tuple[str, ...]) -> np.ndarray:
    """Values transposed to ``order`` (+ component) as float64."""
    dims = order + ((COMPONENT_DIM,) if COMPONENT_DIM in da.dims else ())
    return np.asarray(da.transpose(*dims).values, dtype=np.float64)


def _checked_field(stem: str, field: xr.DataArray, max_frames: int | None) -> tuple[str, xr.DataArray, tuple[str, ...]]:
    """The arguments every time-series export shares, checked: (the field's name, the field, its lattice dims)."""
    if not stem or "/" in stem or os.sep in stem:
        raise InputError(f"stem {stem!r}: expected a plain file name stem without folders")
    if max_frames is not None and (not isinstance(max_frames, (int, np.integer)) or max_frames < 1):
        raise InputError(f"max_frames={max_frames!r}: expected a positive integer or None")
    name = str(field.name) if field.name is not None else "psi"
    field = validate_field(field, f"field {name!r}", allow_nan=True)
    return name, field, lattice_dims(field)


def _point_arrays(
    name: str,
    field: xr.DataArray,
    ldims: tuple[str, ...],
    extra: Mapping[str, xr.DataArray] | None,
    reserved: tuple[str, ...] = (),
) -> dict[str, np.ndarray]:
    """The field and the arrays beside it as point values in lattice order (names unique, not ``reserved``)."""
    arrays = {name: _point_values(field, ldims)}
    for key, arr in (extra or {}).items():
        if key in arrays or key in reserved:
            raise InputError(f"extra array {key!r}: name clashes with another array")
        arrays[key] = _check_extra(key, arr, field, ldims)
    return arrays


def _check_extra(name: str, arr: xr.DataArray, field: xr.DataArray, ldims: tuple[str, ...]) -> np.ndarray:
    if not isinstance(arr, xr.DataArray):
        raise InputError(f"extra array {name!r}: expected an xarray.DataArray, got {type(arr).__name__}")
    if set(lattice_dims(arr)) != set(ldims):
        raise InputError(f"extra array {name!r}: lattice dims {lattice_dims(arr)} differ from the field's {ldims}")
    shape = tuple(arr.sizes[d] for d in ldims)
    want = tuple(field.sizes[d] for d in ldims)
    if shape != want:
        raise InputError(f"extra array {name!r}: shape {shape} along {ldims} differs from the field's {want}")
    return _point_values(arr, ldims)


def _flat(values: np.ndarray, n_lattice: int) -> np.ndarray:
    """C-order flatten of the lattice part; components (if any) stay as columns."""
    if values.ndim == n_lattice:
        return values.reshape(-1)
    return values.reshape(-1, values.shape[-1])


# ----------------------------------------------------------------------------- writers


class ParaViewExporter(Exporter):
    name = "paraview"
    summary = (
        "<task>.pvd + one .vtr (lattice) or .vtp (1D) frame per written slice, at most max_frames; "
        "1+1D also <task>_spacetime.vtr, 1D also <task>.vtp; <task>_view.py, a pvpython script that shows them"
    )

    def write(self, task: ExportTask) -> list[Path]:
        files = write_paraview(task.folder, task.name, task.field, task.extra, max_frames=task.max_frames)
        return files + [
            write_view_script(
                task.folder, task.name, task.field, has_reference=task.reference is not None and task.error is not None
            )
        ]


def write_paraview(
    folder: str | os.PathLike[str],
    stem: str,
    field: xr.DataArray,
    extra: Mapping[str, xr.DataArray] | None = None,
    *,
    max_frames: int | None = None,
) -> list[Path]:
    """Export a field (and arrays beside it) for ParaView.

    Parameters
    ----------
    folder
        Output folder (created if missing).
    stem
        Base name of the files, e.g. the serving task's name.
    field
        A lattice field (``psi(t)``, ``psi(t, x)`` ... ``psi(t, z, y, x)``,
        optionally with a trailing ``component`` dim); stored as point data named
        after ``field.name`` (``"psi"`` if unnamed). NaN values are allowed.
    extra
        More arrays on the same lattice, e.g. ``{"psi_ref": ref,
        "psi_err": err}``, stored as point data under their keys.
    max_frames
        Write at most this many frames, evenly spread over time (first and
        last kept). None: every time step for lattice frames, at most
        :data:`DEFAULT_MAX_POLYLINE_FRAMES` for polyline frames.

    Returns
    -------
    list of pathlib.Path
        The files written: the ``.pvd`` first, then its frames, then the
        ``_spacetime.vtr`` (1+1D) or the whole-curve ``.vtp`` (1D).

    Raises
    ------
    InputError
        A field that breaks the layout, more than 3 spatial dims, a 1D
        vector field with other than 2 or 3 components, or extra arrays on
        another lattice.

    Examples
    --------
    >>> import tempfile, numpy as np, xarray as xr
    >>> t, x = np.linspace(0, 1, 3), np.linspace(0, 2, 5)
    >>> da = xr.DataArray(np.outer(t, x), dims=["t", "x"], coords={"t": t, "x": x})
    >>> with tempfile.TemporaryDirectory() as d:
    ...     [p.name for p in write_paraview(d, "wave", da)]
    ['wave.pvd', 'wave_0000.vtr', 'wave_0001.vtr', 'wave_0002.vtr', 'wave_spacetime.vtr']
    """
    name, field, ldims = _checked_field(stem, field, max_frames)
    arrays = _point_arrays(name, field, ldims, extra, reserved=("time", "TimeValue"))
    times = np.asarray(field.coords[ldims[0]].values, dtype=np.float64)
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    if len(ldims) == 1:
        return _write_polylines(out, stem, name, arrays, times, max_frames)
    if len(ldims) > 4:
        raise InputError(
            f"field {name!r}: {len(ldims) - 1} spatial dims {ldims[1:]}; ParaView export supports at most 3"
        )
    coords = [np.asarray(field.coords[d].values, dtype=np.float64) for d in ldims[1:]]
    return _write_grids(out, stem, arrays, times, coords, max_frames)


def _write_grids(
    out: Path,
    stem: str,
    arrays: dict[str, np.ndarray],
    times: np.ndarray,
    coords: list[np.ndarray],
    max_frames: int | None,
) -> list[Path]:
    n_spatial = len(coords)
    # VTK x is the last (fastest) lattice dim: psi(t, z, y, x) flattens to VTK point order.
    axes = list(reversed(coords)) + [np.zeros(1)] * (3 - n_spatial)
    nt = times.size
    width = max(4, len(str(nt - 1)))
    frames: list[tuple[float, Path]] = []
    for i in _frame_indices(nt, max_frames):
        grid = pv.RectilinearGrid(*axes)
        for key, vals in arrays.items():
            grid.point_data[key] = _flat(vals[i], n_spatial)
        grid.field_data["TimeValue"] = np.array([times[i]])
        frames.append((float(times[i]), _save(grid, out / f"{stem}_{i:0{width}d}.vtr")))
    written = [write_pvd(out / f"{stem}.pvd", frames)] + [f for _, f in frames]
    if n_spatial == 1:
        grid = pv.RectilinearGrid(coords[0], times, np.zeros(1))
        for key, vals in arrays.items():
            grid.point_data[key] = _flat(vals, 2)
        written.append(_save(grid, out / f"{stem}_spacetime.vtr"))
    return written


def _polyline(points: np.ndarray) -> pv.PolyData:
    n = len(points)
    if n >= 2:
        return pv.PolyData(points, lines=np.concatenate([[n], np.arange(n)]))
    if n == 1:
        return pv.PolyData(points)  # one vertex cell
    return pv.PolyData()


def _write_polylines(
    out: Path, stem: str, name: str, arrays: dict[str, np.ndarray], times: np.ndarray, max_frames: int | None
) -> list[Path]:
    vals = arrays[name]
    if vals.ndim == 2 and vals.shape[1] == 1:
        vals = vals[:, 0]
    if vals.ndim == 1:
        points = np.column_stack([times, vals, np.zeros_like(times)])
    elif vals.shape[1] in (2, 3):
        points = np.column_stack([vals, np.zeros((len(vals), 3 - vals.shape[1]))])
    else:
        raise InputError(
            f"field {name!r}: {vals.shape[1]} components; polyline export supports a scalar "
            f"or 2 to 3 components (drawn as points x, y[, z])"
        )
    keep = np.all(np.isfinite(points), axis=1)
    point_data = {"time": times[keep]}
    point_data.update({k: v[keep] for k, v in arrays.items()})
    points = points[keep]
    kept_index = np.flatnonzero(keep)

    def mesh(n: int) -> pv.PolyData:
        pd = _polyline(points[:n])
        if n:
            for key, v in point_data.items():
                pd.point_data[key] = v[:n]
        return pd

    written: list[Path] = []
    nt = times.size
    width = max(4, len(str(nt - 1)))
    frames: list[tuple[float, Path]] = []
    for i in _frame_indices(nt, max_frames, DEFAULT_MAX_POLYLINE_FRAMES):
        n = int(np.searchsorted(kept_index, i, side="right"))  # kept points with index <= i
        pd = mesh(n)
        pd.field_data["TimeValue"] = np.array([times[i]])
        frames.append((float(times[i]), _save(pd, out / f"{stem}_{i:0{width}d}.vtp")))
    written.append(write_pvd(out / f"{stem}.pvd", frames))
    written += [f for _, f in frames]
    written.append(_save(mesh(len(points)), out / f"{stem}.vtp"))
    return written
