"""A polynomial ensemble served stacked (its members side by side on the components, one slice-Newton over the
stack) against its members served one after another, from 81 to 16384 sites in 1+1D and 16^2 to 128^2 in 2+1D.

    python -m benchmarks.ensemble_serve [--quick] [--repeat N] [--only TEXT]

Polynomial ensembles of 3 and 5 members (bootstrap resamples, seed 0) are learned once per lattice dimension on a
small field and served on lattices of growing size with the same spacings: the 1+1D sine-Gordon breather with
Dirichlet strips from the exact solution, the 2+1D sine-Gordon membrane periodic (and with Dirichlet strips on the
smallest and largest), both served by slice-Newton; and a quadratic polynomial (2, 2) learned on a 1+1D string
(Dirichlet), whose DEL is affine (the affine recurrence serves it, ``solver="auto"``). Per row the stacked serve
(``latticedft.serve`` of the ensemble with ``latticedft._serve._ensemble.MEMBERWISE`` off) and the members served one
by one (``MEMBERWISE`` and ``MEMBERWISE_AFFINE`` on: each member served alone, the ensemble's result assembled from
theirs) are timed alternately in one process, the least of ``REPEAT`` each; 'stacked / one by one' above 1 means
serving the members one by one is faster. The two results' member fields are compared to the bit. The load average
is printed before and after.
"""

from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np

import latticedft as ldft
from latticedft import systems

from ._common import Config, Table, load_average
from ._fixtures import string_field

NAME = "ensemble_serve"
TITLE = "Polynomial ensembles served stacked against their members served one by one"
#: Each way is timed this many times, alternately; the fastest counts (the least disturbed by other load).
REPEAT = 5
#: Only the lattices whose label ("1+1D 81 sites, Dirichlet", "2+1D 16^2 periodic" ...) holds this text (``--only``).
ONLY: str | None = None
DX = 0.25
DT = 0.1


def _breather(nx: int, nt: int) -> Any:
    half = DX * (nx - 1) / 2
    with np.errstate(over="ignore"):  # cosh overflows far from the breather: the field is 0 there
        return systems.sine_gordon_breather(0.6, 0.2, xlim=(-half, half), nx=nx, nt=nt, dt=DT)


def _membrane(n: int, nt: int, periodic: bool) -> Any:
    h, dt = 0.05, 0.02
    x = np.arange(n) / 16
    u = 0.8 * np.sin(2 * np.pi * x)[:, None] * np.cos(2 * np.pi * x)[None, :]
    out = np.empty((nt, n, n))
    out[0] = out[1] = u
    c = (dt / h) ** 2
    for i in range(1, nt - 1):
        b = out[i]
        lap = -4 * b + np.roll(b, 1, 0) + np.roll(b, -1, 0) + np.roll(b, 1, 1) + np.roll(b, -1, 1)
        out[i + 1] = 2 * b - out[i - 1] + c * lap - dt**2 * np.sin(b)
    attrs = {d: {"periodic": "true", "period": n * h} for d in ("y", "x")} if periodic else None
    return systems.make_field(out, ("t", "y", "x"), spacing=(dt, h, h), coord_attrs=attrs)


def _ensembles(dim: str, quick: bool) -> dict[int, ldft.EnsembleLagrangian]:
    out = {}
    for members in (3, 5):
        if dim == "1+1D":
            ens = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 4)), members=members, seed=0)
            ldft.learn(ens, [_breather(21 if quick else 81, 40)], progress=False)
        elif dim == "1+1D affine":
            ens = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 2)), members=members, seed=0)
            ldft.learn(ens, string_field(33, 60, "dirichlet")[1], progress=False)
        else:
            model = ldft.PolynomialLagrangian((2, 12), time_symmetric=True)
            ens = ldft.EnsembleLagrangian(model, members=members, seed=0)
            ldft.learn(ens, _membrane(8 if quick else 16, 24, True), progress=False)
        out[members] = ens
    return out


def _cases(quick: bool) -> list[tuple[str, str, Any]]:
    """``(dimension, lattice label, field)`` of every row's lattice."""
    if quick:
        return [
            ("1+1D", "41 sites, Dirichlet", _breather(41, 8)),
            ("2+1D", "8^2 periodic", _membrane(8, 8, True)),
            ("1+1D affine", "33 sites, Dirichlet", string_field(33, 8, "dirichlet")[1]),
        ]
    rows = [("1+1D", f"{nx} sites, Dirichlet", _breather(nx, 40)) for nx in (81, 1024, 4096, 16384)]
    rows += [("2+1D", f"{n}^2 periodic", _membrane(n, 21, True)) for n in (16, 32, 64, 128)]
    rows += [("2+1D", f"{n}^2 Dirichlet", _membrane(n, 21, False)) for n in (16, 128)]
    rows += [
        ("1+1D affine", f"{nx} sites, Dirichlet", string_field(nx, 101, "dirichlet")[1]) for nx in (33, 1024, 4096)
    ]
    return [r for r in rows if ONLY is None or ONLY in f"{r[0]} {r[1]}"]


def _serve(ens: ldft.EnsembleLagrangian, f: Any, solver: str, memberwise: bool) -> tuple[float, Any]:
    import latticedft._serve._ensemble as ensemble

    keep = ensemble.MEMBERWISE, ensemble.MEMBERWISE_AFFINE
    ensemble.MEMBERWISE = ensemble.MEMBERWISE_AFFINE = memberwise
    try:
        t0 = time.perf_counter()
        out = ldft.serve(ens, f, progress=False, solver=solver)
        return time.perf_counter() - t0, out
    finally:
        ensemble.MEMBERWISE, ensemble.MEMBERWISE_AFFINE = keep


def run(cfg: Config) -> Table:
    table = Table(
        NAME,
        TITLE,
        ["lattice", "slices", "members", "solver", "stacked (s)", "one by one (s)", "stacked / one by one",
         "max |stacked - one by one|", "load"],
    )  # fmt: skip
    repeat = 1 if cfg.quick else REPEAT
    models = {dim: _ensembles(dim, cfg.quick) for dim in ("1+1D", "2+1D", "1+1D affine")}
    warm: set[int] = set()
    for dim, label, f in _cases(cfg.quick):
        for members, ens in models[dim].items():
            if id(ens) not in warm:  # the first serve of a model's kernels in the process, not timed
                warm.add(id(ens))
                _serve(ens, f, "auto", False)
                _serve(ens, f, "auto", True)
            for solver in ("lu", "krylov") if dim != "1+1D affine" else ("auto",):
                best = {True: np.inf, False: np.inf}
                got: dict[bool, Any] = {}
                for _ in range(repeat):
                    for way in (False, True):
                        t, got[way] = _serve(ens, f, solver, way)
                        best[way] = min(best[way], t)
                diff = float(np.nanmax(np.abs(got[True].members.values - got[False].members.values)))
                slices = int(got[True].field.sizes["t"])
                table.rows.append(
                    [f"{dim} {label}", slices, members, solver, best[False], best[True], best[False] / best[True],
                     diff, load_average().split(",")[0]]
                )  # fmt: skip
                print(" | ".join(str(c) for c in table.rows[-1]), flush=True)
    table.notes += [
        f"Each time is the least of {repeat} serves, the two ways alternated in one process; 'one by one': the "
        "members served one after another (each alone, on its own folded kernels) and the ensemble's result "
        "assembled from theirs; each model served once both ways before its first row, untimed; "
        "'max |stacked - one by one|' is the largest difference of any member's field between the two (0: to the "
        "bit); 'load': the 1-minute load average after the row. '1+1D affine': a quadratic polynomial (2, 2) "
        "served by the affine recurrence; an ensemble serve takes its members one by one only where "
        "MEMBERWISE_AFFINE is on (off by default).",
    ]
    return table


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.ensemble_serve [--quick] [--repeat N] [--only TEXT]``: the table alone; ``--repeat``
    times each way N times (default :data:`REPEAT`), ``--only`` keeps the lattices whose label holds TEXT."""
    global REPEAT, ONLY
    import argparse

    from ._common import run_alone

    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--repeat", type=int, default=REPEAT)
    p.add_argument("--only", default=None)
    args, rest = p.parse_known_args(argv)
    REPEAT, ONLY = args.repeat, args.only
    return run_alone(run, __doc__, rest)


if __name__ == "__main__":
    sys.exit(main())
