"""Error bars calibrated by held-out serving.

A model learned from the first part of every training field (as model selection does) serves each whole field
from its first two slices; its error on the held-out slices, slice by slice, is the measured error of the model
class, the lattice and the data together. :func:`calibrate` fits a law to it, the relative error at slice ``k``

    ``err(k) / A = scale * (k - 1)^exponent``

(``A`` the field's largest magnitude, ``k - 1`` the steps served from the second given slice, where the error is
0): the exponent by least squares in ``log err`` against ``log (k - 1)`` over every served slice, the scale as
the :data:`QUANTILE` quantile over the held-out slices of the error over the law, halved, so that twice the
estimate covers that share of them (a conformal scale). When model selection ran, the
disagreement of the runner-up candidate with the chosen one, slice by slice, is a second error sample (the
model class's term): the exponent is fitted to the larger of the two. The scale is not: on a held-out slice the
trial's error is measured against the data, and the runner-up's disagreement there is at most that error plus
the runner-up's own (the triangle inequality), so beyond the measured error it adds only the runner-up's. Fitting
the scale to the larger of the two made the noisy ``cases/oscillator-sin`` band 3.8 times its error.

A served task's estimate per slice is the larger of the law and the trial's disagreement with the served
field on the task itself (the trial, learned on less data, served from the same start: :func:`disagreement`).
:meth:`Calibration.estimate` gives the law's part (``psi_err_est``);
:meth:`Calibration.band` gives an ensemble's ``psi_std``: its members' standard deviation scaled by the same
held-out measurement (:attr:`Calibration.spread_scale`: how the trial's error compares with the members' spread on
the held-out slices; the scaled spread takes the law's place), widened to the trial's disagreement where
narrower; :meth:`Calibration.warnings`
names a task that runs longer than, or outside the value range of, the windows the law was measured on. With a
runner-up, the law also records the two trials' disagreement per slice on the training fields
(:attr:`Calibration.candidates`); a task on which they disagree far more (:meth:`Calibration.candidates_ratio`,
the runner-up's trial served beside the trial) is told that the training data do not pin the model down there
(:meth:`Calibration.candidates_warning`: a warning, not a band).
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
import xarray as xr

from ._calibration_law import EXPONENT_RANGE, LAW, ORIGIN, QUANTILE, Calibration
from ._errors import LatticeDFTError, ServeError
from ._lattice import BoundaryKinds
from ._learn import learn
from ._learn._heldout import HOLD_OUT
from ._learn._heldout import held_in as _split
from ._learn._noise import denoised_start
from ._models import AbstractLagrangian
from ._serve import ServeResult, serve

__all__ = [
    "Calibration",
    "calibrate",
    "candidates_disagreement",
    "disagreement",
    "runner_up",
    "served_along",
    "too_short",
    "slice_errors",
    "trial_keywords",
]

#: The runner-up candidate's disagreement enters only when its selection score is within this factor of the
#: chosen one's (a far worse candidate says nothing about the chosen model's error).
RUNNER_UP_WITHIN = 10.0

#: A noise-corrected fit whose held-out relative error (RMS over the lattice over the field's largest magnitude,
#: worst slice) exceeds this is reported as failed: its trial left the data (the limit of an inaccurate task).
#: At 0.1 the double-well Duffing oscillator at sigma = 1e-2 (0.12 held out, 2.8e-2 served on its tests) warned.
NOISE_FAILED = 0.5

#: Folds of training fields (each one more trial fit). With 1, every field is split in time (the held-out windows
#: of model selection). Leaving whole fields out (3 folds) overstated the error on unseen trajectories by orders
#: of magnitude on cases/oscillator-sin (three training amplitudes: two do not pin the third down).
FOLDS = 1


def runner_up(rows: Sequence[Mapping[str, Any]], chosen: int) -> int | None:
    """The runner-up among model selection's candidate ``rows`` (:class:`latticedft.SelectionReport`'s, or their
    JSON form): the index of the lowest score but the ``chosen`` one's, within :data:`RUNNER_UP_WITHIN` times it;
    None without one. A score that is None or not finite is a failed candidate."""

    def score(i: int) -> float | None:
        s = rows[i]["score"]
        return s if s is not None and math.isfinite(s) else None

    best = score(chosen)
    if best is None:
        return None
    others = [
        i for i in range(len(rows)) if i != chosen and (s := score(i)) is not None and s <= RUNNER_UP_WITHIN * best
    ]
    return min(others, key=lambda i: rows[i]["score"]) if others else None


def trial_keywords(learn_kwargs: Mapping[str, Any], ridge: float | None) -> dict[str, Any]:
    """The learn keywords of a trial of a model learned with ``learn_kwargs``: ``ridge="auto"`` replaced by
    ``ridge``, the weight the model's own fit chose (its report's; kept ``"auto"`` when None), as model
    selection's trials take the chosen candidate's and an ensemble's members take member 0's. A trial that chose
    its own weight on its 70 % would be another model: on ``cases/sine-gordon`` with noise 1e-3 it chose 0 where
    the model's fit chose 1e-4, and its serve diverged within 4 slices (a calibration measuring no error)."""
    out = dict(learn_kwargs)
    if out.get("ridge") == "auto" and ridge is not None:
        out["ridge"] = float(ridge)
    return out


def too_short(fields: Sequence[xr.DataArray], hold_out: float = HOLD_OUT) -> str | None:
    """The one-line message of training data too short for a held-out window (None when they are not)."""
    try:
        _split(list(fields), hold_out)
    except LatticeDFTError:
        nt = min(f.sizes[f.dims[0]] for f in fields)
        return (
            f"calibration: the training data are too short for a held-out window (a field of {nt} slices; at least "
            "4 are needed): served without a calibrated error bar (an ensemble's psi_std is its members' spread alone)"
        )
    return None


def slice_errors(model: AbstractLagrangian, field: xr.DataArray, boundary: BoundaryKinds | None) -> np.ndarray:
    """``model`` serving ``field`` from its first two slices (denoised when its training corrected noise): the
    RMS error over the lattice at every slice (NaN where the serve stopped)."""
    return _rms(_served(model, field, boundary), np.asarray(field.values, dtype=np.float64))


def disagreement(trial: AbstractLagrangian, init: xr.DataArray, field: xr.DataArray, **serve_kwargs: Any) -> np.ndarray:
    """The RMS over the lattice, per slice of ``field`` (a served field, its ``slice`` coordinate when thinned),
    of the difference between ``field`` and ``trial`` served from ``init`` with ``serve_kwargs`` (NaN where
    the trial stopped)."""
    theirs = served_along(trial, init, field, **serve_kwargs)
    return _rms(theirs, np.asarray(field.values, dtype=np.float64), field.sizes[field.dims[0]])


def served_along(model: AbstractLagrangian, init: xr.DataArray, field: xr.DataArray, **serve_kwargs: Any) -> np.ndarray:
    """``model`` served from ``init`` with ``serve_kwargs``, on the slices of ``field`` (a served field, its
    ``slice`` coordinate when thinned): the values of the slices it solved (fewer where it stopped)."""
    try:
        other = serve(model, init, progress=False, **serve_kwargs).field
    except ServeError as err:
        other = (err.result[0] if isinstance(err.result, list) else err.result).field
    theirs = np.asarray(other.values, dtype=np.float64)
    if "slice" in field.coords and "slice" not in other.coords:
        k = np.asarray(field["slice"].values)
        theirs = theirs[k[k < theirs.shape[0]]]
    return theirs


def candidates_disagreement(mine: np.ndarray, theirs: np.ndarray, nt: int) -> np.ndarray:
    """The two trials' disagreement per slice (``nt`` slices): the RMS over the lattice of ``theirs - mine``
    (NaN past either's end), as :attr:`Calibration.candidates` measures it before dividing by the magnitude."""
    return _rms(theirs, mine, nt)


def _rms(pred: np.ndarray, ref: np.ndarray, nt: int | None = None) -> np.ndarray:
    """The RMS over the lattice of ``pred - ref`` per slice, ``nt`` slices (NaN past either's end)."""
    nt = ref.shape[0] if nt is None else nt
    out = np.full(nt, math.nan)
    n = min(nt, pred.shape[0], ref.shape[0])
    with np.errstate(invalid="ignore", over="ignore"):
        out[:n] = np.sqrt(np.mean((pred[:n] - ref[:n]).reshape(n, -1) ** 2, axis=1))
    return out


def _trial(
    fresh: AbstractLagrangian,
    train: list[xr.DataArray],
    boundary: BoundaryKinds | None,
    learn_kwargs: dict[str, Any],
) -> AbstractLagrangian:
    """``fresh`` (unlearned) learned on ``train`` as a single model."""
    trial = copy.deepcopy(fresh)
    kw = {k: v for k, v in learn_kwargs.items() if k not in ("ensemble", "ensemble_seed")}
    learn(trial, train, boundary=boundary, progress=False, **{**kw, "symmetries": False})
    return trial


@dataclass
class _Fold:
    """One held-out measurement: the fields a trial learns from, and per field the first held-out slice."""

    train: list[xr.DataArray]
    starts: list[int]


def _folds(fields: list[xr.DataArray], hold_out: float, folds: int = FOLDS) -> list[_Fold]:
    """One fold per group of fields (at most ``folds``, fields ``j::K``): its trial learns from the other
    fields whole and serves the group's fields whole (every slice held out); a single field is split in time
    instead (its trial learns from the first ``1 - hold_out`` of the slices, the last ones are held out)."""
    k = min(len(fields), folds)
    if k == 1:
        held = _split(fields, hold_out)
        return [_Fold(held, [h.sizes[h.dims[0]] for h in held])]
    out = []
    for j in range(k):
        starts = [0 if i % k == j else f.sizes[f.dims[0]] for i, f in enumerate(fields)]
        out.append(_Fold([f for i, f in enumerate(fields) if i % k != j], starts))
    return out


def calibrate(
    fresh: AbstractLagrangian,
    fields: Sequence[xr.DataArray],
    *,
    boundary: BoundaryKinds | None = None,
    runner_up: tuple[AbstractLagrangian, dict[str, Any], str] | None = None,
    hold_out: float = HOLD_OUT,
    quantile: float = QUANTILE,
    folds: int = FOLDS,
    ensemble_model: AbstractLagrangian | None = None,
    record: list[dict[str, Any]] | None = None,
    learned: tuple[AbstractLagrangian, AbstractLagrangian | None] | None = None,
    served: tuple[list[np.ndarray] | None, list[np.ndarray] | None] | None = None,
    chosen: str | None = None,
    runner_trial: list[AbstractLagrangian] | None = None,
    **learn_kwargs: Any,
) -> tuple[Calibration, list[str], AbstractLagrangian]:
    """Measure a calibration law by held-out serving (see the module docstring): ``(law, warnings, trial)``,
    ``trial`` the model of the first fold (learned on the first part of every field).

    ``fresh`` is the chosen model unlearned (its learn keywords ``learn_kwargs``); ``runner_up`` the runner-up
    candidate unlearned, its own learn keywords and its label (its disagreement is measured on the first fold);
    ``folds`` > 1 leaves groups of whole fields out instead of splitting them in time. ``ensemble_model``, the
    learned ensemble, is served on every training field to measure :attr:`Calibration.spread_scale`. A ``record``
    list receives every measured field's samples (slices ``k >= 2``: ``k``, which are ``held`` out, the trial's
    relative error ``rel``, the fitted ``target``, the ``field``'s index), to measure another law on them.
    ``learned``: the trial and the runner-up (None: not learned) as model selection learned them, on the first
    ``1 - hold_out`` of every field with the same keywords (:attr:`latticedft.SelectionReport.trials`): taken as
    they are instead of learning the same fits again (a noise-aware fit repeats its correction), with one fold.
    ``served``: with ``learned``, the fields the two served from every training field when selection scored them
    (:attr:`latticedft.SelectionReport.served`, None where it kept none), taken instead of serving the same
    trials from the same starts again (the same values; one that does not fit the fields is served again).
    With a runner-up trial measured, the law records the two trials' disagreement per slice on the training
    fields (:attr:`Calibration.candidates`) and ``chosen``, the chosen candidate's label; a ``runner_trial`` list
    then receives the runner-up's trial (to serve beside the trial on every task: :meth:`Calibration.candidates_ratio`).
    A law that could not be measured (no held-out slice served) comes back with :attr:`Calibration.failed` set: it
    is no law, and a caller serves without a calibrated error bar. The random state of torch and numpy is left as
    it was. ``InputError`` when the fields are too short
    (:func:`too_short`).
    """
    t0 = time.perf_counter()
    fields = [f.load() for f in fields]
    samples: list[_Sample] = []
    warnings: list[str] = []
    first: AbstractLagrangian | None = None
    with torch.random.fork_rng(devices=[]):
        state = np.random.get_state()
        try:
            for n, fold in enumerate(_folds(fields, hold_out, folds)):
                reuse = learned if n == 0 and folds == 1 else None
                trial = reuse[0] if reuse is not None else _trial(fresh, fold.train, boundary, learn_kwargs)
                first = first or trial
                taken: tuple[list[np.ndarray] | None, list[np.ndarray] | None] = (None, None)
                if reuse is not None:
                    other = reuse[1] if runner_up is not None else None
                    if served is not None:  # one array per training field, or none
                        mine, theirs = (x if x is not None and len(x) == len(fields) else None for x in served)
                        taken = (mine, theirs)
                else:
                    other = _runner_trial(runner_up, fold, boundary) if n == 0 else None
                found = _measure(trial, other, fold, fields, boundary, taken)
                if other is not None and runner_trial is not None:
                    runner_trial.append(other)
                warnings = warnings or _noise_warnings(trial, [x.rel[x.held] for x in found])
                samples += found
        finally:
            np.random.set_state(state)
    cal = _fit(samples, quantile)
    if record is not None:
        record += [{k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in asdict(x).items()} for x in samples]
    cal.spread_scale, cal.spread_std_over_error = (
        _spread_scale(ensemble_model, samples, fields, boundary, quantile)
        if ensemble_model is not None
        else (None, None)
    )
    warnings += _stopped(samples, quantile)
    cal.failed = _degenerate(samples)
    cal.windows, cal.slices = len(fields), max(f.sizes[f.dims[0]] for f in fields)
    lows = [float(np.nanmin(f.values)) for f in fields]
    highs = [float(np.nanmax(f.values)) for f in fields]
    spans = [h - lo for lo, h in zip(lows, highs, strict=True)]
    cal.low, cal.high, cal.span_low, cal.span_high = min(lows), max(highs), min(spans), max(spans)
    used = any(x.disagreement for x in samples)
    cal.runner_up = runner_up[2] if runner_up is not None and used else None
    cal.candidates = _candidates_curve(samples, cal.slices) if used else None
    cal.chosen = chosen if used else None
    cal.wall_time = time.perf_counter() - t0
    assert first is not None
    return cal, warnings, first


@dataclass
class _Sample:
    """The slices ``k >= 2`` of one field served by one trial: their indices ``k``, which are ``held`` out, the
    trial's relative error ``rel`` and the fitted ``target`` (the larger of it and the runner-up's relative
    disagreement)."""

    k: np.ndarray
    held: np.ndarray
    rel: np.ndarray
    target: np.ndarray
    disagreement: bool
    #: The field's index in the training fields.
    field: int = 0
    #: The runner-up's trial's disagreement with the trial (relative, as ``rel``; None without a runner-up).
    between: np.ndarray | None = None


def _candidates_curve(samples: list[_Sample], slices: int) -> list[float | None]:
    """:attr:`Calibration.candidates`: per slice ``k < slices``, the largest of the samples' ``between`` at ``k``
    (None where none is finite; 0 on the two given slices)."""
    curve = np.full(slices, math.nan)
    curve[: min(2, slices)] = 0.0
    for x in samples:
        if x.between is None:
            continue
        k = x.k.astype(np.int64)
        with np.errstate(invalid="ignore"):
            curve[k] = np.fmax(curve[k], x.between)
    return [float(c) if math.isfinite(c) else None for c in curve]


def _runner_trial(
    runner_up: tuple[AbstractLagrangian, dict[str, Any], str] | None, fold: _Fold, boundary: BoundaryKinds | None
) -> AbstractLagrangian | None:
    """The runner-up candidate learned on the fold's fields (None without one, or when its fit fails)."""
    if runner_up is None:
        return None
    try:
        return _trial(runner_up[0], fold.train, boundary, runner_up[1])
    except LatticeDFTError:
        return None


def _measure(
    trial: AbstractLagrangian,
    other: AbstractLagrangian | None,
    fold: _Fold,
    fields: list[xr.DataArray],
    boundary: BoundaryKinds | None,
    taken: tuple[list[np.ndarray] | None, list[np.ndarray] | None] = (None, None),
) -> list[_Sample]:
    """Every field of the fold with held-out slices, served by ``trial`` (and by ``other``, the learned
    runner-up): its slices ``k >= 2``. ``taken``: the fields the two served from every field already (or None),
    taken where they fit the field (:func:`_served_or_taken`) instead of serving again."""
    out = []
    for i, (f, start) in enumerate(zip(fields, fold.starts, strict=True)):
        nt = f.sizes[f.dims[0]]
        k = np.arange(2, nt)
        if start >= nt or not k.size:
            continue
        amp = max(float(np.max(np.abs(f.values))), np.finfo(float).tiny)
        mine = _served_or_taken(trial, f, boundary, taken[0], i)
        rel = _rms(mine, np.asarray(f.values, dtype=np.float64), nt)[k] / amp
        target, between = rel, None
        if other is not None:
            theirs = _served_or_taken(other, f, boundary, taken[1], i)
            between = _rms(theirs, mine, nt)[k] / amp
            target = np.fmax(rel, between)
        out.append(_Sample(k.astype(np.float64), k >= start, rel, target, other is not None, i, between))
    return out


def _served_or_taken(
    model: AbstractLagrangian,
    field: xr.DataArray,
    boundary: BoundaryKinds | None,
    served: list[np.ndarray] | None,
    i: int,
) -> np.ndarray:
    """:func:`_served` of training field ``i``, or its values served already (``served``: one array per training
    field) where they fit ``field``: as many slices or fewer (a serve that left the box), the same lattice."""
    values = served[i] if served is not None and i < len(served) else None
    if values is not None and values.shape[1:] == field.shape[1:] and values.shape[0] <= field.shape[0]:
        return values
    return _served(model, field, boundary)


def _served(model: AbstractLagrangian, field: xr.DataArray, boundary: BoundaryKinds | None) -> np.ndarray:
    """The field ``model`` serves from the first two slices of ``field`` (denoised when its training corrected
    noise); the slices solved when the serve stopped."""
    return np.asarray(_result(model, field, boundary).field.values, dtype=np.float64)


def _result(model: AbstractLagrangian, field: xr.DataArray, boundary: BoundaryKinds | None) -> ServeResult:
    """``model`` serving ``field`` from its first two slices (denoised when its training corrected noise): the
    result, of the slices solved when the serve stopped."""
    noise = (model.report_.noise if model.report_ is not None else None) or {}
    start = denoised_start(model, field) if noise.get("method", "none") != "none" else field
    try:
        return serve(model, start, boundary=boundary, progress=False)
    except ServeError as err:
        return err.result[0] if isinstance(err.result, list) else err.result


def _spread_scale(
    ensemble: AbstractLagrangian,
    samples: list[_Sample],
    fields: list[xr.DataArray],
    boundary: BoundaryKinds | None,
    quantile: float,
) -> tuple[float | None, float | None]:
    """The factor on an ensemble's spread: the ``quantile`` quantile over the held-out slices of the trial's
    error over the spread (RMS over the lattice of the members' standard deviation, the ensemble serving the
    same training field from the same start), halved. The spread is ``psi_std``'s: on a slice where members
    stopped, over those still served there; slices where the members agree exactly, where fewer than
    :data:`latticedft._serve._ensemble.MIN_MEMBERS` are still served, or where the trial's or member 0's serve
    stopped, are left out. With it, the mean scaled spread over the mean error on those slices. (None, None)
    when the ensemble gives no spread."""
    z, rs, ss = [], [], []
    for x in samples:
        f = fields[x.field]
        std = _result(ensemble, f, boundary).std
        if std is None:
            return None, None
        amp = max(float(np.max(np.abs(f.values))), np.finfo(float).tiny)
        s = _rms(np.asarray(std.values, dtype=np.float64), np.zeros(std.shape), f.sizes[f.dims[0]]) / amp
        k = x.k[x.held].astype(int)
        r, sk = x.rel[x.held], s[k]
        ok = np.isfinite(r) & np.isfinite(sk) & (sk > 0)
        z.append(r[ok] / sk[ok])
        rs.append(r[ok])
        ss.append(sk[ok])
    zz = np.concatenate(z) if z else np.zeros(0)
    if not zz.size:
        return None, None
    scale = float(np.quantile(zz, quantile, method="higher")) / 2
    mean_err = float(np.concatenate(rs).mean())
    return scale, float(scale * np.concatenate(ss).mean() / mean_err) if mean_err > 0 else None


def _fit(samples: list[_Sample], quantile: float) -> Calibration:
    """The law fitted to the samples (the exponent by least squares in log-log of the targets over every served
    slice, the scale by the ``quantile`` of the trial's own error over the law on the held-out slices, halved),
    and its held-out coverage of those errors."""
    cat = lambda get: np.concatenate([get(x) for x in samples]) if samples else np.zeros(0)  # noqa: E731
    k_all, y_all = cat(lambda x: x.k), cat(lambda x: x.target)
    ok = np.isfinite(y_all) & (y_all > 0)
    p = 0.0
    if np.unique(k_all[ok]).size >= 2:
        p = float(np.polyfit(np.log(k_all[ok] - ORIGIN), np.log(y_all[ok]), 1)[0])
    p = float(np.clip(p, *EXPONENT_RANGE))
    k, r = cat(lambda x: x.k[x.held]), cat(lambda x: x.rel[x.held])
    shape = (k - ORIGIN) ** p
    z = np.where(np.isfinite(r), r, np.inf) / shape  # a serve that stopped: an unbounded error
    q = float(np.quantile(z, quantile, method="higher")) if z.size else math.inf
    if not math.isfinite(q) and np.isfinite(z).any():
        # stopped on more than 1 - quantile of the slices: fitted to those served (:func:`_stopped` warns)
        q = float(np.quantile(z[np.isfinite(z)], quantile, method="higher"))
    scale = q / 2
    scale = scale if math.isfinite(scale) and scale > 0 else float(np.finfo(float).tiny)
    est = scale * shape
    finite = np.isfinite(r)
    mean_err = float(r[finite].mean()) if finite.any() else math.nan
    return Calibration(
        scale=scale,
        law=LAW,
        origin=ORIGIN,
        exponent=p,
        quantile=quantile,
        windows=0,
        held_out_slices=int(k.size),
        slices=0,
        low=0.0,
        high=0.0,
        coverage=float(np.mean(r <= 2 * est)) if r.size else math.nan,
        std_over_error=float(est[finite].mean() / mean_err) if mean_err > 0 else math.nan,
        runner_up=None,
        wall_time=0.0,
    )


def _degenerate(samples: list[_Sample]) -> str | None:
    """Why no law can be fitted to the samples (None when one can): not one held-out slice with a finite error
    (the trial's serve stopped before every one, or no field had held-out slices). Its quantile would be
    unbounded and the scale meaningless (a law of scale 1e-308 and held-out coverage 0 % was recorded so)."""
    held = [x.rel[x.held] for x in samples]
    total = sum(r.size for r in held)
    if any(np.isfinite(r).any() for r in held):
        return None
    if not total:
        return "no held-out slice was measured"
    return f"the trial model's serve stopped before all {total} held-out slices: no error was measured to scale the law"


def _stopped(samples: list[_Sample], quantile: float) -> list[str]:
    """A trial whose serve stopped before more than ``1 - quantile`` of the held-out slices: the law is fitted to
    the slices it served (a quantile over unbounded errors would be unbounded), and it does not bound the rest."""
    held = [x.rel[x.held] for x in samples]
    n, total = sum(int((~np.isfinite(r)).sum()) for r in held), sum(r.size for r in held)
    if not total or n <= (1 - quantile) * total:
        return []
    fields = sum(1 for r in held if not np.isfinite(r).all())
    return [
        f"calibration: the trial model's serve stopped before {n} of {total} held-out slices ({fields} of "
        f"{len(held)} training fields): the error bar is fitted to the slices it served and does not bound a "
        "serve that stops"
    ]


def _noise_warnings(trial: AbstractLagrangian, rel: list[np.ndarray]) -> list[str]:
    """A noise-corrected fit that does not serve its held-out slices (relative error above
    :data:`NOISE_FAILED`): the correction failed, whatever the noise's share of the second differences."""
    noise = (trial.report_.noise if trial.report_ is not None else None) or {}
    if noise.get("method", "none") == "none":
        return []
    worst = max((float(np.max(np.where(np.isfinite(r), r, np.inf))) for r in rel if r.size), default=0.0)
    if worst <= NOISE_FAILED:
        return []
    share = noise.get("second_difference_ratio")
    shown = f"{share:.2f}" if isinstance(share, float) else "not estimated"
    served = f"to a relative error of {worst:.3g} (above {NOISE_FAILED:g}" if math.isfinite(worst) else "(it stopped"
    return [
        f"noise: the noise-aware fit failed its held-out check: learned on the first {100 * (1 - HOLD_OUT):.0f} % of "
        f"every training field, it serves the rest {served}; the noise's share of the second differences is "
        f"{shown}): the learned equations are unreliable"
    ]
