"""The sparse fit of a :class:`SparseLagrangian`: sequential thresholding inside the gauge-fixed exact solve.

The DEL residual matrix ``R`` (rows: equations on interior sites, columns: the library's terms) of every
training field is cut into contiguous time blocks, each reduced to its triangular factor (``|R_b x| =
|T_b x|``). Sequential thresholding (STLSQ) fits ``coef`` under the gauge, drops every term whose share
``|coef_c| |R e_c|`` of the largest is below the threshold, and refits on the terms left until the support
holds. ``threshold = "auto"`` fits every threshold, and every support on the path of backward elimination
(:func:`backward`), on the first part of each training field and serves each
field's held-out tail from the tail's first two slices (as :func:`latticedft.select` scores); it keeps the
sparsest support served within :data:`SERVE_FLOOR`, or else within :data:`SERVE_SLACK` of the best (the held-out
residual of time blocks decides only where no fit serves). Each support is served only as far as that rule needs
(a few slices at a time, stopped once its error passes the bound it must meet), which keeps the choice and leaves
most of the cost of the supports that fail. Bagged
fits on blocks drawn with replacement give each term an inclusion probability.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from typing import Any, overload

import numpy as np
import torch
import xarray as xr

from .._contract import NumpyForms
from .._errors import InputError, LatticeDFTError
from .._lattice import BoundaryKinds, LatticeField, as_lattice_fields, interior_slices
from .._models import SparseLagrangian
from .._models._sparse import THRESHOLDS
from .._serve import serve
from .._serve._fast1d import numpy_derivatives_of
from .._serve._onedim import WindowServing
from .._serve._options import ServeOptions
from ._exact import (
    _constrained_lstsq,
    _gauge_split,
    _no_hessian,
    _null_solve,
    _qr_r,
    mean_mixed_hessian,
    residual_matrices,
    residual_matrix,
    ridge_weight,
)
from ._gauge import Gauge
from ._heldout import HOLD_OUT, held_in_slices, held_out_score

__all__ = ["learn_sparse", "stlsq", "backward", "BLOCKS", "SLACK", "SERVE_SLACK", "SERVE_FLOOR"]

#: The training rows are cut into about this many time blocks (for the held-out threshold and the bagging).
BLOCKS = 8
#: Where no fit serves, ``threshold = "auto"`` keeps the sparsest support whose held-out residual is within this
#: factor of the best.
SLACK = 2.0
#: ... and the sparsest support whose held-out served error is within this factor of the best: on clean data a
#: few extra terms that absorb the lattice's truncation error serve the held-out slices a little better.
SERVE_SLACK = 3.0
#: A support served within this relative error is taken (the sparsest first): there a lower held-out error
#: measures the lattice's truncation error absorbed by extra terms, not the physics (Kepler from one orbit).
SERVE_FLOOR = 5e-3

_Gauge = tuple[np.ndarray, np.ndarray] | None


def _finite_columns(model: SparseLagrangian, rs: list[np.ndarray]) -> None:
    """Refuse a term whose DEL rows are not finite on the training data, or spike above 1e8 times their median
    magnitude (a singularity met to round-off), with one line naming ``library``."""
    for r in rs:
        bad = [c for c in range(r.shape[1]) if _spiked(r[:, c])]
        if bad:
            names = [model.terms[c].name for c in bad]
            raise InputError.at(
                "library",
                f"term {', '.join(names)} is not finite on the training data (a log of 0 or a negative power "
                "at q = 0?); remove it from the library",
            )


def _spiked(col: np.ndarray) -> bool:
    if not np.isfinite(col).all():
        return True
    mags = np.abs(col[col != 0])
    return bool(mags.size and mags.max() > 1e8 * float(np.median(mags)))


def _blocks(rs: list[np.ndarray], c: int) -> list[np.ndarray]:
    """Each field's rows cut into contiguous time blocks (about :data:`BLOCKS` in all), each as its factor."""
    per = max(1, round(BLOCKS / len(rs)))
    out = []
    for r in rs:
        k = max(1, min(per, r.shape[0] // max(c, 1)))
        out += [_qr_r(b) for b in np.array_split(r, k) if b.shape[0]]
    return out


def _stack(factors: list[np.ndarray]) -> np.ndarray:
    return factors[0] if len(factors) == 1 else _qr_r(np.vstack(factors))


def _stacks(blocks: list[np.ndarray], picks: list[np.ndarray]) -> list[np.ndarray]:
    """:func:`_stack` of the blocks of each pick; blocks of one shape in one batched QR (LAPACK's factor of
    each matrix, the same as one at a time)."""
    if len({b.shape for b in blocks}) > 1 or any(len(p) < 2 for p in picks):
        return [_stack([blocks[i] for i in pick]) for pick in picks]
    rows = np.asarray(blocks)[np.asarray(picks)]  # (bags, picks, rows, C)
    return list(_qr_r(rows.reshape(len(picks), -1, rows.shape[-1])))


def _feasible(g: tuple[np.ndarray, np.ndarray], keep: np.ndarray) -> bool:
    """True when the terms ``keep`` can satisfy the gauge rows ``G coef = g`` (to round-off)."""
    if not keep.any():
        return False
    a = g[0][:, keep]
    x, *_ = np.linalg.lstsq(a, g[1], rcond=None)
    return bool(np.linalg.norm(a @ x - g[1]) <= 1e-9 * max(float(np.linalg.norm(g[1])), 1e-300))


class _Constraint:
    """The gauge rows ``G coef = g`` (or none) and what the solve and the feasibility test take of them per
    support, kept: they do not depend on the rows ``t``, and the same supports recur over the thresholds, the
    passes of thresholding, the backward path and the bags. Both are kept by the gauge rows' columns on the
    support (:meth:`_columns`), not by the support itself: supports whose columns hold the same numbers (a gauge
    that fixes one term's coefficient has zero columns everywhere else, so the backward path's trial supports of
    one size all meet it the same way) get the same arrays, computed once. The fits on the last rows met are kept
    too (every threshold's thresholding and the backward path start from the same supports)."""

    def __init__(self, g: _Gauge):
        self.g = g
        self._split: dict[bytes, tuple[np.ndarray, np.ndarray] | None] = {}
        self._feasible: dict[bytes, bool] = {}
        self._columns: dict[bytes, tuple[np.ndarray, bytes]] = {}
        self._rows: np.ndarray | None = None
        self._fits: dict[tuple[bytes, float], np.ndarray] = {}

    def columns(self, keep: np.ndarray) -> tuple[np.ndarray, bytes]:
        """The gauge rows' columns on the support ``keep`` (a gauge is needed) and a key of their shape and
        numbers: the same key, the same input to :func:`_feasible` and :func:`_gauge_split`, so the same result."""
        assert self.g is not None
        support = keep.tobytes()
        if support not in self._columns:
            a = np.ascontiguousarray(self.g[0][:, keep])
            self._columns[support] = (a, repr(a.shape).encode() + a.tobytes())
        return self._columns[support]

    def feasible(self, keep: np.ndarray) -> bool:
        """True without a gauge, else when the terms ``keep`` can satisfy its rows (:func:`_feasible`)."""
        if self.g is None:
            return True
        _, key = self.columns(keep)
        if key not in self._feasible:
            self._feasible[key] = _feasible(self.g, keep)
        return self._feasible[key]

    def fit(self, t: np.ndarray, active: np.ndarray, ridge: float) -> np.ndarray:
        """The gauge-fixed least-squares coefficients of the terms ``active`` on the rows ``t`` (zero elsewhere):
        :func:`latticedft._learn._exact._constrained_lstsq`, with the gauge's part kept per support."""
        if t is not self._rows:
            self._rows, self._fits = t, {}
        key = (active.tobytes(), ridge)
        if key not in self._fits:
            self._fits[key] = self._solve(t, active, ridge)
        return self._fits[key].copy()

    def _solve(self, t: np.ndarray, active: np.ndarray, ridge: float) -> np.ndarray:
        theta = np.zeros(t.shape[1])
        r = t[:, active]
        if self.g is None:
            theta[active] = _constrained_lstsq(r, None, None, ridge)
            return theta
        a, key = self.columns(active)
        if key not in self._split:
            self._split[key] = _gauge_split(a, self.g[1])
        split = self._split[key]
        if split is None:
            raise _no_hessian()
        lam = ridge_weight(r, ridge) if ridge else 0.0
        theta[active] = _null_solve(r, *split, lam)
        return theta


def _constraint(g: _Gauge | _Constraint) -> _Constraint:
    return g if isinstance(g, _Constraint) else _Constraint(g)


def _gauge_safe(keep: np.ndarray, weight: np.ndarray, con: _Constraint) -> np.ndarray:
    """``keep`` with the gauge's terms added back, largest first, until the gauge can be met."""
    if con.g is None or con.feasible(keep):
        return keep
    keep = keep.copy()
    for c in np.argsort(-weight):
        if con.feasible(keep):
            break
        if not keep[c] and np.any(con.g[0][:, c] != 0):
            keep[c] = True
    return keep


def stlsq(t: np.ndarray, g: _Gauge | _Constraint, threshold: float, ridge: float) -> np.ndarray:
    """Sequential thresholding on the rows ``t`` under the gauge ``g``: the coefficients, zero off the support."""
    con = _constraint(g)
    c = t.shape[1]
    norms = np.sqrt((t**2).sum(0))
    active = _gauge_safe(np.ones(c, dtype=bool), norms, con)
    theta = np.zeros(c)
    for _ in range(c + 1):
        theta = con.fit(t, active, ridge)
        weight = np.abs(theta) * norms
        keep = active & (weight > threshold * weight.max()) if weight.max() > 0 else active
        keep = _gauge_safe(keep, weight, con)
        if (keep == active).all():
            break
        active = keep
    return theta


def _pick(blocks: list[np.ndarray], g: _Gauge | _Constraint, ridge: float) -> tuple[float, dict[str, float]]:
    """The threshold of :data:`THRESHOLDS` with the sparsest support held out within :data:`SLACK` of the best."""
    folds = [(_stack([b for j, b in enumerate(blocks) if j != i]), blocks[i]) for i in range(len(blocks))]
    if len(blocks) < 2:
        return 0.0, {}
    scores: dict[str, float] = {}
    sizes: dict[float, int] = {}
    full = _stack(blocks)
    for thr in THRESHOLDS:
        errs = [float(np.sum((val @ stlsq(train, g, thr, ridge)) ** 2)) for train, val in folds]
        scores[f"{thr:g}"] = math.sqrt(sum(errs))
        sizes[thr] = int(np.count_nonzero(stlsq(full, g, thr, ridge)))
    best = min(scores.values())
    ok = [t for t in THRESHOLDS if scores[f"{t:g}"] <= SLACK * best]
    return min(ok, key=lambda t: (sizes[t], -t)), scores


def _unbatched(fields: list[LatticeField]) -> list[LatticeField]:
    """Every field on its own (a training batch of fields of one shape split up)."""
    return [replace(f, values=v, batch=0) for f in fields for v in (f.values if f.batch else [f.values])]


def _head(model: SparseLagrangian, f: LatticeField, r: np.ndarray, keep: int) -> np.ndarray:
    """The residual matrix of the first ``keep`` slices of the unbatched field ``f``: the first rows of its own,
    ``r`` (rows are time-major; each holds the DEL of one site, which sees only its neighbouring cells)."""
    times = [range(n)[interior_slices((n, *f.shape[1:]), model.stencil, f.boundary)[0]] for n in (f.shape[0], keep)]
    if times[0].start != times[1].start or not len(times[0]) or r.shape[0] % len(times[0]):
        return residual_matrix(model, f.with_values(f.values[:keep]))
    return r[: r.shape[0] // len(times[0]) * len(times[1])]


def _pick_served(
    model: SparseLagrangian,
    fields: list[LatticeField],
    g: _Gauge | _Constraint,
    ridge: float,
    nsites: int,
    rs: list[np.ndarray] | None = None,
) -> tuple[str, dict[str, float]] | None:
    """The rule chosen by held-out serving (a threshold, or a size on the backward path: :func:`_supports`), and
    the served error of every support tried (None where no fit serves): each support, fitted on the first part of
    every field (:func:`latticedft._learn._heldout.held_in`), serves every field's held-out tail from the tail's
    first two slices (as :func:`latticedft._learn._heldout.held_out_score` scores). The sparsest served within
    :data:`SERVE_FLOOR` is taken; else the sparsest within :data:`SERVE_SLACK` of the best. Serving stops early
    (:class:`_Serving`): first each support, the sparsest first, is served only until its error passes
    :data:`SERVE_FLOOR`; where none stays within it, the supports, the best held-out residual first, are served
    on until the error passes :data:`SERVE_SLACK` times the best served so far (a support stopped there cannot be
    chosen). A support stopped early is reported with its error where it stopped (a lower bound). ``rs``: the
    residual matrices of the unbatched fields (scaled by ``1 / sqrt(nsites)``), when at hand."""
    single = _unbatched(fields)
    boundary = dict(zip(single[0].dims[1:], single[0].boundary[1:])) or None
    try:
        keep = held_in_slices([f.shape[0] for f in single], HOLD_OUT)
    except InputError:  # too few slices to hold any out
        return None
    if rs is None:
        rs = [residual_matrix(model, f) / math.sqrt(nsites) for f in single]
    heads = [_head(model, f, r, k) for f, r, k in zip(single, rs, keep)]
    tails = _Tails(single, [min(k, f.shape[0] - 3) for f, k in zip(single, keep)])
    fits = sorted(_supports(_stack(_blocks(heads, model.n_terms)), g, ridge), key=lambda f: np.count_nonzero(f[1]))
    shared: dict[str, Any] = {}  # the tails' lattice fields and their batch, made once for every support
    runs = {label: _Serving(theta, tails, boundary, shared) for label, theta in fits}  # stable: thresholds first
    saved = model.coef.detach().clone()
    try:
        chosen = _serve_supports(model, runs, [r[h.shape[0] :] for r, h in zip(rs, heads)])
    finally:
        with torch.no_grad():
            model.coef.copy_(saved)
    scores = {label: run.error for label, run in runs.items() if run.started}
    return None if chosen is None else (chosen, scores)


def _serve_supports(model: SparseLagrangian, runs: dict[str, _Serving], rest: list[np.ndarray]) -> str | None:
    """The rule of :func:`_pick_served` on the supports ``runs`` (in order of sparsity), serving each no further
    than the rule needs; ``rest``: the residual rows of the held-out tails (the order of the second pass)."""
    for label, run in runs.items():
        if run.advance(model, SERVE_FLOOR) <= SERVE_FLOOR and run.finished:
            return label
    order = sorted(runs, key=lambda k: sum(float(np.sum((r @ runs[k].theta) ** 2)) for r in rest))
    best = math.inf
    for label in order:
        error = runs[label].advance(model, SERVE_SLACK * best)
        if runs[label].finished and math.isfinite(error):
            best = min(best, error)
    if not math.isfinite(best):
        return None
    return next(k for k, run in runs.items() if run.finished and run.error <= SERVE_SLACK * best)


#: Held-out serving advances this many slices at first, then twice as many each time (:class:`_Serving`).
FIRST_CHUNK = 4


class _Tails(Sequence[xr.DataArray]):
    """The held-out tails of the unbatched fields ``single``, each from its slice ``starts[k]`` on: their lattice
    fields (:meth:`fields`, the time axis sliced), and as DataArrays (each field's, sliced) made when first read,
    which only serving by :func:`serve` does (n-D tails, a denoised start): 1D tails are served from their
    lattice fields alone."""

    def __init__(self, single: list[LatticeField], starts: list[int]):
        self._single, self._starts = single, starts
        self._arrays: list[xr.DataArray] | None = None

    def __len__(self) -> int:
        return len(self._single)

    @overload
    def __getitem__(self, i: int) -> xr.DataArray: ...
    @overload
    def __getitem__(self, i: slice) -> Sequence[xr.DataArray]: ...
    def __getitem__(self, i: int | slice) -> xr.DataArray | Sequence[xr.DataArray]:
        if self._arrays is None:
            whole = [f.to_dataarray() for f in self._single]
            self._arrays = [w.isel({w.dims[0]: slice(k, None)}) for w, k in zip(whole, self._starts)]
        return self._arrays[i]

    def fields(self) -> list[LatticeField]:
        """The tails' lattice fields."""
        out = []
        for f, k in zip(self._single, self._starts):
            t = f.dims[0]
            out.append(replace(f, values=f.values[k:], coords={**f.coords, t: f.coords[t][k:]}))
        return out


class _Serving:
    """One support's held-out serving of every tail, advanced a few slices at a time from the last two slices
    served, so that it stops as soon as its error passes a bound (Newton's method restarted on each chunk, so
    the slices agree with serving a tail in one call to within Newton's tolerance). ``error``: the largest
    relative error so far (:func:`latticedft._learn._heldout.held_out_score`'s measure; ``inf`` once serving
    stops). ``shared``: where the tails' lattice fields and the batch serving 1D tails (:class:`WindowServing`)
    are kept for the other supports serving the same tails."""

    def __init__(
        self,
        theta: np.ndarray,
        tails: Sequence[xr.DataArray],
        boundary: BoundaryKinds | None,
        shared: dict[str, Any] | None = None,
    ):
        self.theta, self.tails, self.boundary = theta, tails, boundary
        self._shared = {} if shared is None else shared
        self.error = 0.0
        self.started = False
        self._field = 0
        self._served: np.ndarray | None = None
        self._chunk = FIRST_CHUNK
        # 1D tails: served by the numpy loop without building serve's results (:class:`WindowServing`), from
        # the numpy closed forms of the support being served (None: by the public serve)
        self._fields: list[LatticeField] | None = None
        self._forms: NumpyForms | None = None

    @property
    def finished(self) -> bool:
        """Every tail served, or serving stopped."""
        return self._field >= len(self.tails) or not math.isfinite(self.error)

    def advance(self, model: SparseLagrangian, bound: float) -> float:
        """Serve on until the error passes ``bound`` or every tail is served; the error so far."""
        if self.finished or self.error > bound:
            return self.error
        self.started = True
        with torch.no_grad():
            model.coef.copy_(torch.from_numpy(self.theta))
        noise = (model.report_.noise if model.report_ is not None else None) or {}
        if noise.get("method", "none") != "none":  # a denoised start: the tails served whole
            try:
                self.error = held_out_score(model, list(self.tails), self.boundary)
            except LatticeDFTError:
                self.error = math.inf
            self._field = len(self.tails)
            return self.error
        self._forms = self._numpy_forms(model)
        while not self.finished and self.error <= bound:
            self._chunk_on(model)
        return self.error

    def _numpy_forms(self, model: SparseLagrangian) -> NumpyForms | None:
        """The model's numpy closed forms where every tail is 1D (with their lattice fields), else None."""
        if self._fields is None:
            if "fields" not in self._shared and isinstance(self.tails, _Tails):
                self._shared["fields"] = self.tails.fields()
            elif "fields" not in self._shared:
                names = [f"tails[{k}]" for k in range(len(self.tails))]
                self._shared["fields"] = as_lattice_fields(self.tails, names, boundary=self.boundary, min_slices=2)
            self._fields = self._shared["fields"]
        return numpy_derivatives_of(model) if all(f.ndim == 1 for f in self._fields) else None

    def _window(self, model: SparseLagrangian) -> WindowServing:
        """What serves a window of a 1D tail: one batch for every support serving the same tails, restarted on
        each window (:class:`latticedft._serve._onedim.WindowServing`) instead of built again."""
        if "window" not in self._shared:
            self._shared["window"] = WindowServing(model, ServeOptions.from_keywords(None, progress=False))
        window: WindowServing = self._shared["window"]
        return window

    def _serve_window(self, model: SparseLagrangian, i0: int, start: np.ndarray) -> np.ndarray | None:
        """Slices ``i0, ...`` of the current tail served from the first two of ``start`` (the tail's slices from
        ``i0`` on, in its layout), or None where serving stopped: for 1D tails by :class:`WindowServing` (what
        :func:`serve` serves, without building its results), else by :func:`serve`."""
        try:
            if self._forms is None:
                tail = self.tails[self._field]
                window = tail.isel({tail.dims[0]: slice(i0, i0 + start.shape[0])})
                out = serve(model, window.copy(data=start), boundary=self.boundary, progress=False)
                return np.asarray(out.field.values)
            assert self._fields is not None
            f = self._fields[self._field]
            values = torch.from_numpy(start.reshape(start.shape[0], f.ncomp))
            t0 = float(f.coords[f.dims[0]][i0])
            served, failed = self._window(model)(f.with_values(values, t0), self._forms)
        except LatticeDFTError:
            return None
        return None if failed else served.reshape((served.shape[0], *start.shape[1:]))

    def _reference(self) -> np.ndarray:
        """The current tail's values: its lattice field's (slices, ..., components) where 1D tails are served by
        the numpy loop (the same numbers), else the DataArray's (the layout :func:`serve` takes)."""
        if self._forms is not None:
            assert self._fields is not None
            return self._fields[self._field].values.detach().numpy()
        return np.asarray(self.tails[self._field].values)

    def _chunk_on(self, model: SparseLagrangian) -> None:
        """Serve the next chunk of the current tail."""
        ref = self._reference()
        served = ref[:2] if self._served is None else self._served
        i0, nt = served.shape[0] - 2, ref.shape[0]
        start = ref[i0 : min(nt, i0 + 2 + self._chunk)].copy()
        start[:2] = served[-2:]
        out = self._serve_window(model, i0, start)
        if out is None:
            self.error = math.inf
            return
        new = out[2:]
        scale = max(float(np.max(np.abs(ref))), np.finfo(float).tiny)
        if new.size:
            err = float(np.max(np.abs(new - ref[i0 + 2 : i0 + 2 + new.shape[0]]))) / scale
            self.error = max(self.error, err if math.isfinite(err) else math.inf)
        self._served = np.concatenate([served, new])
        self._chunk *= 2
        if self._served.shape[0] >= nt or new.shape[0] < start.shape[0] - 2:
            self._field, self._served, self._chunk = self._field + 1, None, FIRST_CHUNK


def _fit(t: np.ndarray, g: _Gauge | _Constraint, ridge: float, active: np.ndarray) -> np.ndarray:
    """The gauge-fixed least-squares coefficients on the terms ``active`` (zero elsewhere)."""
    return _constraint(g).fit(t, active, ridge)


def backward(t: np.ndarray, g: _Gauge | _Constraint, ridge: float, stop: int = 0) -> list[np.ndarray]:
    """Backward elimination on the rows ``t`` under the gauge ``g``: from every term, drop one at a time the term
    whose removal raises the residual ``|t coef|`` least (the gauge kept feasible); the coefficients of every
    support on the path, the densest first, down to ``stop`` terms. Unlike thresholding by share, it is not
    misled by near-collinear terms (powers and trig functions of a field far from 0) whose large coefficients
    cancel."""
    con = _constraint(g)
    active = np.ones(t.shape[1], dtype=bool)
    if not con.feasible(active):
        return []
    path = []
    while active.any():
        try:
            path.append(con.fit(t, active, ridge))
        except (InputError, np.linalg.LinAlgError):
            break
        if np.count_nonzero(active) <= stop:
            break
        best: tuple[float, np.ndarray] | None = None
        for j in np.flatnonzero(active):
            trial = active.copy()
            trial[j] = False
            if not trial.any() or not con.feasible(trial):
                continue
            try:
                res = float(np.linalg.norm(t @ con.fit(t, trial, ridge)))
            except (InputError, np.linalg.LinAlgError):
                continue
            if best is None or res < best[0]:
                best = (res, trial)
        if best is None:
            break
        active = best[1]
    return path


def _supports(t: np.ndarray, g: _Gauge | _Constraint, ridge: float) -> list[tuple[str, np.ndarray]]:
    """``(rule, coefficients)`` for each distinct support over :data:`THRESHOLDS` (the rule the largest threshold
    giving it, ``"0.01"``) and then on the :func:`backward` path (``"4 terms"``), fitted on the rows ``t``."""
    out: dict[bytes, tuple[str, np.ndarray]] = {}
    for thr in THRESHOLDS:
        try:
            theta = stlsq(t, g, thr, ridge)
        except (InputError, np.linalg.LinAlgError):
            continue
        out.setdefault((theta != 0).tobytes(), (f"{thr:g}", theta))
    for theta in backward(t, g, ridge):
        out.setdefault((theta != 0).tobytes(), (f"{np.count_nonzero(theta)} terms", theta))
    return list(out.values())


def _refit(rule: str, t: np.ndarray, g: _Gauge | _Constraint, ridge: float) -> np.ndarray:
    """The coefficients of ``rule`` (a threshold, or ``"k terms"`` on the backward path) on the rows ``t``."""
    if not rule.endswith(" terms"):
        return stlsq(t, g, float(rule), ridge)
    size = int(rule.split()[0])
    path = [theta for theta in backward(t, g, ridge, size) if np.count_nonzero(theta) <= size]
    if not path:
        raise InputError.at("threshold", f"no support of {size} terms meets the gauge on these data")
    return path[0]


def _bagged(
    blocks: list[np.ndarray], g: _Gauge | _Constraint, rule: str, ridge: float, bags: int, theta: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Each term's share of ``bags`` fits of ``rule`` on blocks drawn with replacement, and the standard
    deviation of its coefficient over them relative to its coefficient ``theta`` (0 where ``theta`` is 0);
    both NaN without bags or blocks."""
    c = blocks[0].shape[1]
    if bags == 0 or len(blocks) < 2:
        return np.full(c, math.nan), np.full(c, math.nan)
    rng = np.random.default_rng(0)
    picks = [rng.integers(0, len(blocks), len(blocks)) for _ in range(bags)]
    fits = []
    for t in _stacks(blocks, picks):
        try:
            fits.append(_refit(rule, t, g, ridge))
        except (InputError, np.linalg.LinAlgError):
            continue
    if not fits:
        return np.zeros(c), np.full(c, math.nan)
    coefs = np.array(fits)
    kept = theta != 0
    spread = np.zeros(c)
    spread[kept] = coefs[:, kept].std(0) / np.abs(theta[kept])
    return (coefs != 0).sum(0) / bags, spread


def _share(theta: np.ndarray, t: np.ndarray) -> float:
    """The smallest share ``|coef_c| |R e_c|`` of the largest among the kept terms (the threshold a support found
    by backward elimination is reported with)."""
    weight = np.abs(theta) * np.sqrt((t**2).sum(0))
    kept = weight[theta != 0]
    return float(kept.min() / kept.max()) if kept.size and kept.max() > 0 else 0.0


def learn_sparse(
    model: SparseLagrangian,
    fields: list[LatticeField],
    gauge: Gauge,
    ridge: float | str,
    nsites: int,
    shared: dict[str, Any] | None = None,
) -> tuple[float, dict[str, float]]:
    """Fit ``model.coef`` in place (``ridge="auto"`` counts as 0); returns the ridge used and the held-out
    score of every support tried (empty for a given threshold). ``shared``: the residual matrices and the mean
    mixed Hessian, kept there for the next fit of the same library on the same fields (in another gauge)."""
    lam = 0.0 if ridge == "auto" else float(ridge)
    shared = {} if shared is None else shared
    if "rs" not in shared:
        mean = gauge.fixes and shared.get("mean") is None  # the mean mixed Hessian from the same derivatives
        rows, shared_mean = residual_matrices(model, fields, mean)
        rows = [r / math.sqrt(nsites) for r in rows]
        _finite_columns(model, rows)
        shared["rs"] = rows
        if mean:
            shared["mean"] = shared_mean
    rs: list[np.ndarray] = shared["rs"]
    unbatched = not any(f.batch for f in fields)  # then the held-out threshold reuses these rows
    if gauge.fixes and shared.get("mean") is None:
        shared["mean"] = mean_mixed_hessian(model, fields)
    g = _Constraint(gauge.constraint(shared["mean"], model.spacing[0]) if gauge.fixes else None)
    blocks = _blocks(rs, model.n_terms)
    validation: dict[str, float] = {}
    if model.threshold == "auto":
        served = _pick_served(model, fields, g, lam, nsites, rs if unbatched else None)
        if served is None:
            picked, validation = _pick(blocks, g, lam)
            rule = f"{picked:g}"
        else:
            rule, validation = served
    else:
        rule = f"{float(model.threshold)!r}"
    full = _stack(blocks)
    theta = _refit(rule, full, g, lam)
    inclusion, spread = _bagged(blocks, g, rule, lam, model.bags, theta)
    threshold = _share(theta, full) if rule.endswith(" terms") else float(rule)
    with torch.no_grad():
        model.coef.copy_(torch.from_numpy(theta))
        model.inclusion.copy_(torch.from_numpy(inclusion))
        model.threshold_used.fill_(threshold)
    model.bag_spread = spread
    return lam, {f"threshold {k}" if not k.endswith(" terms") else k: v for k, v in validation.items()}
