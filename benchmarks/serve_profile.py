"""Where a serve's time goes: the profiles that docs/performance.md quotes, on the serve-nd benchmark's models and
lattices (:mod:`benchmarks.serve_nd`: the learned (2, 12) polynomial, the analytic sine-Gordon, the in-place
numpy leapfrog).

    OMP_NUM_THREADS=1 PYTHONPATH=. python -m benchmarks.serve_profile [--part NAME ...] [--quick]

Every time is CPU time (``time.process_time``), the least of several calls, and most figures are given in
leapfrog steps of the same lattice measured in the same process (the least CPU time of three runs of the
in-place leapfrog), so that the load of other work moves them less than it moves absolute times; the load
average (as ``uptime`` prints it) is printed before and after each part. Where a module-level switch still
selects the way before a change (``_newton.CHORD_PREDICT``, ``FRESH_FIRST_ON``, ``_solvers.COMPILED_GMRES`` with
``_slices.COMPILED_ASSEMBLY``, the affine probe's kept answer), both ways are served in one process, in rounds
of alternating order, and their served fields compared. The parts (``--part``, repeatable; all by default):

- ``slice-work``: slice-Newton's work per slice of the polynomial rows 2+1D 128^2 and 3+1D 32^3 (10 slices):
  evaluations (with and without the Hessian blocks), GMRES solves and fresh Jacobians per solved slice, and
  each one's cost (an evaluation's pass over the cells and its residual's gather apart), by a timer around every
  call of ``FoldedSlices.evaluate`` (and the ``columns`` and ``both_columns`` passes it makes),
  ``_newton._fresh_blocks``, ``_newton._factorise`` and the linear solve it returns, over 7 serves after a
  warm-up; the shares of a serve that the evaluations, GMRES solves and fresh Jacobians take.
- ``chord``: slice-Newton's chord rules, by ``_newton``'s switches: neither, a fresh Jacobian after a slow chord
  (``FRESH_FIRST_ON``), and with the chord's rate test (``CHORD_PREDICT``, the default): evaluations a slice and
  the CPU time against the leapfrog, 3+1D 32^3 and 64^3, 2+1D 128^2 (5 rounds, the least of 3 serves each way a
  round).
- ``lattice-new``: the analytic rows served with the kept per-lattice tables (slice system, index tables) and
  after dropping them: ``serve`` of 4 slices and of all the row's slices, the least of 5; the solve per slice
  (their difference), the fixed cost per serve, the same with the tables dropped before each call.
- ``fixed-part``: the compiled ``slice_steps`` of the analytic rows (through ``FusedSlices.solve_many``, timed
  inside 15 serves): ns per site and slice against the leapfrog's ns per site and step, and its share of the serve.
- ``faults``: serves of the analytic rows (1+1D 16384 x 66, 2+1D 128^2 x 66, 3+1D 32^3 x 63) with each result
  held until the next serve returns, as the serve-nd benchmark times them, and dropped before it (3 rounds of 5
  serves each way, the order alternated): the minor page faults a serve (their median and most) and the least
  and median CPU time.
- ``linalg``: the compiled GMRES and Jacobian assembly (``_solvers.COMPILED_GMRES`` and
  ``_slices.COMPILED_ASSEMBLY`` together) off and on, the polynomial rows (5 rounds, the least of 3 serves each
  way a round), and a fresh Jacobian's own work after its evaluation each way (3+1D 32^3).
- ``fit3d``: serves of 1, 2, 4, 8 and 16 solved slices of the polynomial rows (3+1D 32^3 and 64^3, 2+1D 128^2
  and 256^2; the least of 5, the sizes alternated) fitted by a line: the fixed cost per serve and the cost per
  slice, per site and slice against the leapfrog's per site and step.
- ``affine``: the affine decision per serve (``_field._affine_prefix``: the probe and its scale) with the probe's
  kept answer dropped before each serve and kept (``_affine._PROBED``), the 2+1D polynomial rows and 3+1D 32^3
  (3 rounds, the least of 7 serves each way a round); the serves themselves beside.

``--quick``: tiny lattices and fewer repeats (seconds; a check that every part runs, not a measurement).
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import math
import resource
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

import latticedft as ldft
from latticedft._serve import _affine, _field, _folded, _fused, _newton, _solvers

from ._common import Table, load_average, print_table
from .serve_nd import _field as lattice_field
from .serve_nd import _forget_lattices, _initial, leapfrog, learned_polynomial, sine_gordon, training_field

NAME = "serve-profile"

#: The slice system's module (``latticedft._serve`` binds the name ``_slices`` to another object).
_slices = importlib.import_module("latticedft._serve._slices")


# --- shared pieces -------------------------------------------------------------------------------------------


class Setup:
    """One row's lattice: its initial field (two slices), sizes and the leapfrog's least CPU time per step."""

    def __init__(self, ndim: int, n: int, slices: int) -> None:
        self.ndim, self.n, self.slices = ndim, n, slices
        self.u0, self.h, self.dt = _initial(ndim, n)
        self.da = lattice_field(np.stack([self.u0, self.u0]), self.h, self.dt)
        self.sites = n**ndim
        self.step = math.inf
        self.leapfrog_again(5)

    def leapfrog_again(self, repeat: int = 1) -> None:
        """The leapfrog's CPU time per step timed again (``repeat`` runs of the row's solved slices, at least 8
        steps); :attr:`step` keeps the least of all."""
        steps = max(self.slices - 2, 8)
        cpu = least_cpu(lambda: leapfrog(self.u0, self.u0, steps, self.dt, self.h), repeat)[0]
        self.step = min(self.step, cpu / steps)

    @property
    def label(self) -> str:
        return f"{self.n}^{self.ndim} x {self.slices}" if self.ndim > 1 else f"{self.n} x {self.slices}"

    def serve(self, model: Any, slices: int | None = None) -> Any:
        return ldft.serve(model, self.da, slices=slices or self.slices, progress=False)

    def least(self, model: Any, slices: int | None = None, repeat: int = 1) -> tuple[float, Any]:
        """The least CPU time of ``repeat`` serves of ``slices`` (the row's by default) and the last result."""
        return least_cpu(lambda: self.serve(model, slices), repeat)


def least_cpu(fn: Callable[[], Any], repeat: int) -> tuple[float, Any]:
    """The least CPU time of ``repeat`` calls of ``fn`` and the last result (each result dropped before the next
    call, so that a served field's memory is free for the next serve, as where a program serves one field after
    another)."""
    best, out = math.inf, None
    for _ in range(repeat):
        out = None
        c0 = time.process_time()
        out = fn()
        best = min(best, time.process_time() - c0)
    return best, out


def field_diff(a: Any, b: Any) -> float:
    """The largest difference of two served fields over the largest value of the first."""
    x, y = np.asarray(a.field.values), np.asarray(b.field.values)
    return float(np.abs(x - y).max() / np.abs(x).max())


@contextlib.contextmanager
def switched(module: Any, names: tuple[str, ...], value: Any) -> Iterator[None]:
    """Module-level switches ``names`` of ``module`` set to ``value`` for a block."""
    before = {k: getattr(module, k) for k in names}
    try:
        for k in names:
            setattr(module, k, value)
        yield
    finally:
        for k, v in before.items():
            setattr(module, k, v)


class Timers:
    """Calls and CPU seconds per part of a serve, from timers wrapped around functions (:meth:`timed`)."""

    def __init__(self) -> None:
        self.calls: dict[str, int] = {}
        self.cpu: dict[str, float] = {}

    def reset(self) -> None:
        self.calls.clear()
        self.cpu.clear()

    def timed(self, name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            c0 = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                self.cpu[name] = self.cpu.get(name, 0.0) + time.process_time() - c0
                self.calls[name] = self.calls.get(name, 0) + 1

        return wrapper

    def per_call(self, name: str) -> float:
        return self.cpu.get(name, 0.0) / self.calls[name] if self.calls.get(name) else math.nan


@contextlib.contextmanager
def slice_newton_timers() -> Iterator[Timers]:
    """Timers around slice-Newton's parts: an evaluation of the folded kernels (``evaluate``, ``evaluate+blocks``
    where the Hessian blocks come in the same pass; within them, the kernels' pass over the cells, ``pass`` and
    ``pass+blocks``, and ``gather``: the rest, the residual read per equation row), a fresh Jacobian's own work
    (``fresh``: its blocks' sizes and singular values; ``factorise``: the solver's choice, the assembly and
    preconditioner) and a linear solve (``solve``). The functions are restored after the block."""
    t = Timers()
    cls = _folded.FoldedSlices
    evaluate, columns, both = cls.evaluate, cls.columns, cls.both_columns
    fresh, factorise = _newton._fresh_blocks, _newton._factorise
    inside = [False]

    def timed_evaluate(self: Any, flat: Any, vol: float, i: int, g_prev: Any, blocks: bool = False) -> Any:
        passes = t.cpu.get("pass", 0.0) + t.cpu.get("pass+blocks", 0.0)
        c0 = time.process_time()
        inside[0] = True
        try:
            return evaluate(self, flat, vol, i, g_prev, blocks)
        finally:
            inside[0] = False
            spent = time.process_time() - c0
            passes = t.cpu.get("pass", 0.0) + t.cpu.get("pass+blocks", 0.0) - passes
            for name, cpu in (("evaluate+blocks" if blocks else "evaluate", spent), ("gather", spent - passes)):
                t.cpu[name] = t.cpu.get(name, 0.0) + cpu
                t.calls[name] = t.calls.get(name, 0) + 1

    def timed_columns(self: Any, *args: Any) -> Any:
        return t.timed("pass", columns)(self, *args) if inside[0] else columns(self, *args)

    def timed_both(self: Any, *args: Any) -> Any:
        return t.timed("pass+blocks", both)(self, *args) if inside[0] else both(self, *args)

    def timed_factorise(sys: Any, blocks: Any, vol: float, cache: dict[str, Any], tol: float) -> None:
        t.timed("factorise", factorise)(sys, blocks, vol, cache, tol)
        cache["solve"] = t.timed("solve", cache["solve"])

    for name, fn in (("evaluate", timed_evaluate), ("columns", timed_columns), ("both_columns", timed_both)):
        setattr(cls, name, fn)
    _newton._fresh_blocks = t.timed("fresh", fresh)
    _newton._factorise = timed_factorise
    try:
        yield t
    finally:
        for name, fn in (("evaluate", evaluate), ("columns", columns), ("both_columns", both)):
            setattr(cls, name, fn)
        _newton._fresh_blocks = fresh
        _newton._factorise = factorise


@functools.lru_cache(maxsize=4)
def untuned_polynomial(ndim: int, orders: tuple[int, int], quick: bool) -> ldft.PolynomialLagrangian:
    """A polynomial of ``orders``, not time-symmetric, learned as :func:`benchmarks.serve_nd.learned_polynomial`
    learns the benchmark's (the same field): one the slice-Newton rules were not tuned on."""
    model = ldft.PolynomialLagrangian(orders=orders, time_symmetric=False)
    ldft.learn(model, training_field(ndim, quick), progress=False)
    return model


def _poly_rows(quick: bool, rows: list[tuple[int, int, int]]) -> list[tuple[int, int, int]]:
    """(dims, sites per axis, slices) of the rows, tiny when ``quick``."""
    if not quick:
        return rows
    small = {1: 64, 2: 12, 3: 6}
    seen: list[tuple[int, int, int]] = []
    for d, _, s in rows:
        row = (d, small[d], min(s, 6))
        if row not in seen:
            seen.append(row)
    return seen


# --- the parts -----------------------------------------------------------------------------------------------


def slice_work(quick: bool) -> Table:
    """Slice-Newton's work per solved slice of the polynomial rows, each part in leapfrog steps."""
    table = Table(
        "slice-work",
        "Slice-Newton's work per slice, learned polynomial (2, 12): counts per solved slice, costs in leapfrog steps",
        [
            "lattice",
            "leapfrog step (ms)",
            "evaluations / slice",
            "of them with blocks",
            "GMRES solves / slice",
            "fresh Jacobians / slice",
            "evaluation",
            "its pass",
            "pass with blocks",
            "residual's gather",
            "GMRES solve",
            "fresh Jacobian's own work",
            "whole slice",
            "share of the serve: evaluations / GMRES / fresh Jacobians",
        ],
    )
    repeat = 2 if quick else 7
    for ndim, n, nt in _poly_rows(quick, [(2, 128, 10), (3, 32, 10)]):
        s = Setup(ndim, n, nt)
        model = learned_polynomial(ndim, quick)
        s.serve(model, 3)  # warm-up: kernels, tables
        per: dict[str, list[float]] = {}
        counts: dict[str, int] = {}
        serve, shares = math.inf, (math.nan, math.nan, math.nan)
        with slice_newton_timers() as t:
            for _ in range(repeat):
                t.reset()
                c0 = time.process_time()
                s.serve(model)
                cpu = time.process_time() - c0
                evals = t.cpu.get("evaluate", 0.0) + t.cpu.get("evaluate+blocks", 0.0)
                calls = t.calls.get("evaluate", 0) + t.calls.get("evaluate+blocks", 0)
                own = t.cpu.get("fresh", 0.0) + t.cpu.get("factorise", 0.0)
                for k, v in (
                    ("evaluation", evals / calls),
                    ("pass", t.per_call("pass")),
                    ("pass+blocks", t.per_call("pass+blocks")),
                    ("gather", t.per_call("gather")),
                    ("solve", t.per_call("solve")),
                    ("fresh", own / t.calls["fresh"] if t.calls.get("fresh") else math.nan),
                ):
                    per.setdefault(k, []).append(v)
                if cpu < serve:
                    serve, shares = cpu, (evals / cpu, t.cpu.get("solve", 0.0) / cpu, own / cpu)
                counts = dict(t.calls)
                s.leapfrog_again()
        solved = nt - 2
        evals_n = counts.get("evaluate", 0) + counts.get("evaluate+blocks", 0)
        table.rows.append(
            [
                f"{ndim}+1D {s.label}",
                s.step * 1e3,
                evals_n / solved,
                counts.get("evaluate+blocks", 0) / solved,
                counts.get("solve", 0) / solved,
                counts.get("fresh", 0) / solved,
                *(
                    float(np.nanmin(per[k])) / s.step
                    for k in ("evaluation", "pass", "pass+blocks", "gather", "solve", "fresh")
                ),
                serve / solved / s.step,
                " / ".join(f"{v:.0%}" for v in shares),
            ]
        )
    table.notes.append(
        f"Counts of the last of {repeat} serves after a warm-up (they are the same every serve); each cost the least "
        "over the serves of its mean per call, CPU time over the leapfrog's least step in the process (timed again "
        "after every serve). An evaluation: the folded kernels' pass over the slice's cells (with the Hessian "
        "blocks' columns where a fresh Jacobian reads them) and the residual read per equation row (the rest of "
        "the call). A fresh Jacobian's own work: after its evaluation, its blocks' sizes and singular values, the "
        "solver's choice, the assembly and preconditioner. 'whole slice': the least serve over the solved slices "
        "(the field's first slice and the range check included); the shares are of that serve."
    )
    return table


#: The ways of slice-Newton's chord, by ``_newton``'s switches: neither rule (every slice starts with the chord of the
#: last Jacobian, kept while it cuts the residual a hundredfold), a fresh start after a slow chord
#: (``FRESH_FIRST_ON``) alone, and with the chord's rate test (``CHORD_PREDICT``): the default.
CHORD_WAYS: dict[str, dict[str, Any]] = {
    "neither": {"CHORD_PREDICT": False, "FRESH_FIRST_ON": 1 << 30},
    "fresh first": {"CHORD_PREDICT": False},
    "both": {},
}


@contextlib.contextmanager
def chord_way(name: str) -> Iterator[None]:
    """``_newton``'s switches of the way ``name`` of :data:`CHORD_WAYS` for a block."""
    way = CHORD_WAYS[name]
    before = {k: getattr(_newton, k) for k in way}
    try:
        for k, v in way.items():
            setattr(_newton, k, v)
        yield
    finally:
        for k, v in before.items():
            setattr(_newton, k, v)


def chord(quick: bool) -> Table:
    """Slice-Newton's chord rules (:data:`CHORD_WAYS`) one after the other, in rounds of alternating order."""
    names = list(CHORD_WAYS)
    table = Table(
        "chord",
        "Slice-Newton's chord: neither rule -> fresh start after a slow chord -> and the chord's rate test (default), "
        "learned polynomials",
        [
            "lattice",
            "orders",
            "leapfrog step (ms)",
            "evaluations / slice",
            *(f"CPU / leapfrog, {k} (rounds)" for k in names),
            "least serve (ms)",
            "fields, each way against the one before: max difference / max",
            "field's largest value",
        ],
    )
    rounds, repeat = (2, 1) if quick else (5, 3)
    rows = [(3, 32, 10, (2, 12)), (3, 64, 9, (2, 12)), (2, 128, 10, (2, 12))]
    rows += [(3, 32, 12, (2, 6)), (2, 128, 12, (2, 6)), (3, 24, 12, (2, 8))]
    if quick:
        rows = [(3, 6, 6, (2, 12)), (2, 12, 6, (2, 12))]  # (a new polynomial class builds its kernels: seconds)
    for ndim, n, nt, orders in rows:
        s = Setup(ndim, n, nt)
        model = learned_polynomial(ndim, quick) if orders == (2, 12) else untuned_polynomial(ndim, orders, quick)
        s.serve(model, 3)
        cpu: dict[str, list[float]] = {k: [] for k in names}
        served: dict[str, Any] = {}
        for r in range(rounds):
            for name in names if r % 2 == 0 else names[::-1]:
                with chord_way(name):
                    t, served[name] = s.least(model, repeat=repeat)
                cpu[name].append(t)
            s.leapfrog_again()
        lf = s.step * (nt - 2)
        table.rows.append(
            [
                f"{ndim}+1D {s.label}",
                f"{orders}" + ("" if orders == (2, 12) else ", not time-symmetric"),
                s.step * 1e3,
                " -> ".join(f"{served[k].newton_iterations / (nt - 2):.2f}" for k in names),
                *(" / ".join(f"{v / lf:.1f}" for v in cpu[k]) for k in names),
                " -> ".join(f"{min(cpu[k]) * 1e3:.1f}" for k in names),
                " / ".join(f"{field_diff(served[b], served[a]):.1e}" for a, b in zip(names, names[1:])),
                float(np.abs(np.asarray(served["both"].field.values)).max()),
            ]
        )
    table.notes.append(
        f"{rounds} rounds, the order alternated; each way of a round the least CPU time of {repeat} serves after a "
        "warm-up, over the least CPU time of the leapfrog's steps (the row's solved slices) in this process (timed "
        "again every round). 'neither': `_newton.CHORD_PREDICT = False` and `FRESH_FIRST_ON` never reached; "
        "'fresh first': `CHORD_PREDICT = False`; 'both': the default. The benchmark's polynomial (2, 12) on its "
        "rows, and polynomials the rules were not tuned on (orders (2, 6) and (2, 8), not time-symmetric, learned "
        "on the same field)."
    )
    return table


def lattice_new(quick: bool) -> Table:
    """The analytic rows' serves with the kept per-lattice tables and after dropping them."""
    table = Table(
        "lattice-new",
        "Analytic sine-Gordon rows: solve per slice and fixed cost per serve, tables kept and dropped (leapfrog steps)",
        [
            "lattice",
            "leapfrog step (ms)",
            "serve / leapfrog",
            "solve per slice",
            "fixed per serve",
            "fixed, lattice new",
        ],
    )
    rows = [(1, 16384, 66), (2, 128, 66), (2, 256, 32), (3, 32, 63), (3, 48, 20), (3, 64, 9)]
    if quick:
        rows = [(1, 256, 12), (2, 16, 12), (3, 8, 12)]
    repeat = 2 if quick else 5
    model = sine_gordon()
    for ndim, n, nt in rows:
        s = Setup(ndim, n, nt)
        s.serve(model, 3)
        t4 = t_all = t_new = math.inf
        for _ in range(repeat):
            t4 = min(t4, s.least(model, 4)[0])
            t_all = min(t_all, s.least(model, repeat=1)[0])
            _forget_lattices()
            t_new = min(t_new, s.least(model, repeat=1)[0])
            s.leapfrog_again()
        per = (t_all - t4) / (nt - 4)
        table.rows.append(
            [
                f"{ndim}+1D {s.label}",
                s.step * 1e3,
                t_all / (s.step * (nt - 2)),
                per / s.step,
                (t_all - per * (nt - 2)) / s.step,
                (t_new - per * (nt - 2)) / s.step,
            ]
        )
    table.notes.append(
        f"`serve` of 4 slices and of all the row's slices after a warm-up, the least CPU time of {repeat} (the three "
        "calls in turn); solve per slice: their difference per slice (Python around the kernel included); fixed: the "
        "rest of a serve of all the slices; lattice new: the same after dropping the slice system and index tables "
        "kept for the last lattices (`_field._SYSTEMS`, `_fused._TABLES`)."
    )
    return table


def fixed_part(quick: bool) -> Table:
    """The compiled ``slice_steps`` timed inside serves of the analytic rows."""
    table = Table(
        "fixed-part",
        "The compiled slice_steps in serves of the analytic sine-Gordon rows",
        [
            "lattice",
            "leapfrog (ns / site and step)",
            "slice_steps (ns / site and slice)",
            "slice_steps / leapfrog",
            "serve (ms)",
            "slice_steps' share of the serve",
            "serve / leapfrog",
        ],
    )
    rows = [(1, 16384, 66), (1, 4096, 66), (2, 128, 66), (3, 32, 63)]
    if quick:
        rows = [(1, 256, 12)]
    repeat = 3 if quick else 15
    model = sine_gordon()
    t = Timers()
    many = _fused.FusedSlices.solve_many
    slices_solved = [0]

    def timed_many(self: Any, flat: Any, i: int, stop: int, *args: Any, **kwargs: Any) -> Any:
        out = t.timed("slice_steps", many)(self, flat, i, stop, *args, **kwargs)
        slices_solved[0] += int(out[0]) - i
        return out

    for ndim, n, nt in rows:
        s = Setup(ndim, n, nt)
        s.serve(model, 3)
        best_kernel, best_serve, per_slices = math.inf, math.inf, 0
        _fused.FusedSlices.solve_many = timed_many  # type: ignore[method-assign]
        try:
            for _ in range(repeat):
                t.reset()
                slices_solved[0] = 0
                serve = s.least(model)[0]  # the served field dropped
                if t.calls.get("slice_steps") and t.cpu["slice_steps"] / slices_solved[0] < best_kernel:
                    best_kernel, per_slices = t.cpu["slice_steps"] / slices_solved[0], slices_solved[0]
                best_serve = min(best_serve, serve)
                s.leapfrog_again()
        finally:
            _fused.FusedSlices.solve_many = many  # type: ignore[method-assign]
        table.rows.append(
            [
                f"{ndim}+1D {s.label}",
                s.step / s.sites * 1e9,
                best_kernel / s.sites * 1e9,
                best_kernel / s.step,
                best_serve * 1e3,
                best_kernel * per_slices / best_serve,
                best_serve / (s.step * (nt - 2)),
            ]
        )
    table.notes.append(
        f"{repeat} serves after a warm-up, each served field dropped before the next serve; the least CPU time of "
        "slice_steps's calls (FusedSlices.solve_many: every slice after the first, which chooses the solver) per "
        "slice solved in them, and of the serves; the serve's share: that time per slice times the slices it "
        "solved over the least serve."
    )
    return table


def faults(quick: bool) -> Table:
    """Serves of the analytic rows with each result held until the next serve returns (the serve-nd benchmark's
    pattern) and dropped before it: page faults and CPU time a serve."""
    table = Table(
        "faults",
        "Page faults of serves of the analytic sine-Gordon rows, each result held until the next returns -> dropped",
        [
            "lattice",
            "field (pages)",
            "faults / serve, held -> dropped: median (most)",
            "serve, held -> dropped: least / median (ms)",
            "median difference / leapfrog step and slice",
        ],
    )
    rows = [(1, 256, 12)] if quick else [(1, 16384, 66), (2, 128, 66), (3, 32, 63)]
    rounds, repeat = (2, 2) if quick else (3, 5)
    model = sine_gordon()
    page = resource.getpagesize()
    for ndim, n, nt in rows:
        s = Setup(ndim, n, nt)
        s.serve(model, 3)
        cpu: dict[bool, list[float]] = {True: [], False: []}
        counts: dict[bool, list[int]] = {True: [], False: []}
        pages = 0
        for r in range(rounds):
            for held in (True, False) if r % 2 == 0 else (False, True):
                kept = s.serve(model) if held else None  # the result held while the next serve runs
                for _ in range(repeat):
                    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
                    c0 = time.process_time()
                    out = s.serve(model)
                    spent = time.process_time() - c0
                    counts[held].append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
                    cpu[held].append(spent)
                    pages = -(-np.asarray(out.field.values).nbytes // page)
                    kept = out if held else None
                    out = None
                del kept
            s.leapfrog_again()
        table.rows.append(
            [
                f"{ndim}+1D {s.label}",
                pages,
                " -> ".join(f"{np.median(counts[k]):.0f} ({max(counts[k])})" for k in (True, False)),
                " -> ".join(f"{min(cpu[k]) * 1e3:.2f} / {np.median(cpu[k]) * 1e3:.2f}" for k in (True, False)),
                float(np.median(cpu[True]) - np.median(cpu[False])) / (s.step * (nt - 2)),
            ]
        )
    table.notes.append(
        f"{rounds} rounds, the order alternated; each way of a round {repeat} timed serves after a warm-up (held: "
        "each served field kept until the next serve returns, as benchmarks.serve_nd times its rows; dropped: freed "
        f"before the next serve); the median and the most of the minor page faults a serve (getrusage) and the "
        f"least and median CPU time; the field's size in pages of {page} bytes; the difference of the median serves "
        "over the leapfrog's least step in the same process times the solved slices."
    )
    return table


def linalg(quick: bool) -> Table:
    """The compiled GMRES and Jacobian assembly off and on, in rounds of alternating order."""
    table = Table(
        "linalg",
        "Slice-Newton's linear algebra compiled (_solvers.COMPILED_GMRES, _slices.COMPILED_ASSEMBLY) off -> on",
        [
            "lattice",
            "leapfrog step (ms)",
            "CPU on / off (rounds)",
            "least serve off -> on (ms)",
            "CPU / leapfrog off -> on",
            "fresh Jacobian's own work off -> on (ms)",
            "linear solve off -> on (ms)",
            "fields, max |on - off| / max",
        ],
    )
    rounds, repeat = (2, 1) if quick else (5, 3)
    for ndim, n, nt in _poly_rows(quick, [(3, 32, 10), (3, 64, 9), (2, 128, 10), (2, 256, 10), (1, 16384, 10)]):
        s = Setup(ndim, n, nt)
        model = learned_polynomial(ndim, quick)
        s.serve(model, 3)
        cpu: dict[bool, list[float]] = {False: [], True: []}
        own: dict[bool, float] = {False: math.inf, True: math.inf}
        solve: dict[bool, float] = {False: math.inf, True: math.inf}
        served: dict[bool, Any] = {}
        for r in range(rounds):
            for on in (False, True) if r % 2 == 0 else (True, False):
                with switched(_solvers, ("COMPILED_GMRES",), on), switched(_slices, ("COMPILED_ASSEMBLY",), on):
                    cpu[on].append(s.least(model, repeat=repeat)[0])
                    with slice_newton_timers() as t:
                        served[on] = s.serve(model)
                    if t.calls.get("fresh"):
                        own[on] = min(own[on], (t.cpu["fresh"] + t.cpu.get("factorise", 0.0)) / t.calls["fresh"])
                    solve[on] = min(solve[on], t.per_call("solve"))
            s.leapfrog_again()
        lf = s.step * (nt - 2)
        table.rows.append(
            [
                f"{ndim}+1D {s.label}",
                s.step * 1e3,
                " / ".join(f"{a / b:.2f}" for a, b in zip(cpu[True], cpu[False])),
                f"{min(cpu[False]) * 1e3:.1f} -> {min(cpu[True]) * 1e3:.1f}",
                f"{min(cpu[False]) / lf:.1f} -> {min(cpu[True]) / lf:.1f}",
                f"{own[False] * 1e3:.2f} -> {own[True] * 1e3:.2f}",
                f"{solve[False] * 1e3:.3f} -> {solve[True] * 1e3:.3f}",
                field_diff(served[True], served[False]),
            ]
        )
        if ndim == 3 and len(table.rows) == 1:  # the first 3+1D row: how far Newton's tolerance leaves the fields
            tight = [ldft.serve(model, s.da, slices=nt, rtol=r, progress=False) for r in (1e-11, 1e-12, 1e-13)]
            table.notes.append(
                f"{s.label}: the served field (rtol 1e-10, the default) against the same served with rtol 1e-11, "
                "1e-12 and 1e-13, the largest difference over the largest value: "
                + ", ".join(f"{field_diff(x, served[True]):.3g}" for x in tight)
                + "."
            )
    table.notes.append(
        f"{rounds} rounds, the order alternated; each way of a round the least CPU time of {repeat} serves after a "
        "warm-up, then one serve with timers around a fresh Jacobian's own work (after its evaluation: its blocks' "
        "sizes and singular values, the solver's choice, the assembly and preconditioner), the least mean per "
        "Jacobian over the rounds; a linear solve (GMRES, or the band LU's in 1+1D) the same way."
    )
    return table


def fit3d(quick: bool) -> Table:
    """Serves of 1, 2, 4, 8 and 16 solved slices fitted by a line: a fixed cost per serve and a cost per slice."""
    table = Table(
        "fit3d",
        "Learned polynomial serves of 1-16 solved slices fitted by a line (least CPU time)",
        [
            "lattice",
            "leapfrog (ns / site and step)",
            "fixed per serve (ms)",
            "per slice (ms)",
            "per slice (ns / site)",
            "per slice / leapfrog step",
            "fixed / per slice",
            "largest residual of the fit (ms)",
        ],
    )
    counts = [1, 2, 4] if quick else [1, 2, 4, 8, 16]
    repeat = 1 if quick else 5
    setups = []
    for ndim, n in [(3, 6), (3, 8), (2, 12), (2, 16)] if quick else [(3, 32), (3, 64), (2, 128), (2, 256)]:
        s = Setup(ndim, n, 10)
        model = learned_polynomial(ndim, quick)
        s.serve(model, 3)
        setups.append((s, model))
    best = {(j, k): math.inf for j in range(len(setups)) for k in counts}
    for r in range(repeat):  # the sizes alternated, each serve once a round
        for j, (s, model) in enumerate(setups):
            for k in counts if r % 2 == 0 else counts[::-1]:
                best[j, k] = min(best[j, k], s.least(model, k + 2)[0])
            s.leapfrog_again()
    for j, (s, _) in enumerate(setups):
        y = np.array([best[j, k] for k in counts])
        slope, fixed = np.polyfit(np.array(counts, dtype=float), y, 1)
        resid = float(np.abs(y - (slope * np.array(counts) + fixed)).max())
        table.rows.append(
            [
                f"{s.ndim}+1D {s.n}^{s.ndim}",
                s.step / s.sites * 1e9,
                fixed * 1e3,
                slope * 1e3,
                slope / s.sites * 1e9,
                slope / s.step,
                fixed / slope,
                resid * 1e3,
            ]
        )
    table.notes.append(
        f"Serves of {', '.join(map(str, counts))} solved slices after a warm-up, the least CPU time of {repeat} (one a "
        "round, the order alternated), fitted by a least-squares line; the leapfrog: the least of 5 runs of 8 steps "
        "and one more each round."
    )
    by_dims: dict[int, list[tuple[int, float, float]]] = {}  # per dimension: (sites, fixed, per slice) in s
    for (s, _), row in zip(setups, table.rows):
        by_dims.setdefault(s.ndim, []).append((s.sites, row[2] / 1e3, row[3] / 1e3))
    parts = []
    for ndim, ((n1, f1, p1), (n2, f2, p2)) in ((d, v[:2]) for d, v in by_dims.items() if len(v) >= 2):
        fixed_lattice = f1 - (f2 - f1) / (n2 - n1) * n1  # a + b N through the two sizes: the part a
        slice_lattice = p1 - (p2 - p1) / (n2 - n1) * n1
        share = (fixed_lattice + 8 * slice_lattice) / (f1 + 8 * p1)
        parts.append(
            f"{ndim}+1D {fixed_lattice * 1e3:.2f} ms a serve and {slice_lattice * 1e3:.2f} ms a slice "
            f"({share:.0%} of a serve of 8 slices of the smaller lattice)"
        )
    table.notes.append(
        "The fixed cost and the cost per slice fitted in turn as a part per site and a part per lattice through "
        "the two sizes of a dimension; the part that does not grow with the sites: " + "; ".join(parts) + "."
    )
    sizes = [6, 8] if quick else [24, 32, 40, 48, 56, 64]
    steps = {n: Setup(3, n, 10) for n in sizes}  # 5 runs each, then 5 more, the sizes in turn
    for n in sizes[::-1]:
        steps[n].leapfrog_again(5)
    table.notes.append(
        "The leapfrog's CPU time per site and step over 3+1D sizes (the least of 10 runs of 8 steps, two rounds): "
        + ", ".join(f"{n}^3 {steps[n].step / n**3 * 1e9:.1f} ns" for n in sizes)
        + "."
    )
    return table


def affine(quick: bool) -> Table:
    """The affine decision per serve with the probe's kept answer dropped before each serve and kept."""
    table = Table(
        "affine",
        "The affine decision per serve (_field._affine_prefix), the probe's answer dropped -> kept",
        [
            "lattice",
            "decision, dropped (rounds, ms)",
            "decision, kept (rounds, ms)",
            "decision's share of the serve, dropped -> kept",
            "serve dropped -> kept (ms)",
            "fields equal",
        ],
    )
    rounds, repeat = (2, 2) if quick else (3, 7)
    t = Timers()
    prefix = _field._affine_prefix
    for ndim, n, nt in _poly_rows(quick, [(2, 64, 10), (2, 128, 10), (2, 256, 10), (3, 32, 10)]):
        s = Setup(ndim, n, nt)
        model = learned_polynomial(ndim, quick)
        s.serve(model, 3)
        decision: dict[bool, list[float]] = {False: [], True: []}
        serve: dict[bool, float] = {False: math.inf, True: math.inf}
        served: dict[bool, Any] = {}
        _field._affine_prefix = t.timed("decision", prefix)
        try:
            for r in range(rounds):
                for kept in (False, True) if r % 2 == 0 else (True, False):
                    least = math.inf
                    for _ in range(repeat):
                        if not kept:
                            _affine._PROBED.clear()
                        t.reset()
                        cpu, served[kept] = s.least(model, repeat=1)
                        serve[kept] = min(serve[kept], cpu)
                        least = min(least, t.cpu.get("decision", math.nan))
                    decision[kept].append(least)
        finally:
            _field._affine_prefix = prefix
        equal = bool(np.array_equal(np.asarray(served[False].field.values), np.asarray(served[True].field.values)))
        table.rows.append(
            [
                f"{ndim}+1D {s.label}",
                " / ".join(f"{v * 1e3:.3f}" for v in decision[False]),
                " / ".join(f"{v * 1e3:.3f}" for v in decision[True]),
                f"{min(decision[False]) / serve[False]:.1%} -> {min(decision[True]) / serve[True]:.1%}",
                f"{serve[False] * 1e3:.2f} -> {serve[True] * 1e3:.2f}",
                equal,
            ]
        )
    table.notes.append(
        f"{rounds} rounds, the order alternated; each way of a round {repeat} serves after a warm-up, the decision's "
        "least CPU time among them (the kept answer dropped before every serve, or kept); the serves' least CPU time "
        "over all rounds."
    )
    return table


#: The parts, by the name ``--part`` takes, in the order they run.
PARTS: dict[str, Callable[[bool], Table]] = {
    "slice-work": slice_work,
    "chord": chord,
    "lattice-new": lattice_new,
    "fixed-part": fixed_part,
    "faults": faults,
    "linalg": linalg,
    "fit3d": fit3d,
    "affine": affine,
}


def run(parts: list[str] | None = None, quick: bool = False, echo: bool = False) -> dict[str, Table]:
    """The tables of ``parts`` (every part by default), each with the load average before and after in its notes;
    ``echo``: print each table as it is done."""
    out = {}
    for name in parts or list(PARTS):
        before = load_average()
        t0 = time.perf_counter()
        table = PARTS[name](quick)
        table.seconds = time.perf_counter() - t0
        end = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
        table.notes.append(f"Load average before {before}, after {load_average()}; {end} at its end.")
        out[name] = table
        if echo:
            print_table(table)
            print(flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="python -m benchmarks.serve_profile", description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--part", action="append", choices=list(PARTS), metavar="NAME", help=f"one of {', '.join(PARTS)}")
    p.add_argument("--quick", action="store_true", help="tiny lattices, few repeats (seconds)")
    args = p.parse_args(argv)
    ldft.limit_threads(1)
    print(f"# {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}, load average: {load_average()}", flush=True)
    run(args.part, args.quick, echo=True)
    print(f"# {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}, load average: {load_average()}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
