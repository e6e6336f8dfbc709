"""Discovery from noisy samples: ``select = "auto"`` with ``noise = "auto"`` on the systems of the discovery table.

    python -m benchmarks.discovery_noise [--only SYSTEM ...] [--sigmas S ...] [--seed N] [--threads N]
    python -m benchmarks.discovery_noise --gauges LIBRARY [--at average] [--only SYSTEM ...] [--sigmas S ...]

Each system of :mod:`benchmarks._discovery_systems` is learned from its training samples with Gaussian noise
added (standard deviation ``sigma`` times the training fields' largest magnitude, seeded), the model chosen as a
case with ``[model] select = "auto"``, ``[train] noise = "auto"`` and no other model key chooses it, then served
from the clean test's first two slices (and boundary strips). Columns:

- ``model``: the candidate ``select`` kept;
- ``terms``, ``coef. error``: the discrete Euler-Lagrange equation of the chosen model against that of the true
  ``L_d`` (:mod:`benchmarks._terms`, unit-mass normalisation), learned/true term counts and the largest relative
  coefficient error (true terms relative to their own coefficient, spurious ones to the smallest true one). The
  clean samples differ from the true ``L_d``'s integrator by ``O(dt^2)`` (the discovery table's ``coef.
  (samples)`` column), which this error includes;
- ``served 50``: the largest error of the served test over its first 50 steps; ``/ sigma``: that over the noise's
  standard deviation; ``leapfrog 50``: the leapfrog of the true equation from the same two slices;
- ``bag spread``: for a sparse model, the largest standard deviation of a kept coefficient over its bagged fits
  (resampled time blocks) relative to the coefficient (``n/a`` for another model);
- ``warned``: the learning report's warnings, shortened (``-`` for none): the run saying its fit may not hold;
- ``select (s)``: the time of the selection with the noise correction.

``--gauges LIBRARY`` measures instead how ``gauge = "auto"`` decides on those noisy samples: the sparse library at
threshold 0.1 learned on every training field, with ``noise`` ``"none"`` and ``"auto"``, in each gauge; per fit the
gauge used, its training ``rel_res`` (for ``auto``: the ``rel_res`` of each gauge the rule compared, ``gauge_scores``),
the terms kept and the served error over 50 steps of the test in noise standard deviations.

Targets (the noise part of term discovery): at ``sigma = 1e-3`` the right terms recovered (the true terms and
no other, coefficients within 5 %) and the served error within 10 sigma over 50 steps; at ``sigma = 1e-2`` the
coefficients within 5 %, or the run warns.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import numpy as np
import xarray as xr

import latticedft as ldft
from latticedft._case._schema import ModelConfig

from . import _discovery_systems as systems_mod
from ._common import Check, Config, Table, load_average, print_table
from ._terms import coefficient_error, terms_cell

NAME = "discovery-noise"
TITLE = 'Discovery from noisy samples: select = "auto", noise = "auto"'
SIGMAS = (1e-3, 1e-2)
#: Served steps the error is measured over.
STEPS = 50
#: Coefficients within this relative error count as recovered.
COEF_TOL = 0.05
#: The served error's bound, in noise standard deviations, at the lowest noise level.
SIGMA_BOUND = 10.0
#: A chosen model with more parameters than this is not expanded into terms (as in :mod:`benchmarks.discovery`).
MAX_EXPANDED = 60
COLUMNS = [
    "system",
    "sigma",
    "model",
    "terms",
    "coef. error",
    "served 50",
    "/ sigma",
    "leapfrog 50",
    "bag spread",
    "warned",
    "select (s)",
]


def noisy(fields: list[xr.DataArray], sigma: float, seed: int) -> tuple[list[xr.DataArray], float]:
    """``fields`` with Gaussian noise of ``sigma`` times their largest magnitude, and that noise's deviation."""
    scale = sigma * max(float(np.abs(f.values).max()) for f in fields)
    rng = np.random.default_rng(seed)
    return [f.copy(data=f.values + scale * rng.standard_normal(f.shape)) for f in fields], scale


def _recovery(model: Any, system: systems_mod.System) -> tuple[str, Any, int, int]:
    """``(terms cell, coefficient error, terms learned, terms true)`` of a chosen model."""
    size = model.n_parameters() if hasattr(model, "n_parameters") else 0
    form = model.symbolic() if hasattr(model, "symbolic") and size <= MAX_EXPANDED else None
    if form is None:
        return ("n/a: dense" if size > MAX_EXPANDED else "n/a: no closed form"), "n/a", 0, -1
    err, n_got, n_want = coefficient_error(form, system.true_ld)
    return terms_cell(n_got, n_want), err, n_got, n_want


def _warned(report: Any) -> str:
    """The learning report's warnings in a few words each (``-`` for none)."""
    words = [" ".join(str(w).split()[:3]).rstrip(":,") for w in getattr(report, "warnings", [])]
    return "; ".join(words) or "-"


def _served(model: Any, system: systems_mod.System, steps: int) -> np.ndarray:
    slices = min(steps + 2, system.slices)
    try:
        out = ldft.serve(model, system.test, slices=slices, boundary=system.boundary, progress=False)
    except ldft.ServeError as exc:
        out = exc.result
    return np.asarray(out.field.values, dtype=float)


def row(system: systems_mod.System, sigma: float, seed: int) -> tuple[list[Any], dict[str, Any]]:
    """One table row and what the targets read of it."""
    n = sum(1 for d in system.test.dims if d != "component")
    train, scale = noisy(system.train, sigma, seed)
    hand = ModelConfig(select="auto").build(n)
    t0 = time.perf_counter()
    rep = ldft.select(hand, train, "auto", boundary=system.boundary, noise="auto")
    seconds = time.perf_counter() - t0
    chosen = rep.rows[rep.chosen]
    label = chosen["label"] if chosen["label"] != "hand-set" else f"hand-set {hand.kind}"
    terms, coef, n_got, n_want = _recovery(rep.model, system)
    ref = np.asarray(system.test.values, dtype=float)
    slices = min(STEPS + 2, system.slices)
    mine = systems_mod.max_errors(_served(rep.model, system, STEPS), ref, slices)[0]
    base = systems_mod.max_errors(system.leapfrog(system.test, slices), ref, slices)[0]
    warned = _warned(rep.model.report_)
    spread = getattr(rep.model, "bag_spread", None)
    bag = float(np.nanmax(spread)) if spread is not None and np.isfinite(spread).any() else "n/a"
    recovered = isinstance(coef, float) and n_got == n_want and coef <= COEF_TOL
    out = [system.name, sigma, label, terms, coef, mine, mine / scale, base, bag, warned, seconds]
    return out, {"sigma": sigma, "recovered": recovered, "within": mine <= SIGMA_BOUND * scale, "warned": warned != "-"}


def targets(seen: list[dict[str, Any]], sigmas: tuple[float, ...]) -> list[Check]:
    """The noise targets over the rows measured."""
    checks = []
    low = [s for s in seen if s["sigma"] == min(sigmas)]
    if low:
        rec, within = sum(s["recovered"] for s in low), sum(s["within"] for s in low)
        checks.append(
            Check(
                f"at sigma = {min(sigmas):g}: the true terms alone, coefficients within {COEF_TOL:.0%}",
                f"{rec} of {len(low)} systems",
                rec == len(low),
            )
        )
        checks.append(
            Check(
                f"at sigma = {min(sigmas):g}: served error within {SIGMA_BOUND:g} sigma over {STEPS} steps",
                f"{within} of {len(low)} systems",
                within == len(low),
            )
        )
    high = [s for s in seen if s["sigma"] == max(sigmas) and max(sigmas) > min(sigmas)]
    if high:
        ok = sum(s["recovered"] or s["warned"] for s in high)
        checks.append(
            Check(
                f"at sigma = {max(sigmas):g}: coefficients within {COEF_TOL:.0%}, or the run warns",
                f"{ok} of {len(high)} systems ({sum(s['recovered'] for s in high)} recovered)",
                ok == len(high),
            )
        )
    return checks


def run(cfg: Config, names: tuple[str, ...] | None = None, sigmas: tuple[float, ...] = SIGMAS, seed: int = 0) -> Table:
    """The table for ``names`` (default: every system) at each of ``sigmas``."""
    names = names or tuple(systems_mod.SYSTEMS)
    table = Table(NAME, TITLE, list(COLUMNS))
    table.notes.append(f"load average (uptime) at the start: {load_average()}")
    seen: list[dict[str, Any]] = []
    for name in names:
        system = systems_mod.build(name, cfg.quick)
        for sigma in sigmas:
            cells, reading = row(system, sigma, seed)
            table.rows.append(cells)
            seen.append(reading)
            print(f"  {name} sigma {sigma:g}: {cells[2]}, {cells[3]}, served {cells[6]:.3g} sigma", flush=True)
    table.checks += targets(seen, sigmas)
    table.notes += [
        f"noise: Gaussian, sigma times the training fields' largest magnitude, seed {seed}; the test is clean.",
        f"served 50: largest error over the first {STEPS} served steps from the test's first two slices; / sigma: "
        "over the noise's standard deviation; leapfrog 50: the leapfrog of the true equation from the same slices.",
        "coef. error: the chosen model's normalised DEL against the true L_d's (includes the O(dt^2) difference of "
        "exact samples from the true L_d's integrator).",
        f"load average (uptime) at the end: {load_average()}",
    ]
    return table


GAUGE_COLUMNS = ["system", "sigma", "noise", "gauge asked", "gauge used", "rel_res", "gauge_scores", "kept", "/ sigma"]


def gauges(cfg: Config, names: tuple[str, ...], sigmas: tuple[float, ...], library: str, at: str, seed: int) -> Table:
    """How ``gauge = "auto"`` decides on the noisy samples: ``library`` (threshold 0.1) in each gauge (``--gauges``)."""
    table = Table(NAME + "-gauges", f"gauge = 'auto' on noisy samples: {library}", list(GAUGE_COLUMNS))
    table.notes.append(f"load average (uptime) at the start: {load_average()}")
    for name in names:
        system = systems_mod.build(name, cfg.quick)
        ref = np.asarray(system.test.values, dtype=float)
        slices = min(STEPS + 2, system.slices)
        for sigma in sigmas:
            train, scale = noisy(system.train, sigma, seed)
            for mode in ("none", "auto"):
                for gauge in ("auto", "unit-mass", "trace"):
                    model = ldft.SparseLagrangian(library, threshold=0.1, at=at)
                    rep = ldft.learn(model, train, boundary=system.boundary, noise=mode, gauge=gauge, progress=False)
                    err = systems_mod.max_errors(_served(model, system, STEPS), ref, slices)[0]
                    scores = ", ".join(f"{k} {v:.2g}" for k, v in rep.gauge_scores.items()) or "-"
                    kept = ", ".join(model.kept_terms())
                    table.rows.append([name, sigma, mode, gauge, rep.gauge, rep.rel_res, scores, kept, err / scale])
    table.notes.append(f"load average (uptime) at the end: {load_average()}")
    return table


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.discovery_noise", description=__doc__.split("\n\n")[0])
    p.add_argument("--only", action="append", default=[], metavar="SYSTEM", help=", ".join(systems_mod.SYSTEMS))
    p.add_argument("--sigmas", type=float, nargs="+", default=list(SIGMAS), help="noise levels (default 1e-3 1e-2)")
    p.add_argument("--seed", type=int, default=0, help="seed of the noise (default 0)")
    p.add_argument("--quick", action="store_true", help="the systems' small sizes")
    p.add_argument("--threads", type=int, default=1, help="threads of torch and BLAS (default 1)")
    p.add_argument("--gauges", metavar="LIBRARY", help="measure gauge = 'auto' on LIBRARY instead of the table")
    p.add_argument("--at", default="anchor", help="the sparse model's 'at' for --gauges (default anchor)")
    args = p.parse_args(argv)
    names = systems_mod.chosen(p, args.only)
    if any(not s > 0 for s in args.sigmas):
        p.error("--sigmas: expected noise levels > 0")
    ldft.limit_threads(args.threads)
    print(f"# python -m benchmarks.discovery_noise {' '.join(argv if argv is not None else sys.argv[1:])}")
    print(f"# load average (uptime) before: {load_average()}", flush=True)
    t0 = time.perf_counter()
    cfg = Config(quick=args.quick, threads=args.threads)
    if args.gauges:
        table = gauges(cfg, tuple(names or systems_mod.SYSTEMS), tuple(args.sigmas), args.gauges, args.at, args.seed)
    else:
        table = run(cfg, names or None, tuple(args.sigmas), args.seed)
    table.seconds = time.perf_counter() - t0
    print_table(table)
    print(f"# load average (uptime) after: {load_average()}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
