"""Figures of a served task: the field against its reference, its error over time, the drift of its invariants.

One figure per task (the ``figures`` export format, ``<task>.png``), drawn on
matplotlib's Agg canvas directly (no pyplot, no ``show``), so it works on
headless machines and touches no global state. From top to bottom:

* a red box when the task is incomplete ("INCOMPLETE: stopped at slice k of
  N (reason)") or carries warnings (the task file's ``latticedft_*``
  attributes);
* the field, in the style of Qin (2020):

  - 1D scalar ``psi(t)``: prediction as solid circles, reference as empty
    squares, against t (Figs 2-4);
  - 1D orbits ``psi(t, component)`` with 2+ components: the x-y plane,
    prediction in red, reference in blue (Figs 8-9);
  - 1+1D ``psi(t, x)``: space-time images of prediction, reference and
    error side by side;
  - 2+1D and 3+1D: snapshots at a few times (rows prediction / reference /
    error; 3+1D shows the middle slice of the extra dims);

  vector fields on 1+1D and higher lattices show their first component;
* the error over time, when a reference covers the task: max and RMS of
  ``psi - psi_ref`` per slice on a log scale, and the same for the baseline
  when the task file has ``baseline_err_max``/``baseline_err_rms``;
* the drift of the conserved quantities the task file holds (``invariant``,
  ``energy``, ``charge_<name>``: every series over time of these names), as
  ``|Q(t) - Q(0)| / |Q(0)|`` on a log scale.

Every axis and colour bar names its quantity and units, from the CF
attributes ``long_name`` and ``units`` of the arrays when present (units
``"1"`` read "dimensionless"). :func:`task_figure` builds the figure of a
task file (or of an export task) without saving it; :func:`plot_prediction`
draws and saves one from arrays.
"""

from __future__ import annotations

import json
import os
import textwrap
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import xarray as xr

from latticedft._errors import InputError
from latticedft.io._labels import coord_label as _label
from latticedft.io._labels import quantity_label
from latticedft.io._labels import units_text as _units_text
from latticedft.io.exporters import Exporter, ExportTask
from latticedft.io.fields import COMPONENT_DIM, lattice_dims

if TYPE_CHECKING:  # matplotlib is imported when a figure is drawn
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure, SubFigure

__all__ = ["plot_prediction", "task_figure", "save_figure", "FigureExporter", "DRIFT_SERIES"]

_MAX_MARKERS = 200  # markers drawn per 1D curve; more points are thinned
_WRAP = 110  # characters per line of the status box
#: Series of a task file drawn as conserved quantities: these names, and every name starting with ``charge_``.
DRIFT_SERIES = ("energy", "invariant")
_RED = "#b00000"


# ----------------------------------------------------------------------------- labels


def _quantity(da: xr.DataArray, variable: str, suffix: str = "") -> str:
    return quantity_label(da, variable, suffix, width=42)


def _error_label(variable: str, units: Any, what: str = "") -> str:
    return f"{what}|{variable} - {variable}_ref|{_units_text(units)}".strip()


# ----------------------------------------------------------------------------- helpers


def _coord(da: xr.DataArray, dim: str) -> np.ndarray:
    if dim in da.coords:
        return np.asarray(da.coords[dim].values, dtype=np.float64)
    return np.arange(da.sizes[dim], dtype=np.float64)


def _common(pred: xr.DataArray, ref: xr.DataArray) -> tuple[xr.DataArray, xr.DataArray]:
    """Cut both arrays to their common extent, position by position (pred's coords win)."""
    if set(lattice_dims(ref)) != set(lattice_dims(pred)) or (COMPONENT_DIM in pred.dims) != (COMPONENT_DIM in ref.dims):
        raise InputError(f"reference dims {ref.dims} do not match prediction dims {pred.dims}")
    ref = ref.transpose(*pred.dims)
    cut = {d: min(pred.sizes[d], ref.sizes[d]) for d in pred.dims}
    pred = pred.isel({d: slice(0, n) for d, n in cut.items()})
    ref = ref.isel({d: slice(0, n) for d, n in cut.items()})
    ref = ref.copy(data=ref.values)
    ref = ref.assign_coords({d: pred.coords[d] for d in pred.dims if d in pred.coords})
    return pred, ref


def _first_component(da: xr.DataArray) -> tuple[xr.DataArray, str]:
    if COMPONENT_DIM in da.dims:
        label = str(da.coords[COMPONENT_DIM].values[0]) if COMPONENT_DIM in da.coords else "0"
        return da.isel({COMPONENT_DIM: 0}), label
    return da, ""


def _markevery(n: int) -> int:
    return max(1, n // _MAX_MARKERS)


def _limits(*arrays: np.ndarray) -> tuple[float, float]:
    vals = np.concatenate([a[np.isfinite(a)].ravel() for a in arrays] + [np.zeros(0)])
    if vals.size == 0:
        return -1.0, 1.0
    lo, hi = float(vals.min()), float(vals.max())
    return (lo, hi) if hi > lo else (lo - 0.5, hi + 0.5)


def _err_limits(err: np.ndarray) -> tuple[float, float]:
    m = float(np.nanmax(np.abs(err))) if np.isfinite(err).any() else 0.0
    m = m if m > 0 else 1.0
    return -m, m


def _per_slice(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Max of ``|values|`` and RMS over everything but the first axis, ignoring NaN (NaN for an empty slice)."""
    flat = np.asarray(values, dtype=np.float64).reshape(values.shape[0], -1)
    finite = np.isfinite(flat)
    count = finite.sum(axis=1)
    worst = np.where(finite, np.abs(flat), -np.inf).max(axis=1, initial=-np.inf)
    squares = np.where(finite, flat, 0.0) ** 2
    rms = np.sqrt(squares.sum(axis=1) / np.maximum(count, 1))
    empty = count == 0
    worst[empty] = np.nan
    rms[empty] = np.nan
    return worst, rms


def _decade(ax: Axes) -> None:
    """Let a log axis span at least a decade around its curves (a near-constant curve otherwise fills it)."""
    values = [np.asarray(line.get_ydata(), dtype=np.float64) for line in ax.get_lines()]
    finite = np.concatenate([v[np.isfinite(v) & (v > 0)] for v in values] + [np.zeros(0)])
    if finite.size == 0:
        return
    lo, hi = float(finite.min()), float(finite.max())
    if hi / lo < 10:
        mid = np.sqrt(lo * hi)
        ax.set_ylim(mid / 10**0.5 / 1.5, mid * 10**0.5 * 1.5)


def _positive(values: np.ndarray) -> np.ndarray:
    """Values for a log axis: NaN where not positive."""
    v = np.asarray(values, dtype=np.float64)
    return np.where(v > 0, v, np.nan)


# ----------------------------------------------------------------------------- run status


class _Status:
    """What the task file's global attributes say about the run (all empty for plain arrays)."""

    def __init__(self, attrs: Mapping[str, Any], n_slices: int):
        complete = str(attrs.get("latticedft_complete", "")).strip().lower()
        self.incomplete = complete == "false"
        self.total = _as_int(attrs.get("latticedft_steps"))
        stopped = _as_int(attrs.get("latticedft_stopped_at_slice"))
        self.stopped_at = stopped if stopped is not None else (n_slices if self.incomplete else None)
        reason = attrs.get("latticedft_stop_reason")
        self.reason = " ".join(str(reason).split()) if reason not in (None, "") else None
        self.warnings = _warnings(attrs.get("latticedft_warnings"))

    def lines(self) -> list[str]:
        out = []
        if self.incomplete:
            msg = f"INCOMPLETE: stopped at slice {self.stopped_at}"
            if self.total is not None:
                msg += f" of {self.total}"
            if self.reason:
                msg += f" ({self.reason})"
            out.append(msg)
        out += [f"WARNING: {w}" for w in self.warnings]
        return [seg for line in out for seg in textwrap.wrap(line, _WRAP, subsequent_indent="    ")]


def _as_int(value: Any) -> int | None:
    try:
        return int(value) if value not in (None, "") else None
    except (TypeError, ValueError):
        return None


def _warnings(value: Any) -> list[str]:
    """The ``latticedft_warnings`` attribute (a JSON list of one-line strings) as a list."""
    if value in (None, ""):
        return []
    if isinstance(value, str):
        try:
            value = json.loads(value)
        except ValueError:
            return [" ".join(value.split())]
    if isinstance(value, (list, tuple, np.ndarray)):
        return [" ".join(str(w).split()) for w in value if str(w).strip()]
    return [" ".join(str(value).split())]


def _stop_span(pred: xr.DataArray, status: _Status) -> tuple[float, float] | None:
    """(last served time, time the task asked for) when it stopped early and both are known."""
    if not status.incomplete or status.total is None:
        return None
    tdim = lattice_dims(pred)[0]
    t = _coord(pred, tdim)
    if t.size < 2 or status.total <= t.size:
        return None
    return float(t[-1]), float(t[0] + (t[1] - t[0]) * (status.total - 1))


def _mark_unserved(ax: Axes, span: tuple[float, float] | None, vertical: bool) -> None:
    """Hatch the part of the time axis the task did not reach."""
    if span is None:
        return
    lo, hi = span
    kw: dict[str, Any] = {"facecolor": "none", "edgecolor": _RED, "hatch": "//", "alpha": 0.35, "lw": 0}
    if vertical:
        ax.axhspan(lo, hi, **kw)
        ax.set_ylim(top=hi)
        ax.text(0.5, (lo + hi) / 2, "not served", transform=ax.get_yaxis_transform(), ha="center", color=_RED)
    else:
        ax.axvspan(lo, hi, **kw)
        ax.set_xlim(right=hi)
        ax.text((lo + hi) / 2, 0.5, "not served", transform=ax.get_xaxis_transform(), ha="center", color=_RED)


# ----------------------------------------------------------------------------- field panels


def _plot_series(
    sf: Figure | SubFigure,
    pred: xr.DataArray,
    ref: xr.DataArray | None,
    train: Sequence[xr.DataArray],
    span: tuple[float, float] | None,
) -> None:
    tdim = lattice_dims(pred)[0]
    var = str(pred.name or "psi")
    if COMPONENT_DIM in pred.dims:
        comps = [pred.isel({COMPONENT_DIM: k}) for k in range(pred.sizes[COMPONENT_DIM])]
        labels = (
            [str(v) for v in pred.coords[COMPONENT_DIM].values]
            if COMPONENT_DIM in pred.coords
            else [str(k) for k in range(len(comps))]
        )
        ylabels = [_quantity(pred, var, f"_{lab}") for lab in labels]
    else:
        comps, ylabels = [pred], [_quantity(pred, var)]
    axes = sf.subplots(len(comps), 1, sharex=True, squeeze=False)[:, 0]
    for k, ax in enumerate(axes):
        for j, tr in enumerate(train):
            trk = tr.isel({COMPONENT_DIM: k}) if COMPONENT_DIM in tr.dims else tr
            ax.plot(
                _coord(tr, lattice_dims(tr)[0]),
                trk.values,
                "-",
                color="0.7",
                lw=1,
                label="training data" if j == 0 else None,
            )
        t = _coord(pred, tdim)
        if ref is not None:
            refk = ref.isel({COMPONENT_DIM: k}) if COMPONENT_DIM in ref.dims else ref
            ax.plot(
                _coord(ref, tdim),
                refk.values,
                "s",
                mfc="none",
                mec="tab:blue",
                ms=6,
                markevery=_markevery(t.size),
                label="reference",
            )
        ax.plot(t, comps[k].values, "o", color="tab:red", ms=3.5, markevery=_markevery(t.size), label="prediction")
        ax.set_ylabel(ylabels[k])
        _mark_unserved(ax, span, vertical=False)
        ax.legend(loc="best", fontsize="small")
    axes[-1].set_xlabel(_label(pred, tdim))


def _plot_orbit(ax: Axes, pred: xr.DataArray, ref: xr.DataArray | None, train: Sequence[xr.DataArray]) -> None:
    var = str(pred.name or "psi")
    labels = [str(v) for v in pred.coords[COMPONENT_DIM].values[:2]] if COMPONENT_DIM in pred.coords else ["x", "y"]
    for j, tr in enumerate(train):
        v = np.asarray(tr.values)
        ax.plot(v[:, 0], v[:, 1], "-", color="0.7", lw=1, label="training data" if j == 0 else None)
    if ref is not None:
        v = np.asarray(ref.values)
        ax.plot(
            v[:, 0], v[:, 1], "s", mfc="none", mec="tab:blue", ms=5, markevery=_markevery(len(v)), label="reference"
        )
    v = np.asarray(pred.values)
    ax.plot(v[:, 0], v[:, 1], "o", color="tab:red", ms=3, markevery=_markevery(len(v)), label="prediction")
    ax.set_xlabel(_quantity(pred, var, f"_{labels[0]}"))
    ax.set_ylabel(_quantity(pred, var, f"_{labels[1]}"))
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best", fontsize="small")


def _plot_spacetime(
    sf: Figure | SubFigure,
    pred: xr.DataArray,
    ref: xr.DataArray | None,
    span: tuple[float, float] | None,
    suffix: str,
) -> None:
    tdim, xdim = lattice_dims(pred)
    var = str(pred.name or "psi")
    t, x = _coord(pred, tdim), _coord(pred, xdim)
    extent = (x[0], x[-1], t[0], t[-1])
    value_label = _quantity(pred, var, suffix)
    panels = [("prediction", pred.values, value_label)]
    if ref is not None:
        err_label = f"{var}{suffix} - {var}{suffix}_ref" + _units_text(pred.attrs.get("units"))
        panels += [("reference", ref.values, value_label), ("error", pred.values - ref.values, err_label)]
    axes = sf.subplots(1, len(panels), sharey=True, squeeze=False)[0]
    vlim = _limits(*(p for _, p, _ in panels[:2]))
    for ax, (name, img, cb_label) in zip(axes, panels):
        is_err = name == "error"
        lo, hi = _err_limits(img) if is_err else vlim
        im = ax.imshow(
            img,
            origin="lower",
            aspect="auto",
            extent=extent,
            vmin=lo,
            vmax=hi,
            cmap="RdBu_r" if is_err else "viridis",
            interpolation="nearest",
        )
        sf.colorbar(im, ax=ax, label=cb_label)
        ax.set_title(name)
        ax.set_xlabel(_label(pred, xdim))
        _mark_unserved(ax, span, vertical=True)
    axes[0].set_ylabel(_label(pred, tdim))


def _plot_snapshots(
    sf: Figure | SubFigure, pred: xr.DataArray, ref: xr.DataArray | None, suffix: str, n_times: int = 3
) -> None:
    from matplotlib.ticker import MaxNLocator

    dims = lattice_dims(pred)
    var = str(pred.name or "psi")
    tdim, ydim, xdim = dims[0], dims[-2], dims[-1]
    middle = {d: pred.sizes[d] // 2 for d in dims[1:-2]}  # 3+1D: middle slice of extra dims
    where = ", ".join(f"{d} = {_coord(pred, d)[i]:.4g}" for d, i in middle.items())
    pred = pred.isel(middle)
    ref = ref.isel(middle) if ref is not None else None
    nt = pred.sizes[tdim]
    idx = np.unique(np.round(np.linspace(0, nt - 1, min(n_times, nt))).astype(int))
    value_label = quantity_label(pred, var, suffix, width=28)
    rows = [("prediction", pred, value_label)]
    if ref is not None:
        err_label = f"{var}{suffix} - {var}{suffix}_ref" + _units_text(pred.attrs.get("units"))
        rows += [("reference", ref, value_label), ("error", pred - ref, "\n".join(textwrap.wrap(err_label, 28)))]
    x, y = _coord(pred, xdim), _coord(pred, ydim)
    extent = (x[0], x[-1], y[0], y[-1])
    t = _coord(pred, tdim)
    axes = sf.subplots(len(rows), len(idx), squeeze=False, sharex=True, sharey=True)
    vlim = _limits(*(np.asarray(r.isel({tdim: idx}).values) for _, r, _ in rows[:2]))
    for r, (name, da, cb_label) in enumerate(rows):
        is_err = name == "error"
        imgs = np.asarray(da.isel({tdim: idx}).values)
        lo, hi = _err_limits(imgs) if is_err else vlim
        for c, i in enumerate(idx):
            ax = axes[r, c]
            im = ax.imshow(
                imgs[c],
                origin="lower",
                extent=extent,
                vmin=lo,
                vmax=hi,
                cmap="RdBu_r" if is_err else "viridis",
                interpolation="nearest",
            )
            if r == 0:
                ax.set_title(f"{tdim} = {t[i]:.4g}" + (f"\n({where})" if where else ""))
            if c == 0:
                ax.set_ylabel(f"{name}\n{_label(pred, ydim)}")
            if r == len(rows) - 1:
                ax.set_xlabel(_label(pred, xdim))
                ax.xaxis.set_major_locator(MaxNLocator(nbins=4, prune="upper"))  # no clash between panels
        sf.colorbar(im, ax=list(axes[r]), shrink=0.9, pad=0.02, fraction=0.04, label=cb_label)


# ----------------------------------------------------------------------------- over time


def _plot_errors(
    ax: Axes,
    pred: xr.DataArray,
    err: xr.DataArray,
    series: Mapping[str, xr.DataArray],
    span: tuple[float, float] | None,
) -> None:
    tdim = lattice_dims(pred)[0]
    var = str(pred.name or "psi")
    units = pred.attrs.get("units", err.attrs.get("units"))
    t = _coord(pred, tdim)
    values = np.asarray(err.transpose(tdim, ...).values)
    worst, rms = _per_slice(values)
    one_site = values[0].size == 1  # psi(t): max and rms are the same number
    if one_site:
        ax.semilogy(t, _positive(worst), "-", color="tab:red", lw=1.5, label="learned L_d")
    else:
        ax.semilogy(t, _positive(worst), "-", color="tab:red", lw=1.5, label="learned L_d: max")
        ax.semilogy(t, _positive(rms), "--", color="tab:red", lw=1.2, label="learned L_d: rms")
    base_max, base_rms = series.get("baseline_err_max"), series.get("baseline_err_rms")
    if one_site and base_max is not None:
        base_rms = None
    if base_max is not None or base_rms is not None:
        ref_series = base_max if base_max is not None else base_rms
        assert ref_series is not None
        name = str(ref_series.attrs.get("baseline") or "baseline")
        name = name if "baseline" in name else f"{name} (baseline)"
        name = textwrap.shorten(name, 50, placeholder="...")
        if base_max is not None:
            ax.semilogy(
                _coord(base_max, tdim),
                _positive(base_max.values),
                "-",
                color="0.35",
                lw=1.2,
                label=name if one_site else f"{name}: max",
            )
        if base_rms is not None:
            ax.semilogy(
                _coord(base_rms, tdim), _positive(base_rms.values), "--", color="0.35", lw=1, label=f"{name}: rms"
            )
    if not np.isfinite(_positive(worst)).any():
        ax.text(0.5, 0.5, "error exactly zero", transform=ax.transAxes, ha="center")
    ax.set_xlabel(_label(pred, tdim))
    ax.set_ylabel(f"error {_error_label(var, units)}")
    ax.set_title("error against the reference, per slice")
    _decade(ax)
    _mark_unserved(ax, span, vertical=False)
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(loc="best", fontsize="small")


def drift_series(series: Mapping[str, xr.DataArray]) -> dict[str, xr.DataArray]:
    """The conserved quantities among a task's series: ``energy``, ``invariant`` and every ``charge_*``."""
    return {k: v for k, v in sorted(series.items()) if k in DRIFT_SERIES or k.startswith("charge_")}


def _plot_drift(
    ax: Axes, pred: xr.DataArray, series: Mapping[str, xr.DataArray], span: tuple[float, float] | None
) -> None:
    tdim = lattice_dims(pred)[0]
    absolute = []
    for k, (name, q) in enumerate(series.items()):
        values = np.asarray(q.values, dtype=np.float64)
        finite = values[np.isfinite(values)]
        if finite.size == 0:
            continue
        q0 = finite[0]
        scale = abs(q0)
        long_name = q.attrs.get("long_name")
        label = f"{long_name} ({name})" if long_name not in (None, "", name) else name
        if scale == 0 or np.max(np.abs(finite)) < 1e-300:
            scale, label = 1.0, f"{label} (absolute: Q(0) = 0)"
            absolute.append(name)
        drift = _positive(np.abs(values - q0) / scale)
        t = _coord(q, tdim) if tdim in q.dims else np.arange(values.size, dtype=np.float64)
        ax.semilogy(t, drift, "-", lw=1.3, color=f"C{k % 10}", label=textwrap.shorten(label, 60, placeholder="..."))
    ax.set_xlabel(_label(pred, tdim))
    ax.set_ylabel(
        "relative drift |Q(t) - Q(0)| / |Q(0)|" if not absolute or len(absolute) < len(series) else "|Q(t) - Q(0)|"
    )
    ax.set_title("conserved quantities: drift from the first slice")
    _decade(ax)
    _mark_unserved(ax, span, vertical=False)
    ax.grid(True, which="major", alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize="small")


# ----------------------------------------------------------------------------- the figure


def _build(
    pred: xr.DataArray,
    ref: xr.DataArray | None,
    err: xr.DataArray | None = None,
    *,
    series: Mapping[str, xr.DataArray] | None = None,
    attrs: Mapping[str, Any] | None = None,
    title: str | None = None,
    train: Sequence[xr.DataArray] | None = None,
) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

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
        subs.pop(0).text(
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
        _plot_errors(time_axes.pop(0), pred, err, series, span)
    if drift:
        _plot_drift(time_axes.pop(0), pred, drift, span)
    if title:
        fig.suptitle(title + (f" ({pred.name or 'psi'}{suffix} shown)" if suffix else ""), fontsize="large")
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
    skip = {variable, f"{variable}_ref", f"{variable}_err"}
    series = {str(k): v for k, v in ds.data_vars.items() if v.dims == (tdim,) and str(k) not in skip}
    name = str(ds.attrs.get("latticedft_task") or stem)
    return _build(pred, ref, err, series=series, attrs=ds.attrs, title=title or name, train=train)


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
