"""A stacked ensemble of polynomials on the folded kernels against the torch evaluation of the stack: serve time and
each member's difference from itself served alone.

    python -m benchmarks.stacked_folded [--quick]

An ensemble is served here as one stacked model (its members side by side on the components;
``latticedft._serve._ensemble.MEMBERWISE`` off: a serve of such an ensemble takes its members one by one otherwise,
``benchmarks.ensemble_serve``). Where every member is a polynomial that the folded kernels serve, each Newton
iteration evaluates every member by its own folded kernels on its own components
(``latticedft._serve._stackfold``); the torch evaluation of the stack (``CellDerivatives`` on the stacked model, as
before) is the same run with that path turned off (``_stepper.stacked_folded`` giving None). The two are timed
alternately in one process (the least of ``REPEAT`` calls each); the members' fields are compared with the members
served alone (on the folded kernels, as a single polynomial is served). The 1D row is served by the numpy Newton
loop either way (slice-Newton and its kernels are n-D): the two times measure the same code, a gauge of the noise.
The load average is printed before and after.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

import latticedft as ldft
from latticedft import systems

from ._common import Config, Table

NAME = "stacked_folded"
TITLE = "Stacked polynomial ensembles: folded kernels per member against the torch evaluation of the stack"
MEMBERS = 5
#: Each way is timed this many times, alternately; the fastest counts (the least disturbed by other load).
REPEAT = 5


def _oscillator(quick: bool) -> tuple[str, ldft.EnsembleLagrangian, Any, dict[str, Any]]:
    train = [systems.oscillator_sin(a) for a in (1.2, 0.8, 0.4)]
    orders = (2, 4) if quick else (4, 8)
    ens = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian(orders), members=MEMBERS, seed=0)
    ldft.learn(ens, train, progress=False)
    return f"1D oscillator, polynomial {orders}", ens, systems.oscillator_sin(1.0), {"slices": 51}


def _breather(quick: bool) -> tuple[str, ldft.EnsembleLagrangian, Any, dict[str, Any]]:
    nx, nt = (21, 12) if quick else (81, 40)
    train = systems.sine_gordon_breather(0.5, xlim=(-10, 10), nx=nx, nt=40, dt=0.1)
    test = systems.sine_gordon_breather(0.6, 0.2, xlim=(-10, 10), nx=nx, nt=nt, dt=0.1)
    ens = ldft.EnsembleLagrangian(ldft.PolynomialLagrangian((2, 4)), members=MEMBERS, seed=0)
    ldft.learn(ens, [train], progress=False)
    return f"1+1D sine-Gordon breather, {nx} sites, polynomial (2, 4)", ens, test, {}


def _membrane(quick: bool) -> tuple[str, ldft.EnsembleLagrangian, Any, dict[str, Any]]:
    n, nt = (8, 8) if quick else (16, 41)
    h, dt = 0.05, 0.02
    x = np.arange(n) / n
    u = 0.8 * np.sin(2 * np.pi * x)[:, None] * np.cos(2 * np.pi * x)[None, :]
    out = np.empty((max(nt, 24), n, n))
    out[0] = out[1] = u
    c = (dt / h) ** 2
    for i in range(1, out.shape[0] - 1):
        b = out[i]
        lap = -4 * b + np.roll(b, 1, 0) + np.roll(b, -1, 0) + np.roll(b, 1, 1) + np.roll(b, -1, 1)
        out[i + 1] = 2 * b - out[i - 1] + c * lap - dt**2 * np.sin(b)
    attrs = {d: {"periodic": "true", "period": n * h} for d in ("y", "x")}

    def field(v: np.ndarray) -> Any:
        return systems.make_field(v, ("t", "y", "x"), spacing=(dt, h, h), coord_attrs=attrs)

    model = ldft.PolynomialLagrangian((2, 12), time_symmetric=True)
    ens = ldft.EnsembleLagrangian(model, members=MEMBERS, seed=0)
    ldft.learn(ens, field(out[:24]), progress=False)
    return f"2+1D sine-Gordon membrane, {n} x {n} periodic, polynomial (2, 12)", ens, field(out[:nt]), {}


def _timed(fn: Callable[[], Any]) -> tuple[float, Any]:
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def run(cfg: Config) -> Table:
    import latticedft._serve._ensemble as ensemble
    import latticedft._serve._stepper as stepper

    keep = ensemble.MEMBERWISE
    ensemble.MEMBERWISE = False  # the stacked run, both ways (its members one by one: benchmarks.ensemble_serve)
    try:
        return _run(cfg, stepper)
    finally:
        ensemble.MEMBERWISE = keep


def _run(cfg: Config, stepper: Any) -> Table:
    folded = stepper.stacked_folded
    table = Table(
        NAME,
        TITLE,
        [
            "case",
            "solver",
            "slices",
            "torch evaluation (s)",
            "folded per member (s)",
            "speed-up",
            f"{MEMBERS} members alone (s)",
            "max |member - alone|, torch",
            "max |member - alone|, folded",
        ],
    )
    repeat = 1 if cfg.quick else REPEAT
    for build in (_oscillator, _breather, _membrane):
        label, ens, init, kw = build(cfg.quick)
        for solver in ("lu", "krylov") if build is not _oscillator else ("auto",):
            skw = dict(kw, progress=False, solver=solver)
            alone = [ldft.serve(ens.member(k), init, **skw).field.values for k in range(len(ens))]
            best = {"torch": np.inf, "folded": np.inf, "alone": np.inf}
            diff = {}
            for _ in range(repeat):
                t0 = time.perf_counter()
                for k in range(len(ens)):
                    ldft.serve(ens.member(k), init, **skw)
                best["alone"] = min(best["alone"], time.perf_counter() - t0)
                for way in ("torch", "folded"):
                    stepper.stacked_folded = folded if way == "folded" else (lambda *a: None)  # type: ignore[assignment]
                    try:
                        t, out = _timed(lambda e=ens, f=init, o=skw: ldft.serve(e, f, **o))
                    finally:
                        stepper.stacked_folded = folded  # type: ignore[assignment]
                    best[way] = min(best[way], t)
                    diff[way] = max(float(np.abs(out.members.values[k] - alone[k]).max()) for k in range(len(ens)))
            slices = int(out.field.sizes[out.field.dims[0]])
            table.rows.append(
                [label, solver, slices, best["torch"], best["folded"], best["torch"] / best["folded"], best["alone"],
                 diff["torch"], diff["folded"]]
            )  # fmt: skip
    table.notes += [
        f"{MEMBERS} members learned on bootstrap resamples (seed 0). Each time is the least of {repeat} serves of "
        f"the stacked ensemble, the two ways alternated in one process; '{MEMBERS} members alone': the members "
        "served one after another (single polynomials, on the folded kernels), the least of as many; "
        "'max |member - alone|' is the largest difference of any member's field from that member served alone "
        "(0: to the bit).",
    ]
    return table


if __name__ == "__main__":
    from ._common import run_alone

    sys.exit(run_alone(run, __doc__))
