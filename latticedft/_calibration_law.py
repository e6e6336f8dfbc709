"""The calibration law: its record (:class:`Calibration`, JSON-compatible), the error estimate and band it gives a
served task, and the warnings when a task lies beyond what it was measured on. :mod:`latticedft._calibrate`
measures it by held-out serving."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import xarray as xr

__all__ = [
    "CANDIDATES_FLOOR",
    "CANDIDATES_RATIO",
    "EXPONENT_RANGE",
    "LAW",
    "ORIGIN",
    "QUANTILE",
    "RANGE_MARGIN",
    "Calibration",
]

#: Twice the calibrated estimate covers this share of the held-out slices' errors.
QUANTILE = 0.95
#: A task whose served values leave the training fields' range by more than this share of its width is
#: outside the calibration's range.
RANGE_MARGIN = 0.05
#: A task on which the two best candidates' trials (the chosen one's and the runner-up's, served from the task's
#: start) disagree more than this many times as much as on the training fields (the median over the task's slices
#: within the windows of the ratio per slice) draws a warning (:meth:`Calibration.candidates_warning`): the task
#: lies where the training data do not pin the model down. Measured by ``python -m benchmarks.calibration``
#: (docs/uncertainty.md, "The candidates' check").
CANDIDATES_RATIO = 10.0
#: The training disagreement a task's is divided by is at least this (relative to the field's largest magnitude).
CANDIDATES_FLOOR = 1e-12
#: The law's time is the number of steps served, ``k - ORIGIN`` at slice ``k``: slice 1 is given (error 0), slice 2
#: the first step. In the slice index ``k`` itself the law put ``2^exponent`` on the first step and fitted a steeper
#: exponent to short windows (``klein-gordon-periodic``: 2.11 in ``k``, 1.73 in ``k - 1``, over 21 slices).
ORIGIN = 1.0
LAW = "err(k) = A * scale * (k - 1)^exponent (k: slice index, k - 1 the steps served, A: the field's largest magnitude)"
#: The growth exponent is kept in this interval (an error that shrinks with time is not extrapolated so).
EXPONENT_RANGE = (0.0, 3.0)


@dataclass
class Calibration:
    """A calibration law measured by held-out serving (see the module docstring); JSON-compatible by
    :meth:`to_dict`."""

    scale: float
    exponent: float
    quantile: float
    #: Training fields (windows) measured, held-out slices counted, the longest field served (slices).
    windows: int
    held_out_slices: int
    slices: int
    #: The training fields' value range.
    low: float
    high: float
    #: Over the held-out slices: the share whose error is within twice the estimate, and mean estimate over
    #: mean error (the chosen model's error alone).
    coverage: float
    std_over_error: float
    runner_up: str | None
    wall_time: float
    law: str = "err(k) = A * scale * k^exponent (k: slice index, A: the field's largest magnitude)"
    #: The law's time is ``k - origin``: 1 (the steps served from the second given slice) since it was measured
    #: so; 0 in a law recorded before (the slice index, as its ``law`` text says).
    origin: float = 0.0
    #: With an ensemble: the factor on its members' spread, the :data:`QUANTILE` quantile over the held-out
    #: slices of the trial's error over the spread on the same slice, halved (None without an ensemble).
    spread_scale: float | None = None
    #: With an ensemble: over the same held-out slices, the mean scaled spread over the mean error (the
    #: spread's :attr:`std_over_error`; None without a :attr:`spread_scale`).
    spread_std_over_error: float | None = None
    #: Why the law is degenerate (None when it is not): no held-out slice was served, so no scale was measured.
    #: Callers serve without a calibrated error bar and report a failed calibration.
    failed: str | None = None
    #: The training fields' amplitudes (the range of a field's values, largest less smallest), smallest and
    #: largest (None in a law recorded before them).
    span_low: float | None = None
    span_high: float | None = None
    #: With a runner-up trial measured: per slice ``k`` of the longest training field, the largest over the
    #: training fields of the two trials' disagreement (RMS over the lattice of the difference of the runner-up's
    #: trial and the chosen one's, served from the same start, over the field's largest magnitude; None where
    #: neither was served). None without a runner-up, or in a law recorded before it.
    candidates: list[float | None] | None = None
    #: The chosen candidate's label (with a runner-up trial measured; None otherwise).
    chosen: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Calibration:
        return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d})

    def estimate(self, k: np.ndarray, amplitude: float) -> np.ndarray:
        """The error estimate (RMS over the lattice, 1 std) at slice indices ``k``; 0 on the two given slices."""
        kk = np.asarray(k, dtype=np.float64)
        est = amplitude * self.scale * np.maximum(kk - self.origin, 1.0) ** self.exponent
        return np.where(kk < 2, 0.0, est)

    def band(self, std: xr.DataArray, est: np.ndarray, other: np.ndarray | None = None) -> xr.DataArray:
        """An ensemble's calibrated ``psi_std``: its members' standard deviation times :attr:`spread_scale`,
        widened at every site of a slice by the factor that brings its RMS over the lattice up to the floor
        where it is narrower (a slice whose members agree exactly gets the floor at every site). With a
        :attr:`spread_scale` the scaled spread takes the law's place: the floor is ``other``, the trial's
        disagreement per slice (none when None); without one (a law recorded before it), the spread is taken
        as it is and the floor is the estimate ``est``. The band's RMS is the larger of spread and floor."""
        if self.spread_scale is None:
            floor = np.asarray(est, dtype=np.float64)
        else:
            floor = np.zeros(len(est)) if other is None else np.nan_to_num(np.asarray(other, dtype=np.float64))
        e = floor
        s = np.asarray(std.values, dtype=np.float64) * (1.0 if self.spread_scale is None else self.spread_scale)
        with np.errstate(invalid="ignore"):
            rms = np.sqrt(np.nanmean(s.reshape(s.shape[0], -1) ** 2, axis=1)) if s.size else np.zeros(0)
        shape = (-1, *([1] * (s.ndim - 1)))
        with np.errstate(divide="ignore", invalid="ignore"):
            up = np.where(rms > 0, np.fmax(e / rms, 1.0), 1.0).reshape(shape)
        flat = (rms == 0).reshape(shape)
        out = std.copy(data=np.where(flat, np.broadcast_to(e.reshape(shape), s.shape), s * up))
        out.attrs = {**std.attrs, "long_name": "calibrated standard deviation (ensemble and held-out error)"}
        return out

    def members_warning(self, members: np.ndarray) -> str | None:
        """The warning of an ensemble's resampled members (1 .. N - 1) whose own fields (``members``: ``(members,
        slices, ...)``) leave the training fields' range or amplitudes as :meth:`warnings` measures them on the
        task's field (member 0's, so member 0 is not repeated here): one line naming each such member and how
        (None when none does)."""
        margin = RANGE_MARGIN * max(self.high - self.low, np.finfo(float).tiny)
        out = []
        for k in range(1, members.shape[0]):
            finite = members[k][np.isfinite(members[k])]
            if not finite.size:
                continue
            why = []
            low, high = float(finite.min()), float(finite.max())
            if low < self.low - margin or high > self.high + margin:
                why.append(f"values [{low:.3g}, {high:.3g}]")
            if self.span_low is not None and self.span_high is not None:
                span = high - low
                if span < (1 - RANGE_MARGIN) * self.span_low or span > (1 + RANGE_MARGIN) * self.span_high:
                    why.append(f"amplitude {span:.3g}")
            if why:
                out.append(f"member {k} ({', '.join(why)})")
        if not out:
            return None
        spans = (
            f", amplitudes [{self.span_low:.3g}, {self.span_high:.3g}]"
            if self.span_low is not None and self.span_high is not None
            else ""
        )
        return (
            f"calibration: {len(out)} of {members.shape[0] - 1} resampled ensemble members serve outside the "
            f"training fields the error bar was measured along (range [{self.low:.3g}, {self.high:.3g}]{spans}): "
            f"{'; '.join(out)}; "
            "the band does not bound their fields there"
        )

    def candidates_ratio(self, between: np.ndarray, k: np.ndarray) -> float | None:
        """How much more the two best candidates' trials disagree on a task than on the training fields: the median
        over the task's slices ``k`` (indices, ``2 <= k <`` :attr:`slices`) of ``between`` (their disagreement on
        the task per slice, relative to its largest magnitude; NaN where either trial stopped: an unbounded ratio)
        over :attr:`candidates` (at least :data:`CANDIDATES_FLOOR`). None without :attr:`candidates` or slices."""
        if self.candidates is None:
            return None
        train = np.array([math.nan if c is None else c for c in self.candidates], dtype=np.float64)
        kk = np.asarray(k, dtype=np.int64)
        inside = (kk >= 2) & (kk < train.size)
        kk, d = kk[inside], np.asarray(between, dtype=np.float64)[inside]
        ok = np.isfinite(train[kk])
        if not ok.any():
            return None
        ratio = np.where(np.isfinite(d[ok]), d[ok], math.inf) / np.maximum(train[kk][ok], CANDIDATES_FLOOR)
        return float(np.median(ratio))

    def candidates_warning(self, ratio: float | None, slices: int) -> str | None:
        """The warning of a task whose :meth:`candidates_ratio` is above :data:`CANDIDATES_RATIO` (None when it
        is not), the median taken over ``slices`` slices."""
        if ratio is None or not ratio > CANDIDATES_RATIO:
            return None
        return (
            f"calibration: the two best candidates ({self.chosen}, {self.runner_up}) disagree {ratio:.3g} times more "
            f"on this task than on the training fields (median over its first {slices} slices): the task lies where "
            "the training data do not pin the model down, and its error may be far beyond the band"
        )

    def warnings(self, served_slices: int, values: np.ndarray) -> list[str]:
        """Why a task's estimate is extrapolated: it serves more slices than the longest window measured, its
        values leave the training fields' range (by more than :data:`RANGE_MARGIN` of its width), or its
        amplitude (the range of its values) is below the smallest training field's or above the largest's (by more
        than :data:`RANGE_MARGIN` of it)."""
        out = []
        if served_slices > self.slices:
            out.append(
                f"calibration: the task serves {served_slices} slices, the error bar was measured on windows of at "
                f"most {self.slices}: beyond them the law (exponent {self.exponent:.2g}) is extrapolated"
            )
        finite = values[np.isfinite(values)]
        margin = RANGE_MARGIN * max(self.high - self.low, np.finfo(float).tiny)
        if finite.size and (finite.min() < self.low - margin or finite.max() > self.high + margin):
            out.append(
                f"calibration: the served field spans [{finite.min():.3g}, {finite.max():.3g}], outside the range "
                f"[{self.low:.3g}, {self.high:.3g}] of the windows the error bar was measured on"
            )
        if finite.size and self.span_low is not None and self.span_high is not None:
            span = float(finite.max() - finite.min())
            if span < (1 - RANGE_MARGIN) * self.span_low or span > (1 + RANGE_MARGIN) * self.span_high:
                out.append(
                    f"calibration: the served field's amplitude (range of values) {span:.3g} is outside the "
                    f"training fields' [{self.span_low:.3g}, {self.span_high:.3g}]: the error bar was measured "
                    "along the training fields and does not bound the model's error on another one"
                )
        return out
