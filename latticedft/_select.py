"""Model selection by serving: each candidate learns from the first part of every training field and serves the
whole field from its first two slices (and its boundary strips); the smallest error wins."""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import xarray as xr

from ._calibrate import runner_up
from ._errors import InputError, LatticeDFTError, ServeError
from ._lattice import BoundaryKinds
from ._learn import learn
from ._learn._data import as_fields
from ._learn._heldout import HOLD_OUT
from ._learn._heldout import held_in as _split
from ._learn._heldout import held_out_score as _score
from ._learn._noise import SPREAD_WARN, largest_spread
from ._learn._sparse import SERVE_FLOOR
from ._models import MODELS, AbstractLagrangian
from ._models._sparse import SparseLagrangian, default_library, exact_step_libraries
from ._options import option

__all__ = [
    "SelectionReport",
    "select",
    "auto_candidates",
    "sparse_candidates",
    "HOLD_OUT",
    "FACTOR",
    "KEEP_BELOW",
    "BEATEN",
    "BEYOND_CEILING",
]

#: The fraction of every training field's slices that no candidate learns from (its served error is the score).
#: A candidate replaces the hand-set model only when its score is below the hand-set score by this factor.
FACTOR = 2.0
#: The hand-set model is kept when its score is at or below this: it serves the held-out slices to this relative
#: error, and a lower score there no longer predicts a lower error elsewhere (docs/selection.md).
KEEP_BELOW = 1e-6
#: ... but never when a candidate scores this many times lower: a hand-set model beaten so far is not kept.
BEATEN = 100.0
#: A hand-set model kept by ``keep_below`` is still replaced by the candidate chosen on the held-out slices when,
#: learned on every training field but the one of largest amplitude, that candidate serves the field left out
#: ``factor`` times better than the hand-set model does, and within this (relative): below ``keep_below`` the
#: held-out slices no longer rank models, and serving a larger amplitude than was learned from does (the quartic
#: single well of ``benchmarks.untuned``: the hand-set polynomial scores 3.5e-9 on the held-out slices, cannot serve
#: amplitude 1.0 learned from 0.5 alone, and serves the test at 1.6 to 0.26; the exact-step candidate serves it
#: to 0.05). A candidate that serves the field left out worse than this has not found the physics either.
BEYOND_CEILING = 1e-1
#: A sparse candidate (``kind = "sparse"``) within this factor of the lowest score is preferred to a denser one:
#: held-out slices of the training fields cannot show that a few symbolic terms extrapolate and a dense fit
#: of the same orbit does not (docs/sparse.md: Kepler from one orbit).
SPARSE_FACTOR = 100.0
#: ... and so is one that serves the held-out slices within ``SERVE_FLOOR`` (5e-3): there a lower score measures
#: the lattice's truncation error absorbed by more terms, not the physics (Kepler from one orbit: the true two
#: terms score 1.6e-3, the polynomial (2, 2) 8.5e-7 and escapes beyond the training orbit).
SPARSE_FLOOR = SERVE_FLOOR
#: ... but not one that serves the held-out slices worse than this: its few terms do not hold the physics, and the
#: field is lost (the double pendulum's vector library without its coupling term scored 0.61 within 100x of a
#: polynomial's 1.5e-2); its five true terms, discretised by the trapezoid rule, which serves less accurately than
#: the polynomial there, scored 3.0e-2.
SPARSE_CEILING = 1e-1
#: The library ``"auto"`` also tries on a time-only lattice of several components (coupled pendulums, several
#: bodies): unequal masses (every product of two velocities), on-site trig functions, and the products of
#: ``cos(q_i - q_j)`` with the velocity products, its terms evaluated at both ends of the step (``at =
#: "average"``: the trapezoid rule, which a mass depending on the positions needs to be met exactly).
COUPLED_LIBRARY = "velocities + trig:1 + cosdiff*velocities"
#: The library ``"auto"`` also tries on a time-only scalar lattice: the powers and the trig functions of ``q^2``
#: (``cos(q^2 - 1) = cos 1 cos q^2 + sin 1 sin q^2``, paper Example 2's double well). Without ``trig:1``: with it,
#: ``q^3 + sin q`` fits the true ``q`` on one orbit (nearly collinear there) and the test is served 2x worse.
SQUARE_TRIG_LIBRARY = "kinetic + poly:4 + trig:1@2"
#: The thresholds of the sparse candidates ``"auto"`` tries first (with the default library of the lattice).
SPARSE_THRESHOLDS: tuple[float | str, ...] = (1e-1, 1e-2, "auto")
#: The threshold of the exact-step corrections candidates (:func:`latticedft._models._sparse.exact_step_libraries`):
#: low enough to keep the ``O(h^2)`` corrections of exact samples (their share is about ``h^2/24`` of the largest),
#: high enough to drop the round-off coefficients they get on data that a first-order ``L_d`` obeys exactly.
EXACT_STEP_THRESHOLD = 1e-5
#: ... and of the fifth-order ones, whose ``O(h^4)`` terms have shares of about ``h^4/720``.
EXACT_STEP_THRESHOLD_5 = 1e-9


@dataclass
class SelectionReport:
    """What :func:`select` measured: one row per candidate (the hand-set model first), and the choice.

    ``rows[i]`` holds ``label`` (the candidate's settings in words), ``kind``, ``options``, ``ridge``,
    ``score`` (the largest error of the served held-out fields over the field's largest magnitude; ``inf``
    for a failed fit or serve), ``status`` (``"ok"`` or why it failed), ``n_parameters`` (None when the fit
    failed), ``wall_time`` (s) and, for a sparse candidate learned, ``terms`` (the names of the terms it kept).
    """

    rows: list[dict[str, Any]]
    chosen: int
    reason: str
    hold_out: float
    factor: float
    warnings: list[str] = field(default_factory=list)
    #: The chosen candidate, learned on the whole of every training field.
    model: AbstractLagrangian | None = None
    #: A hand-set score at or below this kept the hand-set model.
    keep_below: float = KEEP_BELOW
    #: Every candidate as learned on the first ``1 - hold_out`` of each field (None where its fit failed), in the
    #: order of ``rows``: the calibration's trial and runner-up (:func:`latticedft._calibrate.calibrate`).
    trials: list[AbstractLagrangian | None] = field(default_factory=list, repr=False, compare=False)
    #: The fields the chosen candidate's and the runner-up's trials (:func:`latticedft._calibrate.runner_up`)
    #: served when scored, one array per training field (from its first two slices, the slices served), in the
    #: order of ``rows``: None for the other candidates, and where a fit failed, a serve stopped or the
    #: candidates' fields so far exceeded ``selection_served_bytes`` (:func:`latticedft.set_options`). The
    #: calibration takes them instead of serving the same trials again.
    served: list[list[np.ndarray] | None] = field(default_factory=list, repr=False, compare=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible (scores of failed candidates as ``None``)."""
        rows = [{**r, "score": _finite(r["score"])} for r in self.rows]
        rows = [{**r, "beyond": _finite(r["beyond"])} if "beyond" in r else r for r in rows]
        return {
            "candidates": rows,
            "chosen": self.chosen,
            "chosen_label": self.rows[self.chosen]["label"],
            "reason": self.reason,
            "hold_out": self.hold_out,
            "factor": self.factor,
            "keep_below": self.keep_below,
            "warnings": list(self.warnings),
        }

    def table_lines(self) -> list[str]:
        """The candidate table, one line per candidate; the chosen one marked ``*``."""
        lines = [f"{'':2}{'score':>10}  {'time':>7}  candidate"]
        for i, r in enumerate(self.rows):
            score = f"{r['score']:10.3e}" if math.isfinite(r["score"]) else f"{'failed':>10}"
            note = "" if r["status"] == "ok" else f"  ({r['status']})"
            if "beyond" in r:
                beyond = f"{r['beyond']:.3e}" if math.isfinite(r["beyond"]) else "failed"
                note += f"  (largest field left out: {beyond})"
            lines.append(f"{'*' if i == self.chosen else ' ':2}{score}  {r['wall_time']:6.1f}s  {r['label']}{note}")
        return lines


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def _label(change: Mapping[str, Any] | AbstractLagrangian) -> str:
    """The candidate in words: its changes to the hand-set settings (``"hand-set"`` for none)."""
    if isinstance(change, AbstractLagrangian):
        return f"{change.kind}({', '.join(f'{k}={v!r}' for k, v in change.options().items())})"
    return ", ".join(f"{k}={v!r}" for k, v in change.items()) or "hand-set"


def sparse_candidates(n: int, m: int) -> list[dict[str, Any]]:
    """The sparse candidates ``"auto"`` tries first on a lattice of ``n`` axes and ``m`` components: the default
    library of :class:`latticedft.SparseLagrangian` at each threshold of :data:`SPARSE_THRESHOLDS`, then for a
    scalar field the library with its lattice corrections (on a time-only lattice also with ``at = "average"``),
    and its powers and its trig functions each alone (on a time-only lattice also :data:`SQUARE_TRIG_LIBRARY`), for
    a vector field the library without the terms singular at ``q = 0`` (``threshold = "auto"``) and, on a time-only
    lattice, :data:`COUPLED_LIBRARY` at each threshold of :data:`SPARSE_THRESHOLDS`.

    >>> sparse_candidates(1, 1)[0]
    {'kind': 'sparse', 'library': 'kinetic + poly:4 + trig:1', 'threshold': 0.1}
    """
    out: list[dict[str, Any]] = [
        {"kind": "sparse", "library": default_library(n, m), "threshold": t} for t in SPARSE_THRESHOLDS
    ]
    out += exact_step_candidates(n, m)
    if m == 1:
        out.append({"kind": "sparse", "library": default_library(n, m, corrections=True), "threshold": "auto"})
        if n == 1:  # a position-dependent mass, met exactly by the trapezoid rule (at both ends of the step)
            out.append({**out[-1], "at": "average"})
        # the on-site powers and trig functions apart: on a field far from 0 they are nearly collinear, and
        # together they fit the data with a few wrong terms that do not extrapolate (phi^4 about its vacuum)
        base = default_library(n, m).replace(" + poly:4 + trig:1", "")
        out += [{"kind": "sparse", "library": f"{base} + {f}", "threshold": "auto"} for f in ("poly:4", "trig:1")]
        if n == 1:  # a potential periodic in q^2 (a double well cos(q^2 - 1)), without the trig of q itself
            out.append({"kind": "sparse", "library": SQUARE_TRIG_LIBRARY, "threshold": "auto"})
    else:  # without the terms singular at q = 0, which refuse data through the origin (a charged particle)
        regular = default_library(n, m).replace(" + norm:-1 + log", "")
        out.append({"kind": "sparse", "library": regular, "threshold": "auto"})
        if n == 1:  # several degrees of freedom of unequal masses coupled through their differences
            coupled = {"kind": "sparse", "library": COUPLED_LIBRARY, "at": "average"}
            out += [{**coupled, "threshold": t} for t in SPARSE_THRESHOLDS]
    return out


def exact_step_candidates(n: int, m: int) -> list[dict[str, Any]]:
    """The exact-step corrections candidates of a time-only lattice: each library of
    :func:`latticedft._models._sparse.exact_step_libraries` in the trapezoid rule (``at = "average"``), those to
    ``O(h^3)`` at :data:`EXACT_STEP_THRESHOLD`, those to ``O(h^5)`` at :data:`EXACT_STEP_THRESHOLD_5`.

    >>> exact_step_candidates(1, 2)[0]["library"]
    'kinetic + norm:-1,-4 + kinetic*norm:-3 + radial*norm:-5'
    """
    steps = [(lib, EXACT_STEP_THRESHOLD) for lib in exact_step_libraries(n, m)]
    steps += [(lib, EXACT_STEP_THRESHOLD_5) for lib in exact_step_libraries(n, m, order=5)]
    return [{"kind": "sparse", "library": lib, "at": "average", "threshold": t} for lib, t in steps]


def is_exact_step(row: Mapping[str, Any]) -> bool:
    """True for a candidate row of an exact-step corrections candidate (its options as
    :func:`exact_step_candidates` made them)."""
    options = row.get("options", {})
    made = exact_step_candidates(1, 1) + exact_step_candidates(1, 2)
    return row.get("kind") == "sparse" and any(
        all(options.get(k) == c[k] for k in ("library", "at", "threshold")) for c in made
    )


def auto_candidates(model: AbstractLagrangian, n: int, ridge: Any = 0.0, m: int | None = None) -> list[dict[str, Any]]:
    """The candidates of ``"auto"`` for a hand-set model on an ``n``-dimensional lattice, as option changes: the
    sparse libraries first (:func:`sparse_candidates`, when the field's components ``m`` are given), then the
    kind's own (:meth:`AbstractLagrangian.auto_candidates`). Polynomial: other orders, time symmetry and input
    scaling flipped, ``ridge="auto"``, and on a 1D lattice feature libraries (``kind = "features"``); feature
    library: differences 2 and 4, then the same; sparse: other thresholds; MLP (and any kind with a ``scale``
    option): input scaling flipped.
    """
    return (sparse_candidates(n, m) if m is not None else []) + model.auto_candidates(n, ridge)


def _spec(model: AbstractLagrangian, change: Mapping[str, Any], ridge: Any) -> tuple[str, dict[str, Any], Any]:
    """``(kind, options, ridge)`` of the hand-set model with ``change`` applied (a new kind starts from its
    defaults)."""
    change = dict(change)
    new_ridge = change.pop("ridge", ridge)
    own = MODELS.name_of(model)
    kind = change.pop("kind", own)
    if kind not in MODELS:
        raise InputError.at("candidates", f"unknown model kind {kind!r} (expected one of {sorted(MODELS)})")
    options = {**(model.options() if kind == own else {}), **change}
    if options.get("preset") is not None:  # a preset (an MLP's) fills the rest; keep only what was set
        options = {k: v for k, v in options.items() if k == "preset" or k in change}
    return kind, options, new_ridge


def _build(model: AbstractLagrangian, kind: str, options: dict[str, Any]) -> AbstractLagrangian:
    stencil = model.stencil if model.has_stencil else None
    try:
        return MODELS[kind](**options, stencil=stencil)
    except LatticeDFTError as exc:
        raise InputError.at("candidates", f"{kind} {options}: {exc}") from None
    except TypeError as exc:
        raise InputError.at("candidates", f"bad options for kind {kind!r} ({exc})") from None


def _short(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= 120 else text[:117] + "..."


def select(
    model: AbstractLagrangian,
    data: Any,
    candidates: str | Sequence[Mapping[str, Any] | AbstractLagrangian] = "auto",
    *,
    hold_out: float = HOLD_OUT,
    factor: float = FACTOR,
    keep_below: float = KEEP_BELOW,
    boundary: BoundaryKinds | None = None,
    **learn_kwargs: Any,
) -> SelectionReport:
    """Choose a model by serving held-out data, then learn it on all of it.

    Every candidate (the hand-set ``model`` first) learns from the first ``1 - hold_out`` of each training
    field's time slices, then serves each whole field from its first two slices (and, on Dirichlet axes,
    its boundary strips). Its score is the largest served error over the field's largest magnitude, worst
    field first; a fit that fails, a serve that stops or a non-finite field scores ``inf``. The best
    candidate is the one with the fewest parameters among those within ``factor`` of the lowest score (a sparse
    candidate, the fewest terms, within :data:`SPARSE_FACTOR` of it first); it
    replaces the hand-set model only when its score is ``factor`` times smaller than the hand-set one's (a sparse
    candidate preferred so replaces a hand-set model of another kind without it) and the hand-set score is above
    ``keep_below`` (or :data:`BEATEN` times the candidate's). With two training fields or more, a hand-set model
    that ``keep_below`` would keep is replaced when the candidate, learned on every field but the one of largest
    amplitude, serves that one ``factor`` times better and within :data:`BEYOND_CEILING` (the row's ``beyond``).
    Under noise (a candidate whose fit corrected it), the sparse candidates whose kept coefficients vary over
    their bagged fits by at most ``SPREAD_WARN`` (the row's ``spread``) come first among the sparse ones. When
    every candidate fails the hand-set model is kept with a warning.

    Parameters
    ----------
    model : AbstractLagrangian
        The hand-set model (unlearned); the first candidate.
    data : DataArray or a list of them
        The training fields (as for :func:`latticedft.learn`), each with at least 4 time slices.
    candidates : "auto" or list
        ``"auto"`` (the sparse libraries first, see :func:`auto_candidates`), or a list whose items are option
        changes of the hand-set model (``{"orders": [2, 2]}``, ``{"kind": "features", "features": ["trig:1"]}``,
        ``{"ridge": "auto"}``) or unlearned models.
    hold_out : float
        Fraction of every field's slices held out, in (0, 1).
    factor : float
        How much better (>= 1) a candidate must score to replace the hand-set model.
    keep_below : float
        A hand-set score at or below this (>= 0) keeps the hand-set model unless a candidate scores
        :data:`BEATEN` times lower: held-out slices served to this relative error no longer rank models by
        their error on other data (0: off).
    boundary, **learn_kwargs
        Passed to :func:`latticedft.learn` (and ``boundary`` to :func:`latticedft.serve`); ``symmetries``
        only to the final fit.

    Returns
    -------
    SelectionReport
        The candidate table and the choice; ``report.model`` is the chosen candidate learned on all the data
        (its ``report_.selection`` holds :meth:`SelectionReport.to_dict`).
    """
    _check_arguments(model, candidates, hold_out, factor, keep_below)
    items = list(data) if isinstance(data, (list, tuple)) else [data]
    if not all(isinstance(d, xr.DataArray) for d in items):
        raise InputError.at("data", "expected a DataArray or a list of DataArrays (time first)")
    first = as_fields(items, boundary)[0]  # checks the fields (one lattice, one layout)
    fields: list[xr.DataArray] = [d.load() for d in items]
    ridge = learn_kwargs.pop("ridge", 0.0)
    learn_kwargs.pop("progress", None)  # every fit here runs without a progress bar
    changes = auto_candidates(model, first.ndim, ridge, first.ncomp) if candidates == "auto" else list(candidates)
    specs = _candidates(model, changes, ridge)
    held = _split(fields, hold_out)
    done, served = [], []
    budget = option("selection_served_bytes")
    for fresh, r, _ in specs:
        out: list[np.ndarray] = []
        done.append(_trial(fresh, r, held, fields, boundary, learn_kwargs, out))
        size = sum(a.nbytes for a in out)
        kept = done[-1][1] is not None and len(out) == len(fields) and size <= budget
        budget -= size if kept else 0
        served.append(out if kept else None)
    rows = [{**row, **measured} for (_, _, row), (measured, _) in zip(specs, done, strict=True)]
    beyond = _beyond(specs, rows, fields, boundary, learn_kwargs) if len(fields) > 1 else None
    chosen, reason, warnings = _choose(rows, factor, keep_below, beyond)
    second = runner_up(rows, chosen)
    chosen_model = copy.deepcopy(specs[chosen][0])
    report = learn(chosen_model, fields, boundary=boundary, ridge=specs[chosen][1], progress=False, **learn_kwargs)
    sel = SelectionReport(
        rows=rows,
        chosen=chosen,
        reason=reason,
        hold_out=float(hold_out),
        factor=float(factor),
        warnings=warnings,
        keep_below=float(keep_below),
        trials=[trial for _, trial in done],
        served=[out if i in (chosen, second) else None for i, out in enumerate(served)],
    )
    report.selection = sel.to_dict()
    report.warnings.extend(warnings)
    sel.model = chosen_model
    return sel


def _check_arguments(
    model: AbstractLagrangian, candidates: Any, hold_out: float, factor: float, keep_below: float
) -> None:
    """Refuse a bad argument of :func:`select` (an ``InputError`` naming it)."""
    if not isinstance(model, AbstractLagrangian):
        raise InputError.at("model", f"expected a latticedft model, got {type(model).__name__}")
    if not (isinstance(hold_out, (int, float)) and not isinstance(hold_out, bool) and 0 < hold_out < 1):
        raise InputError.at("hold_out", f"expected a number in (0, 1), got {hold_out!r}")
    if not (isinstance(factor, (int, float)) and not isinstance(factor, bool) and factor >= 1):
        raise InputError.at("factor", f"expected a number >= 1, got {factor!r}")
    if not (isinstance(keep_below, (int, float)) and not isinstance(keep_below, bool) and keep_below >= 0):
        raise InputError.at("keep_below", f"expected a number >= 0, got {keep_below!r}")
    if isinstance(candidates, str) and candidates != "auto":
        raise InputError.at("candidates", f"expected 'auto' or a list of candidates, got {candidates!r}")


def _candidates(
    model: AbstractLagrangian, changes: Sequence[object], ridge: Any
) -> list[tuple[AbstractLagrangian, Any, dict[str, Any]]]:
    """The candidates, the hand-set model first, once each: ``(fresh model, ridge, table row)``; ``changes``
    are option tables or models (anything else is refused)."""
    specs: list[tuple[AbstractLagrangian, Any, dict[str, Any]]] = []
    seen: set[str] = set()
    for change in [{}, *changes]:
        if isinstance(change, AbstractLagrangian):
            fresh, kind, options, r = change, change.kind, change.options(), ridge
        elif isinstance(change, Mapping):
            kind, options, r = _spec(model, change, ridge)
            fresh = copy.deepcopy(model) if not change else _build(model, kind, options)
            options = fresh.options()
        else:
            raise InputError.at("candidates", f"expected option tables or models, got {type(change).__name__}")
        label = _label(change)
        key = repr((kind, sorted(options.items()), r))
        if key in seen:
            continue
        seen.add(key)
        specs.append((fresh, r, {"label": label, "kind": kind, "options": options, "ridge": r}))
    return specs


def _trial(
    fresh: AbstractLagrangian,
    ridge: Any,
    held: list[xr.DataArray],
    fields: list[xr.DataArray],
    boundary: BoundaryKinds | None,
    learn_kwargs: dict[str, Any],
    served: list[np.ndarray] | None = None,
) -> tuple[dict[str, Any], AbstractLagrangian | None]:
    """One candidate learned on the ``held`` parts and scored on the whole ``fields``: its row's measurements, and
    the learned candidate (None when its fit failed). ``served`` receives the fields it served (one per field
    until a serve stops: :func:`latticedft._learn._heldout.held_out_score`)."""
    trial = copy.deepcopy(fresh)
    t0 = time.perf_counter()
    n_parameters, kept, spread = None, None, None
    try:
        rep = learn(
            trial, held, boundary=boundary, ridge=ridge, progress=False, **{**learn_kwargs, "symmetries": False}
        )
        n_parameters = trial.n_parameters()
        kept = _kept_terms(trial)
        spread = _noisy_spread(trial, rep.noise)
        score, status = _score(trial, fields, boundary, served), "ok"
        if not math.isfinite(score):
            status = "served field not finite"
    except ServeError as exc:
        score, status = math.inf, f"serve stopped: {_short(exc)}"
    except (LatticeDFTError, ArithmeticError, ValueError, RuntimeError) as exc:
        # the package's errors and a candidate's numerics (a division by zero, an overflow, numpy's and torch's
        # linear-algebra errors): that candidate failed, the others are still tried
        score, status = math.inf, f"{type(exc).__name__}: {_short(exc)}"
    row = {"score": score, "status": status, "n_parameters": n_parameters, "wall_time": time.perf_counter() - t0}
    row = row if kept is None else {**row, "terms": kept}
    row = row if spread is None else {**row, "spread": spread}
    return row, (trial if n_parameters is not None else None)


def _noisy_spread(trial: AbstractLagrangian, noise: dict[str, Any] | None) -> float | None:
    """A sparse candidate's largest relative spread of a kept coefficient over its bagged fits, when its fit
    corrected the noise of its data (None otherwise: on clean data small corrections are kept on purpose)."""
    if noise is None or noise.get("method") == "none":
        return None
    spread = largest_spread(trial)
    return None if spread is None else spread[0]


def _beyond(
    specs: list[tuple[AbstractLagrangian, Any, dict[str, Any]]],
    rows: list[dict[str, Any]],
    fields: list[xr.DataArray],
    boundary: BoundaryKinds | None,
    learn_kwargs: dict[str, Any],
) -> Callable[[int], float]:
    """The score beyond the training amplitudes, computed for a candidate when :func:`_choose` asks for it (once):
    the candidate learned on every training field but the one of largest amplitude (:func:`largest_field`) serves
    that one from its first two slices (and its boundary strips); the score and its time go into the row
    (``beyond``, ``wall_time``)."""
    big = largest_field(fields)
    rest = [f for i, f in enumerate(fields) if i != big]

    def score(i: int) -> float:
        if "beyond" not in rows[i]:
            fresh, ridge, _ = specs[i]
            measured, _ = _trial(fresh, ridge, rest, [fields[big]], boundary, learn_kwargs)
            rows[i]["beyond"] = measured["score"]
            rows[i]["wall_time"] += measured["wall_time"]
        return float(rows[i]["beyond"])

    return score


def largest_field(fields: Sequence[xr.DataArray]) -> int:
    """The index of the field of largest amplitude: the largest range of values (maximum less minimum) of one
    component over its sites and slices (the first such field)."""

    def amplitude(f: xr.DataArray) -> float:
        values = np.asarray(f.transpose(..., "component").values if "component" in f.dims else f.values[..., None])
        flat = values.reshape(-1, values.shape[-1])
        return float(np.max(np.ptp(flat, axis=0)))

    return int(np.argmax([amplitude(f) for f in fields]))


def _kept_terms(model: AbstractLagrangian) -> list[str] | None:
    """The names of the terms a learned sparse model kept (None for another kind)."""
    return model.kept_terms() if isinstance(model, SparseLagrangian) else None


def _choose(
    rows: list[dict[str, Any]], factor: float, keep_below: float, beyond: Callable[[int], float] | None = None
) -> tuple[int, str, list[str]]:
    """``(chosen row, reason, warnings)``: the best candidate is the one with the fewest parameters among
    those within ``factor`` of the lowest score, or the sparse one with the fewest terms among the sparse
    candidates within :data:`SPARSE_FACTOR` of it (and below :data:`SPARSE_CEILING`) or below :data:`SPARSE_FLOOR`;
    it replaces the hand-set model
    (row 0) only when ``factor`` times better (a preferred sparse one also when not, unless the hand-set model is
    sparse itself) and the hand-set score is above ``keep_below``, or else when it scores ``factor`` times lower
    than the hand-set model and within :data:`BEYOND_CEILING` on ``beyond`` (a row's score beyond the training
    amplitudes: :func:`_beyond`; None: not measured, with fewer than two training fields)."""
    scores = [r["score"] for r in rows]
    lowest = min(scores)
    near = [i for i, sc in enumerate(scores) if math.isfinite(sc) and sc <= factor * lowest]
    best = min(near, key=lambda i: (rows[i]["n_parameters"], scores[i])) if near else int(np.argmin(scores))
    sparse = [
        i
        for i, sc in enumerate(scores)
        if i > 0
        and rows[i].get("kind") == "sparse"
        and math.isfinite(sc)
        and sc <= max(min(SPARSE_FACTOR * lowest, SPARSE_CEILING), SPARSE_FLOOR)
    ]
    stable = [i for i in sparse if rows[i].get("spread", 0.0) <= SPREAD_WARN]
    sparse = stable or sparse  # under noise, the candidates whose kept coefficients hold over the bags
    dense = best
    if sparse and best not in sparse:  # a few symbolic terms near the lowest score: they extrapolate
        best = min(sparse, key=lambda i: (rows[i]["n_parameters"], scores[i]))
    if best in sparse:  # the exact step's corrections, when they serve better, are physics, not extra terms
        best = _exact_step_over(rows, sparse, best, factor)
    if not math.isfinite(scores[best]):
        warning = (
            f"model selection: every one of {len(rows)} candidates failed to serve the held-out data "
            "(their reasons are in the candidate table); kept the hand-set model, which may not serve"
        )
        return 0, "every candidate failed; kept the hand-set model", [warning]
    if best != 0 and scores[0] <= keep_below and not scores[best] * BEATEN <= scores[0]:
        tied = _tied_sparse(rows, sparse, keep_below)
        if tied is not None:  # below keep_below the scores do not rank models: the fewest terms decide
            return (
                tied,
                f"{rows[tied]['label']} scored {scores[tied]:.3e} and the hand-set model {scores[0]:.3e}, both at "
                f"or below keep_below = {keep_below:g}, where scores do not rank models: the sparse one is kept",
                [],
            )
        if dense != 0 and scores[dense] * BEATEN <= scores[0]:  # never keep a hand-set model beaten 100x
            return (
                dense,
                f"{rows[dense]['label']} scored {scores[dense]:.3e}, {BEATEN:g}x below the hand-set model's "
                f"{scores[0]:.3e} (the sparse {rows[best]['label']} scored {scores[best]:.3e})",
                [],
            )
        if beyond is not None and _extrapolates_better(beyond, best, factor):
            return (
                best,
                f"the hand-set model scored {scores[0]:.3e}, at or below keep_below = {keep_below:g}, but "
                f"{rows[best]['label']} (scored {scores[best]:.3e}) served the training field of largest amplitude, "
                f"learned without it, to {beyond(best):.3e} against the hand-set model's {beyond(0):.3e}",
                [],
            )
        return (
            0,
            f"the hand-set model scored {scores[0]:.3e}, at or below keep_below = {keep_below:g}: kept "
            f"({rows[best]['label']} scored {scores[best]:.3e}{_beyond_note(rows, best)})",
            [],
        )
    # a sparse candidate preferred near the lowest score replaces a dense hand-set model it does not beat 2x
    preferred = best in sparse and rows[0].get("kind") != "sparse"
    if best == 0 or not (scores[best] * factor < scores[0] or preferred):
        reason = (
            f"the hand-set model scored {scores[0]:.3e}; no candidate was {factor:g}x better"
            if best != 0
            else f"the hand-set model scored best ({scores[0]:.3e})"
        )
        return 0, reason, []
    return best, f"{rows[best]['label']} scored {scores[best]:.3e} against the hand-set model's {scores[0]:.3e}", []


def _extrapolates_better(beyond: Callable[[int], float], best: int, factor: float) -> bool:
    """Whether candidate ``best`` serves beyond the training amplitudes within :data:`BEYOND_CEILING` and ``factor``
    times better than the hand-set model (row 0); the hand-set model is not scored when ``best`` misses the
    ceiling."""
    mine = beyond(best)
    return mine <= BEYOND_CEILING and mine * factor < beyond(0)


def _beyond_note(rows: list[dict[str, Any]], best: int) -> str:
    """``", beyond the training amplitudes 5.8e-02 against the hand-set model's failed"`` where measured."""
    if "beyond" not in rows[best]:
        return ""
    theirs = rows[0].get("beyond")
    against = "" if theirs is None else f" against the hand-set model's {theirs:.3e}"
    return f", beyond the training amplitudes {rows[best]['beyond']:.3e}{against}"


def _tied_sparse(rows: list[dict[str, Any]], sparse: list[int], keep_below: float) -> int | None:
    """The sparse candidate (of ``sparse``) with the fewest terms among those scored at or below ``keep_below``,
    when the hand-set model (row 0) is not sparse itself; else None. Below ``keep_below`` a lower score no longer
    predicts a lower error elsewhere, so a dense hand-set model there is no better than a few symbolic terms
    there, and the few terms (a closed form) are kept, as :data:`SPARSE_FLOOR` prefers them above it."""
    if rows[0].get("kind") == "sparse":
        return None
    tied = [i for i in sparse if rows[i]["score"] <= keep_below]
    if not tied:
        return None
    return _exact_step_over(rows, tied, min(tied, key=lambda i: (rows[i]["n_parameters"], rows[i]["score"])), FACTOR)


def _exact_step_over(rows: list[dict[str, Any]], pool: list[int], best: int, factor: float) -> int:
    """The exact-step corrections candidate of ``pool`` with the lowest score when it scores ``factor`` times
    below the sparse candidate ``best`` and keeps every term ``best`` kept (else ``best``): its extra terms are then
    the ``O(h^2)`` corrections of one step of the continuous flow to the same physics (:func:`exact_step_candidates`),
    which serve a test beyond the training better than the true terms alone, and which it drops on data that a
    first-order ``L_d`` obeys exactly. (Without the same terms it fits another potential, with large corrections:
    paper Example 2's ``cos(q^2 - 1)`` by ``trig:3`` and ``Dtq^4`` terms, which serve its test 90x the leapfrog.)"""
    physics = set(rows[best].get("terms") or ["?"])  # its terms, which the corrections must come on top of
    better = [
        i
        for i in pool
        if is_exact_step(rows[i])
        and rows[i]["score"] * factor < rows[best]["score"]
        and physics <= set(rows[i]["terms"])
    ]
    return min(better, key=lambda i: rows[i]["score"]) if better else best
