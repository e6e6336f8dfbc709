"""A task's figure assembled from its panels, saved atomically; the ``figures`` export format."""

from __future__ import annotations

import json
import os
import textwrap
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import xarray as xr

from latticedft._errors import InputError
from latticedft.io.exporters import Exporter, ExportTask
from latticedft.io.fields import COMPONENT_DIM, lattice_dims

if TYPE_CHECKING:  # matplotlib is imported when a figure is drawn
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
from ._panels import (
    _common,
    _first_component,
    _plot_drift,
    _plot_errors,
    _plot_orbit,
    _plot_series,
    _plot_snapshots,
    _plot_spacetime,
    drift_series,
)
from ._status import _RED, _Status, _stop_span


def _aligned(
    pred: xr.DataArray, ref: xr.DataArray | None, err: xr.DataArray | None
) -> tuple[xr.DataArray, xr.DataArray | None, xr.DataArray | None, tuple[str, ...]]:
    """The prediction checked (components last), the reference on its lattice, the error to show (``pred -
    ref`` unless a matching one is given, in the prediction's units) and the lattice dims."""
    if not isinstance(pred, xr.DataArray):
        raise InputError(f"prediction: expected an xarray.DataArray, got {type(pred).__name__}")
    dims = lattice_dims(pred)
    if not dims:
        raise InputError(f"prediction dims {pred.dims}: expected at least a time dim")
    if COMPONENT_DIM in pred.dims and pred.dims[-1] != COMPONENT_DIM:
        pred = pred.transpose(..., COMPONENT_DIM)
    if ref is not None:
        pred, ref = _common(pred, ref)
    if err is not None and (err.dims != pred.dims or err.shape != pred.shape):
        err = None
    if err is None and ref is not None:
        err = pred - ref
    if err is not None:
        err = err.assign_attrs(units=pred.attrs.get("units", err.attrs.get("units")))
    return pred, ref, err, dims


def _status_box(sub: Any, lines: list[str]) -> None:
    """The status lines (INCOMPLETE, WARNING) in a red box across the top of the figure."""
    sub.text(
        0.5,
        0.5,
        "\n".join(lines),
        ha="center",
        va="center",
        color=_RED,
        fontsize="medium",
        fontweight="bold",
        bbox={"facecolor": "#fff0f0", "edgecolor": _RED, "boxstyle": "round,pad=0.4"},
    )


def _build(
    pred: xr.DataArray,
    ref: xr.DataArray | None,
    err: xr.DataArray | None = None,
    *,
    series: Mapping[str, xr.DataArray] | None = None,
    attrs: Mapping[str, Any] | None = None,
    title: str | None = None,
    train: Sequence[xr.DataArray] | None = None,
    spread: xr.DataArray | None = None,
) -> Figure:
    """The figure of one task: the layout, a straight sequence of panels in grid order; each panel's drawing
    lives in ``_panels``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    pred, ref, err, dims = _aligned(pred, ref, err)
    series = dict(series or {})
    status = _Status(attrs or {}, pred.sizes[dims[0]])
    span = _stop_span(pred, status)
    drift = drift_series(series)
    lines = status.lines()

    n_space = len(dims) - 1
    ncomp = pred.sizes.get(COMPONENT_DIM, 1)
    orbit = n_space == 0 and ncomp >= 2
    comp = _first_component(pred)[1] if n_space else ""
    suffix = f"_{comp}" if comp else ""
    if n_space == 0:
        width, top = (11.0, 5.6) if orbit else (10.0, 1.2 + 2.3 * ncomp)
    elif n_space == 1:
        width, top = (12.6 if ref is not None else 6.0), 3.9
    else:
        width, top = 11.0, 3.0 * (3 if ref is not None else 1) + 0.7
    n_time = int(err is not None) + int(bool(drift))  # panels over time
    # rows: the status box, the field, the panels over time (side by side; an orbit has them on its right)
    heights = [0.3 + 0.2 * len(lines)] if lines else []
    heights += [max(top, 2.6 * n_time) if orbit else top]
    heights += [3.1] if n_time and not orbit else []
    width = max(width, 9.0 if n_time == 2 else 6.0)
    fig = Figure(figsize=(width, sum(heights) + 0.4), layout="constrained")
    FigureCanvasAgg(fig)
    subs = list(fig.subfigures(len(heights), 1, height_ratios=heights, squeeze=False)[:, 0])
    if lines:
        _status_box(subs.pop(0), lines)
    field_fig = subs.pop(0)
    train = list(train or [])
    time_axes: list[Axes] = []
    if orbit:
        if n_time:
            left, right = field_fig.subfigures(1, 2, width_ratios=[1.0, 1.0])
            _plot_orbit(left.add_subplot(), pred, ref, train)
            time_axes = list(right.subplots(n_time, 1, squeeze=False)[:, 0])
        else:
            _plot_orbit(field_fig.add_subplot(), pred, ref, train)
    elif n_space == 0:
        _plot_series(field_fig, pred, ref, train, span)
    else:
        pred1 = _first_component(pred)[0]
        ref1 = _first_component(ref)[0] if ref is not None else None
        if n_space == 1:
            _plot_spacetime(field_fig, pred1, ref1, span, suffix)
        else:
            _plot_snapshots(field_fig, pred1, ref1, suffix)
    if n_time and not time_axes:
        time_axes = list(subs.pop(0).subplots(1, n_time, squeeze=False)[0])
    if err is not None:
        _plot_errors(time_axes.pop(0), pred, err, series, span, spread)
    if drift:
        _plot_drift(time_axes.pop(0), pred, drift, span)
    equation = str((attrs or {}).get("latticedft_L_d", ""))
    if title or equation:
        head = (title or "") + (f" ({pred.name or 'psi'}{suffix} shown)" if suffix and title else "")
        lines = ([head] if head else []) + textwrap.wrap(equation, 110)
        fig.suptitle("\n".join(lines), fontsize="large")
    return fig


def task_figure(
    source: ExportTask | xr.Dataset | str | os.PathLike[str],
    variable: str | None = None,
    *,
    title: str | None = None,
    train: Sequence[xr.DataArray] | None = None,
) -> Figure:
    """The figure of one served task, built and not saved.

    Parameters
    ----------
    source
        A task file ``<task>.nc`` (path or open Dataset) or an
        :class:`~latticedft.io.exporters.ExportTask`.
    variable
        The served field's name in the file; default: the case's variable
        recorded in the file, else ``psi``.
    title
        Figure title; default: the task's title or name.
    train
        Training fields drawn in grey behind 1D plots (an export task's own
        are used otherwise).

    Returns
    -------
    matplotlib.figure.Figure
        On an Agg canvas; ``fig.savefig(path)`` or :func:`save_figure` writes it.

    Examples
    --------
    >>> import numpy as np, xarray as xr
    >>> t = np.linspace(0, 6, 40)
    >>> ref = xr.DataArray(np.sin(t), dims=["t"], coords={"t": t}, name="psi")
    >>> ds = xr.Dataset({"psi": ref[:30] + 1e-3, "psi_ref": ref[:30]})
    >>> ds.attrs.update(latticedft_complete="false", latticedft_steps=40)
    >>> fig = task_figure(ds, title="oscillator")
    >>> any("INCOMPLETE: stopped at slice 30 of 40" in t.get_text() for t in fig.texts + fig.subfigs[0].texts)
    True
    """
    if isinstance(source, ExportTask):
        one_d = len(lattice_dims(source.field)) == 1
        return _build(
            source.field,
            source.reference,
            source.error,
            series=source.series,
            attrs=source.attrs,
            title=title or source.title or source.name,
            train=train if train is not None else (source.train if one_d else None),
            spread=source.spread,
        )
    if isinstance(source, xr.Dataset):
        return _from_dataset(source, variable, title, train, "<dataset>")
    path = Path(source)
    if not path.is_file():
        raise InputError(f"{path}: file not found; expected a task file <task>.nc")
    with xr.open_dataset(path, engine="netcdf4", decode_times=False) as ds:
        return _from_dataset(ds.load(), variable, title, train, path.stem)


def _from_dataset(
    ds: xr.Dataset, variable: str | None, title: str | None, train: Sequence[xr.DataArray] | None, stem: str
) -> Figure:
    if variable is None:
        try:
            variable = str(json.loads(str(ds.attrs.get("latticedft_config", "{}")))["field"]["variable"])
        except (ValueError, KeyError, TypeError):
            variable = "psi"
    if variable not in ds.data_vars:
        raise InputError(f"{stem}: no variable {variable!r} (variables: {', '.join(map(str, ds.data_vars))})")
    pred = ds[variable]
    tdim = pred.dims[0]
    ref = ds[f"{variable}_ref"] if f"{variable}_ref" in ds.data_vars else None
    err = ds[f"{variable}_err"] if f"{variable}_err" in ds.data_vars else None
    skip = {variable, f"{variable}_ref", f"{variable}_err", f"{variable}_mean", f"{variable}_std"}
    series = {str(k): v for k, v in ds.data_vars.items() if v.dims == (tdim,) and str(k) not in skip}
    name = str(ds.attrs.get("latticedft_task") or stem)
    spread = ds[f"{variable}_std"] if f"{variable}_std" in ds.data_vars else None
    return _build(pred, ref, err, series=series, attrs=ds.attrs, title=title or name, train=train, spread=spread)


def save_figure(fig: Figure, path: str | os.PathLike[str], *, dpi: int = 100) -> Path:
    """Save ``fig`` (PNG, PDF, SVG ... by suffix) atomically: a temporary file, then a rename."""
    target = Path(path)
    fmt = target.suffix.lstrip(".").lower() or "png"
    tmp = target.parent / f".{target.stem}.{uuid.uuid4().hex[:12]}.{fmt}"
    try:
        fig.savefig(tmp, format=fmt, dpi=dpi)
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return target


def plot_prediction(
    path: str | os.PathLike[str],
    pred: xr.DataArray,
    ref: xr.DataArray | None = None,
    *,
    title: str | None = None,
    train: Sequence[xr.DataArray] | None = None,
) -> Path:
    """Draw a prediction against its reference and save it (PNG, PDF, SVG ... by suffix).

    Parameters
    ----------
    path
        Output image; written atomically (temporary file, then rename).
    pred
        The served field (a lattice field; NaN where it stopped early).
    ref
        The reference on the same lattice, or None. When the lengths differ
        the common leading part is compared, and the error per slice is drawn
        below the field.
    title
        Figure title.
    train
        Training fields drawn in grey behind 1D plots (ignored otherwise).

    Returns
    -------
    pathlib.Path
        The image written.

    Examples
    --------
    >>> import tempfile, numpy as np, xarray as xr
    >>> t = np.linspace(0, 6, 40)
    >>> ref = xr.DataArray(np.sin(t), dims=["t"], coords={"t": t})
    >>> with tempfile.TemporaryDirectory() as d:
    ...     p = plot_prediction(f"{d}/f.png", ref + 1e-3, ref, title="oscillator")
    ...     p.stat().st_size > 0
    True
    """
    one_d = isinstance(pred, xr.DataArray) and len(lattice_dims(pred)) == 1
    fig = _build(pred, ref, title=title, train=train if one_d else None)
    return save_figure(fig, path)


class FigureExporter(Exporter):
    name = "figures"
    summary = (
        "<task>.png: the prediction against its reference, the error per slice (and the baseline's), "
        "the drift of the conserved quantities; a red box when the task stopped early or warned"
    )

    def write(self, task: ExportTask) -> list[Path]:
        return [save_figure(task_figure(task), task.folder / f"{task.name}.png")]
