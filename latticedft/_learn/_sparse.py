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
from dataclasses import replace
from typing import Any

import numpy as np
import torch

from .._errors import InputError
from .._lattice import LatticeField, interior_slices
from .._models import SparseLagrangian
from .._models._sparse import THRESHOLDS
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
from ._heldout import HOLD_OUT, SupportServing, Tails, held_in_slices

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
    (:class:`SupportServing`): first each support, the sparsest first, is served only until its error passes
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
    tails = Tails(single, [min(k, f.shape[0] - 3) for f, k in zip(single, keep)])
    fits = sorted(_supports(_stack(_blocks(heads, model.n_terms)), g, ridge), key=lambda f: np.count_nonzero(f[1]))
    shared: dict[str, Any] = {}  # the tails' lattice fields and their batch, made once for every support
    runs = {label: SupportServing(theta, tails, boundary, shared) for label, theta in fits}  # stable: thresholds first
    saved = model.coef.detach().clone()
    try:
        chosen = _serve_supports(model, runs, [r[h.shape[0] :] for r, h in zip(rs, heads)])
    finally:
        with torch.no_grad():
            model.coef.copy_(saved)
    scores = {label: run.error for label, run in runs.items() if run.started}
    return None if chosen is None else (chosen, scores)


def _serve_supports(model: SparseLagrangian, runs: dict[str, SupportServing], rest: list[np.ndarray]) -> str | None:
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
