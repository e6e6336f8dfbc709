"""What a figure says about the run itself: incomplete runs, warnings, the unserved part of the time axis."""

from __future__ import annotations

import json
import textwrap
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
import xarray as xr

from latticedft.io._labels import unit_scale
from latticedft.io.fields import lattice_dims

if TYPE_CHECKING:  # matplotlib is imported when a figure is drawn
    from matplotlib.axes import Axes


_WRAP = 110  # characters per line of the status box


_RED = "#b00000"


def _coord(da: xr.DataArray, dim: str) -> np.ndarray:
    """The values of ``dim`` to draw: a coordinate in a scaled unit (``"58.14 days"``) in the plain unit
    (days: the axis label says ``[days]``, not ``[58.14 days]``); the indices without a coordinate."""
    if dim in da.coords:
        factor = unit_scale(da.coords[dim].attrs.get("units"))[0]
        return np.asarray(da.coords[dim].values, dtype=np.float64) * factor
    return np.arange(da.sizes[dim], dtype=np.float64)


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
