"""The panels of a task's figure: the field, its error per slice, the drift of invariants and charges."""

from __future__ import annotations

import textwrap
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import xarray as xr

from latticedft._errors import InputError
from latticedft.io._labels import coord_label, quantity_label
from latticedft.io._labels import units_text as _units_text
from latticedft.io.fields import COMPONENT_DIM, lattice_dims

if TYPE_CHECKING:  # matplotlib is imported when a figure is drawn
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure, SubFigure
from ._status import _coord, _mark_unserved

_MAX_MARKERS = 200  # markers drawn per 1D curve; more points are thinned


#: Series of a task file drawn as conserved quantities: these names, and every name starting with ``charge_``.
DRIFT_SERIES = ("energy", "invariant")


def _label(da: xr.DataArray, dim: str) -> str:
    """Axis label of a coordinate, in the units ``_coord`` draws it in."""
    return coord_label(da, dim, scaled=True)


def _quantity(da: xr.DataArray, variable: str, suffix: str = "") -> str:
    return quantity_label(da, variable, suffix, width=42)


def _set_ylabel(ax: Axes, text: str | Sequence[str]) -> None:
    """``text`` as the y label of ``ax``, in lines no longer than the axes is high (a longer label is cut off
    at the figure's edge): at most 6 points a character of a 10-point label. A string breaks at any space, a
    sequence only between its parts (``["error", "|psi - psi_ref|", "[au]"]``)."""
    width = max(16, int(ax.bbox.height / ax.figure.dpi * 72 / 6.0))
    lines: list[str] = []
    for part in text.split() if isinstance(text, str) else text:
        if lines and len(lines[-1]) + 1 + len(part) <= width:
            lines[-1] += " " + part
        else:
            lines.append(part)
    ax.set_ylabel("\n".join(lines))


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
        ylabels = [quantity_label(pred, var, f"_{lab}") for lab in labels]
    else:
        comps, ylabels = [pred], [quantity_label(pred, var)]
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
        _set_ylabel(ax, ylabels[k])
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
        if name != "reference":  # "not served" is said of the served field (and its error), not of the reference
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


def _plot_errors(
    ax: Axes,
    pred: xr.DataArray,
    err: xr.DataArray,
    series: Mapping[str, xr.DataArray],
    span: tuple[float, float] | None,
    spread: xr.DataArray | None = None,
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
    estimate = series.get(f"{var}_err_est")
    if spread is not None and spread.shape == pred.shape:
        calibrated = "calibrated" in str(spread.attrs.get("long_name", ""))
        _plot_band(ax, t, np.asarray(spread.transpose(*pred.dims).values), rms, calibrated=calibrated)
        _mark_stopped_members(ax, t, spread.attrs)
        _mark_stopped_members(ax, t, spread.attrs, "outside_members", "outside_from_slice", "leaves its range")
    elif estimate is not None and estimate.shape == (len(t),):
        _plot_band(ax, t, np.asarray(estimate.values), rms, label="calibrated error estimate")
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
    _set_ylabel(ax, ["error", f"|{var} - {var}_ref|", *_units_text(units).split()])
    ax.set_title("error against the reference, per slice")
    _decade(ax)
    _mark_unserved(ax, span, vertical=False)
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(loc="best", fontsize="small")


def _plot_band(
    ax: Axes, t: np.ndarray, std: np.ndarray, rms_error: np.ndarray, *, calibrated: bool = False, label: str = ""
) -> None:
    """An error bar: 2 and 3 times the RMS over sites of an ensemble's standard deviation (or of a single
    model's calibrated estimate, ``label``), per slice (the error it bounds is the RMS error over sites;
    docs/uncertainty.md)."""
    flat = std.reshape(std.shape[0], -1)
    s = np.full(flat.shape[0], np.nan)
    some = np.isfinite(flat).any(axis=1)  # slices the members did not all reach have no spread
    s[some] = np.sqrt(np.nanmean(flat[some] ** 2, axis=1))
    two, three = _positive(2 * s), _positive(3 * s)
    found = np.concatenate([v[np.isfinite(v)] for v in (two, _positive(rms_error))])
    if not found.size:
        return
    floor = float(found.min()) / 10
    ax.fill_between(t, floor, np.where(np.isfinite(three), three, floor), color="tab:blue", alpha=0.12, lw=0)
    ax.fill_between(t, floor, np.where(np.isfinite(two), two, floor), color="tab:blue", alpha=0.25, lw=0)
    what = label or ("ensemble (calibrated)" if calibrated else "ensemble")
    ax.semilogy(t, two, "-", color="tab:blue", lw=1, label=f"{what}: 2 std (3 std lighter), rms over sites")


def _mark_stopped_members(
    ax: Axes,
    t: np.ndarray,
    attrs: Mapping[str, Any],
    who_key: str = "stopped_members",
    at_key: str = "stopped_at_slice",
    what: str = "stops",
) -> None:
    """A dotted line where members of an ensemble stopped (the spread is over fewer members from there); with
    ``outside_members``/``outside_from_slice``, where members' fields leave their own training range."""
    members = np.atleast_1d(np.asarray(attrs.get(who_key, []), dtype=np.int64))
    at = np.atleast_1d(np.asarray(attrs.get(at_key, []), dtype=np.int64))
    stopped = at_key == "stopped_at_slice"
    for k, i in enumerate(sorted(set(int(i) for i in at if 0 <= i < len(t)))):
        who = ", ".join(str(int(m)) for m, j in zip(members, at, strict=False) if j == i)
        label = ("member(s) stopped" if stopped else "member(s) left their training range") if k == 0 else None
        ax.axvline(t[i], color="tab:blue" if stopped else "tab:orange", ls=":", lw=1, label=label)
        ax.annotate(
            f"member {who} {what}",
            (t[i], 0.02),
            xycoords=("data", "axes fraction"),
            fontsize="x-small",
            rotation=90,
            color="tab:blue" if stopped else "tab:orange",
            va="bottom",
        )


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
    relative = not absolute or len(absolute) < len(series)
    _set_ylabel(ax, ["relative drift", "|Q(t) - Q(0)| / |Q(0)|"] if relative else ["|Q(t) - Q(0)|"])
    ax.set_title("conserved quantities: drift from the first slice")
    _decade(ax)
    _mark_unserved(ax, span, vertical=False)
    ax.grid(True, which="major", alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize="small")
