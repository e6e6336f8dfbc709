"""Figures of a prediction against its reference, in the style of Qin (2020).

Figures are drawn on matplotlib's Agg canvas directly (no pyplot, no
``show``), so they work on headless machines and touch no global state.

* 1D scalar ``psi(t)``: prediction as solid circles, reference as empty
  squares, against t (Qin 2020, Figs 2-4).
* 1D orbits ``psi(t, component)`` with 2+ components: the x-y plane,
  prediction in red, reference in blue (Figs 8-9).
* 1+1D ``psi(t, x)``: space-time images of prediction, reference and error
  side by side, with colorbars.
* 2+1D and 3+1D: snapshots at a few times (rows prediction / reference /
  error; 3+1D shows the middle slice of the extra dims).

Vector fields on 1+1D and higher lattices show their first component.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import xarray as xr
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from latticedft._errors import InputError
from latticedft.io.exporters import Exporter, ExportTask
from latticedft.io.fields import COMPONENT_DIM, lattice_dims

__all__ = ["plot_prediction", "FigureExporter"]

_MAX_MARKERS = 200  # markers drawn per 1D curve; more points are thinned


def _label(da: xr.DataArray, dim: str) -> str:
    attrs = da.coords[dim].attrs if dim in da.coords else {}
    units = attrs.get("units")
    return f"{dim} [{units}]" if units else str(dim)


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
        return da.isel({COMPONENT_DIM: 0}), f" (component {label})"
    return da, ""


def _markevery(n: int) -> int:
    return max(1, n // _MAX_MARKERS)


def _plot_series(fig: Figure, pred: xr.DataArray, ref: xr.DataArray | None, train: Sequence[xr.DataArray]) -> None:
    tdim = lattice_dims(pred)[0]
    if COMPONENT_DIM in pred.dims:
        comps = [pred.isel({COMPONENT_DIM: k}) for k in range(pred.sizes[COMPONENT_DIM])]
        labels = (
            [str(v) for v in pred.coords[COMPONENT_DIM].values]
            if COMPONENT_DIM in pred.coords
            else [str(k) for k in range(len(comps))]
        )
    else:
        comps, labels = [pred], [str(pred.name or "psi")]
    axes = fig.subplots(len(comps), 1, sharex=True, squeeze=False)[:, 0]
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
        ax.set_ylabel(labels[k])
        ax.legend(loc="best", fontsize="small")
    axes[-1].set_xlabel(_label(pred, tdim))


def _plot_orbit(ax: Axes, pred: xr.DataArray, ref: xr.DataArray | None, train: Sequence[xr.DataArray]) -> None:
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
    ax.set_xlabel(labels[0])
    ax.set_ylabel(labels[1])
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best", fontsize="small")


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


def _plot_spacetime(fig: Figure, pred: xr.DataArray, ref: xr.DataArray | None) -> None:
    tdim, xdim = lattice_dims(pred)
    t, x = _coord(pred, tdim), _coord(pred, xdim)
    extent = (x[0], x[-1], t[0], t[-1])
    panels = [("prediction", pred.values)]
    if ref is not None:
        panels += [("reference", ref.values), ("error", pred.values - ref.values)]
    axes = fig.subplots(1, len(panels), sharey=True, squeeze=False)[0]
    vlim = _limits(*(p for _, p in panels[:2]))
    for ax, (name, img) in zip(axes, panels):
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
        fig.colorbar(im, ax=ax)
        ax.set_title(name)
        ax.set_xlabel(_label(pred, xdim))
    axes[0].set_ylabel(_label(pred, tdim))


def _plot_snapshots(fig: Figure, pred: xr.DataArray, ref: xr.DataArray | None, n_times: int = 3) -> None:
    dims = lattice_dims(pred)
    tdim, ydim, xdim = dims[0], dims[-2], dims[-1]
    middle = {d: pred.sizes[d] // 2 for d in dims[1:-2]}  # 3+1D: middle slice of extra dims
    pred = pred.isel(middle)
    ref = ref.isel(middle) if ref is not None else None
    nt = pred.sizes[tdim]
    idx = np.unique(np.round(np.linspace(0, nt - 1, min(n_times, nt))).astype(int))
    rows = [("prediction", pred)]
    if ref is not None:
        rows += [("reference", ref), ("error", pred - ref)]
    x, y = _coord(pred, xdim), _coord(pred, ydim)
    extent = (x[0], x[-1], y[0], y[-1])
    t = _coord(pred, tdim)
    axes = fig.subplots(len(rows), len(idx), squeeze=False, sharex=True, sharey=True)
    vlim = _limits(*(np.asarray(r.isel({tdim: idx}).values) for _, r in rows[:2]))
    for r, (name, da) in enumerate(rows):
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
                ax.set_title(f"{tdim} = {t[i]:.4g}")
            if c == 0:
                ax.set_ylabel(f"{name}\n{_label(pred, ydim)}")
            if r == len(rows) - 1:
                ax.set_xlabel(_label(pred, xdim))
        fig.colorbar(im, ax=list(axes[r]), shrink=0.9, pad=0.02, fraction=0.04)


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
        the common leading part is compared.
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
    if not isinstance(pred, xr.DataArray):
        raise InputError(f"prediction: expected an xarray.DataArray, got {type(pred).__name__}")
    dims = lattice_dims(pred)
    if not dims:
        raise InputError(f"prediction dims {pred.dims}: expected at least a time dim")
    if COMPONENT_DIM in pred.dims and pred.dims[-1] != COMPONENT_DIM:
        pred = pred.transpose(..., COMPONENT_DIM)
    if ref is not None:
        pred, ref = _common(pred, ref)
    train = list(train or [])
    target = Path(path)
    fmt = target.suffix.lstrip(".").lower() or "png"

    n_space = len(dims) - 1
    if n_space == 0:
        ncomp = pred.sizes.get(COMPONENT_DIM, 1)
        fig = Figure(figsize=(6.4, 4.8) if ncomp >= 2 else (7.0, 3.6), layout="constrained")
        if ncomp >= 2:
            _plot_orbit(fig.add_subplot(), pred, ref, train)
        else:
            _plot_series(fig, pred, ref, train)
    else:
        pred, suffix = _first_component(pred)
        if ref is not None:
            ref, _ = _first_component(ref)
        title = (title or "") + suffix if suffix else title
        if n_space == 1:
            fig = Figure(figsize=(4.2 * (3 if ref is not None else 1), 3.8), layout="constrained")
            _plot_spacetime(fig, pred, ref)
        else:
            nrows = 3 if ref is not None else 1
            # a fixed layout: constrained layout costs ~1 s for this many panels
            fig = Figure(figsize=(10.0, 3.0 * nrows + 0.6))
            fig.subplots_adjust(
                left=0.1,
                right=0.86,
                bottom=0.5 / (3.0 * nrows + 0.6) + 0.03,
                top=1 - 0.6 / (3.0 * nrows + 0.6),
                wspace=0.08,
                hspace=0.12,
            )
            _plot_snapshots(fig, pred, ref)
    if title:
        fig.suptitle(title)
    FigureCanvasAgg(fig)

    tmp = target.parent / f".{target.stem}.{uuid.uuid4().hex[:12]}.{fmt}"
    try:
        fig.savefig(tmp, format=fmt, dpi=100)
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return target


class FigureExporter(Exporter):
    name = "figures"
    summary = "<task>.png: the prediction against its reference (training fields behind 1D plots)"

    def write(self, task: ExportTask) -> list[Path]:
        one_d = len(lattice_dims(task.field)) == 1
        return [
            plot_prediction(
                task.folder / f"{task.name}.png",
                task.field,
                task.reference,
                title=task.title or task.name,
                train=task.train if one_d else None,
            )
        ]
