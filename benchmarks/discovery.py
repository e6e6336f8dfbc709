"""Discovery: ``select = "auto"`` on systems with a known discrete Lagrangian, served beyond the training range.

    python -m benchmarks.discovery [--quick] [--only SYSTEM ...] [--no-peers] [--threads N]

For each system of :mod:`benchmarks._discovery_systems` (the paper's two oscillators, Kepler from one orbit,
sine-Gordon and phi^4 in 1+1D and 2+1D, a nonlinear Klein-Gordon string, a charged particle in a magnetic
field, the pendulum, the double pendulum) the model is chosen as a case with ``[model] select = "auto"`` and no
other model key chooses it (the default model, ``latticedft.select`` with the case's boundary), then the test
field is served from its first two slices beyond the training range. Columns:

- ``chosen``: the candidate ``select`` kept (``hand-set`` is the default polynomial);
- ``terms``: when the chosen model has a closed form (``model.symbolic()``), the number of terms of the discrete
  Euler-Lagrange equation it implies against the true one's, and ``coef. error`` the largest relative error of
  their coefficients after the unit-mass normalisation (:mod:`benchmarks._terms`); ``n/a: no closed form``
  otherwise;
- ``served``: the largest error of the served test over its slices (``inf`` where serving stopped);
  ``leapfrog``: that of the explicit leapfrog of the true equation at the same steps from the same two slices;
  ``ratio``: served over leapfrog (at most 1 is the target);
- ``fit (s)``: the time to learn the chosen candidate on all the training data, ``dense (s)``: that of today's
  default model (the dense exact solve), ``cost``: their ratio (same run, same data).

Peers (the ``bench`` extra; rows say ``not installed`` when they are not) fit the ODE systems only:
PySINDy (``x'' = f(x, x')`` from finite differences of the training data, then the test integrated from its
exact initial state) and py-xl-sindy (a Lagrangian catalog, its implicit regression on the same data); see
:mod:`benchmarks._discovery_peers`.

``--quick``: the pendulum, Kepler and sine-Gordon 1+1D at small sizes, without the peers (well under a minute).
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from typing import Any

import numpy as np
import xarray as xr

import latticedft as ldft
from latticedft._case._schema import ModelConfig
from latticedft._stencil import Stencil

from . import _discovery_systems as systems_mod
from ._common import Check, Config, Table, load_average, text
from ._discovery_peers import peer_rows, rows_for, xl_own_rows
from ._terms import coefficient_error, terms_cell

NAME = "discovery"
TITLE = 'Discovery: select = "auto" on known systems, served beyond the training range'
QUICK = ("pendulum", "kepler", "sine-gordon-1d")
COLUMNS = [
    "system",
    "beyond the training",
    "model",
    "terms",
    "coef. error",
    "served",
    "leapfrog",
    "ratio",
    "fit (s)",
    "dense (s)",
    "cost",
]


def lattice_dims(field: xr.DataArray) -> int:
    """Lattice dimensions of a field (time included, the component axis not)."""
    return sum(1 for d in field.dims if d != "component")


def served(model: Any, system: systems_mod.System) -> np.ndarray:
    """The test served from its first two slices (and boundary strips): the slices reached."""
    try:
        out = ldft.serve(model, system.test, slices=system.slices, boundary=system.boundary, progress=False)
    except ldft.ServeError as exc:
        out = exc.result
    return np.asarray(out.field.values, dtype=float)


#: A chosen model with more parameters than this is not expanded into terms: sympy's expansion of the DEL of a
#: dense polynomial on a 2+1D stencil (315 parameters, degree 8 in 7 neighbour values) runs for tens of minutes.
MAX_EXPANDED = 60


def recovery(model: Any, system: systems_mod.System) -> tuple[str, Any]:
    """``(terms, coefficient error)`` of a chosen model against the true ``L_d``."""
    size = model.n_parameters() if hasattr(model, "n_parameters") else 0
    if size > MAX_EXPANDED:
        return f"n/a: dense ({size} parameters)", "n/a"
    try:
        form = model.symbolic() if hasattr(model, "symbolic") else None
    except ldft.LatticeDFTError as exc:
        return f"n/a: {type(exc).__name__}: {' '.join(str(exc).split())[:60]}", "n/a"
    if form is None:
        return "n/a: no closed form", "n/a"
    err, n_got, n_want = coefficient_error(form, system.true_ld)
    return terms_cell(n_got, n_want), err


def _fit_time(kind: str, options: dict[str, Any], ridge: Any, system: systems_mod.System, n: int) -> float:
    model = ldft.MODELS[kind](**copy.deepcopy(options), stencil=Stencil.first_order(n))
    t0 = time.perf_counter()
    ldft.learn(model, system.train, boundary=system.boundary, ridge=ridge, progress=False)
    return time.perf_counter() - t0


def latticedft_rows(system: systems_mod.System) -> list[list[Any]]:
    """The system's rows for ``select = "auto"`` (one per error horizon)."""
    n = lattice_dims(system.test)
    hand = ModelConfig(select="auto").build(n)  # what a case with select = "auto" and no other model key builds
    rep = ldft.select(hand, system.train, "auto", boundary=system.boundary)
    row = rep.rows[rep.chosen]
    print(f"  {system.key}: selection: {rep.reason}", flush=True)
    orders = hand.options().get("orders")
    label = row["label"] if row["label"] != "hand-set" else f"hand-set {hand.kind}{tuple(orders) if orders else ''}"
    terms, coef = recovery(rep.model, system)
    fit = _fit_time(row["kind"], row["options"], row["ridge"], system, n)
    dense = _fit_time("polynomial", {}, 0.0, system, n)
    return rows_for(system, label, terms, coef, served(rep.model, system), fit, dense)


def targets(rows: list[list[Any]]) -> list[Check]:
    """The targets, over latticedft's rows: served beyond the training at or below the true leapfrog, the
    true terms to 1e-3 where the chosen model has a closed form, the fit within 3x the dense solve."""
    col = {c: i for i, c in enumerate(COLUMNS)}
    ratios = [r[col["ratio"]] for r in rows]
    closed = [r[col["coef. error"]] for r in rows if isinstance(r[col["coef. error"]], float)]
    costs = [r[col["cost"]] for r in rows]
    return [
        Check(
            "served error at or below the true leapfrog's (ratio <= 1), every system",
            f"{sum(x <= 1 for x in ratios)} of {len(ratios)} rows; worst ratio {max(ratios):.3g}",
            all(x <= 1 for x in ratios),
        ),
        Check(
            "true terms recovered to 1e-3 relative, every system",
            f"{sum(e <= 1e-3 for e in closed)} of {len(rows)} rows (closed form in {len(closed)})",
            len(closed) == len(rows) and all(e <= 1e-3 for e in closed),
        ),
        Check(
            "fit at most 3x the dense exact solve of the default model",
            f"worst {max(costs):.3g}x",
            max(costs) <= 3,
        ),
    ]


def run(cfg: Config, names: tuple[str, ...] | None = None, peers: bool | None = None) -> Table:
    """The table for ``names`` (default: every system; :data:`QUICK` when quick), with the peers' rows unless
    quick (or ``peers`` says otherwise)."""
    names = names or (QUICK if cfg.quick else tuple(systems_mod.SYSTEMS))
    peers = (not cfg.quick) if peers is None else peers
    table = Table(NAME, TITLE, list(COLUMNS))
    table.notes.append(f"load average (uptime) at the start: {load_average()}")
    mine: list[list[Any]] = []
    for name in names:
        system = systems_mod.build(name, cfg.quick)
        mine += latticedft_rows(system)
        table.rows += mine[-len(system.at or (0,)) :]
        if peers and system.ode is not None:
            table.rows += peer_rows(system)
        last = table.rows[-1]
        print(f"  {name}: {last[2]}, served {last[5]:.3g}, leapfrog {last[6]:.3g}", flush=True)
    if peers:
        table.rows += xl_own_rows()
    table.checks += targets(mine)
    table.notes += [
        "served / leapfrog: largest error over the test's slices, both from its first two slices (and boundary "
        "strips); ratio <= 1 is the target. Kepler: after 50 and after 200 steps.",
        "coef. error: the discrete Euler-Lagrange equation of the chosen model against that of the true L_d "
        "(trapezoid rule, first-order stencil), each normalised to unit mass; true terms relative to their own "
        "coefficient, spurious ones relative to the smallest true coefficient. Data are exact solutions (not "
        "leapfrog output), so an O(dt^2) coefficient difference is expected even for the right terms.",
        "cost: fit time of the chosen candidate over that of the default polynomial (the dense exact solve), "
        "both learned on all the training data in this run.",
        f"load average (uptime) at the end: {load_average()}",
    ]
    return table


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.discovery", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help=f"small sizes, {', '.join(QUICK)} only, no peers")
    p.add_argument("--only", action="append", default=[], metavar="SYSTEM", help=", ".join(systems_mod.SYSTEMS))
    p.add_argument("--no-peers", action="store_true", help="leave out the PySINDy and py-xl-sindy rows")
    p.add_argument("--peers", action="store_true", help="add the peers' rows in quick mode too")
    p.add_argument("--threads", type=int, default=1, help="threads of torch and BLAS (default 1)")
    args = p.parse_args(argv)
    names = tuple(n for item in args.only for n in item.split(",") if n)
    unknown = [n for n in names if n not in systems_mod.SYSTEMS]
    if unknown:
        p.error(f"unknown system {unknown[0]!r}; choose from {', '.join(systems_mod.SYSTEMS)}")
    ldft.limit_threads(args.threads)
    print(f"# python -m benchmarks.discovery {' '.join(argv if argv is not None else sys.argv[1:])}")
    print(f"# load average (uptime) before: {load_average()}", flush=True)
    peers = False if args.no_peers else (True if args.peers else None)
    t0 = time.perf_counter()
    table = run(Config(quick=args.quick, threads=args.threads), names or None, peers)
    table.seconds = time.perf_counter() - t0
    print(text(table))
    for c in table.checks:
        print(f"  [{'met' if c.met else 'NOT met'}] {c.target}: {c.measured}")
    print(f"# load average (uptime) after: {load_average()}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
