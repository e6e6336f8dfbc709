"""Selection on systems that no default was tuned on: the check a change of selection's rules must pass besides
the discovery table.

    python -m benchmarks.untuned [--only SYSTEM ...] [--scores]

Each system is built and scored as a row of :mod:`benchmarks.discovery` (``select = "auto"`` on the default model,
the test served from its first two slices beyond the training amplitudes, against the leapfrog of the true
equation at the same step), and the selection's reason is printed. The systems:

- ``quartic``: the hardening single well ``q'' = -q - 0.5 q^3``, dt = 0.2, trained at amplitudes 0.5 and 1.0 (101
  slices each), tested at 1.6 (301 slices);
- ``cubic``: the asymmetric well ``q'' = -q + 0.3 q^2``, dt = 0.2, trained at 0.5 and 1.0, tested at 1.4;
- ``softening``: ``q'' = -q + 0.2 q^3``, dt = 0.2, trained at 0.5 and 1.0, tested at 1.5.

``--scores``: every candidate of ``"auto"`` scored three ways beside its error on the test: on the held-out slices
(selection's score), beyond the training amplitudes (learned on the field of amplitude 0.5 alone, serving the one
of 1.0 from its first two slices: the score ``select`` gives a hand-set model that ``keep_below`` would keep), and
learned on both fields, serving the test.
"""

from __future__ import annotations

import argparse
import copy
import math
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import sympy

import latticedft as ldft
from latticedft import _select
from latticedft._case._schema import ModelConfig

from . import _discovery_systems as systems_mod
from ._common import load_average
from .discovery import COLUMNS, latticedft_rows, served

H = 0.2


def _well(name: str, potential: Callable[[Any], Any], test: float) -> Callable[[bool], systems_mod.System]:
    def build(quick: bool) -> systems_mod.System:
        spec = systems_mod.ode_spec(1, lambda q, v: v[0] ** 2 / 2 - potential(q[0]))
        train = [([0.5], [0.0], 101), ([1.0], [0.0], 101)]
        note = f"0.5, 1.0 -> {test}"
        return systems_mod._ode_system(name, spec, H, train, ([test], [0.0], 301), note)

    return build


SYSTEMS: dict[str, Callable[[bool], systems_mod.System]] = {
    "quartic": _well("quartic single well", lambda q: q**2 / 2 + q**4 / 8, 1.6),
    "cubic": _well("cubic well", lambda q: q**2 / 2 - sympy.Rational(1, 10) * q**3, 1.4),
    "softening": _well("softening well", lambda q: q**2 / 2 - q**4 / 20, 1.5),
}


def scores(system: systems_mod.System) -> list[str]:
    """One line per candidate of ``"auto"``: held-out score, score beyond the training amplitudes, test error."""
    hand = ModelConfig(select="auto").build(1)
    fields = [f.load() for f in system.train]
    specs = _select._candidates(hand, _select.auto_candidates(hand, 1, 0.0, 1), 0.0)
    held = _select._split(fields, _select.HOLD_OUT)
    big = _select.largest_field(fields)
    rest = [f for i, f in enumerate(fields) if i != big]
    ref = np.asarray(system.test.values, dtype=float)
    base = systems_mod.max_errors(system.leapfrog(system.test, system.slices), ref, system.slices)[0]
    lines = [f"{system.name}: leapfrog {base:.3e}", f"{'held out':>10} {'beyond':>10} {'test':>10} {'/ leapfrog':>10}"]
    for fresh, ridge, row in specs:
        inside, _ = _select._trial(fresh, ridge, held, fields, None, {})
        beyond, _ = _select._trial(fresh, ridge, rest, [fields[big]], None, {})
        model = copy.deepcopy(fresh)
        try:
            ldft.learn(model, fields, ridge=ridge, progress=False)
            test = systems_mod.max_errors(served(model, system), ref, system.slices)[0]
        except (ldft.LatticeDFTError, ArithmeticError, ValueError, RuntimeError):
            test = math.inf
        cells = [inside["score"], beyond["score"], test, test / base]
        lines.append(" ".join(f"{c:10.3e}" for c in cells) + f"  {row['label']}")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.untuned", description=__doc__.split("\n\n")[0])
    p.add_argument("--only", action="append", default=[], metavar="SYSTEM", help=", ".join(SYSTEMS))
    p.add_argument("--scores", action="store_true", help="every candidate scored three ways beside its test error")
    args = p.parse_args(argv)
    names = [n for item in args.only for n in item.split(",") if n] or list(SYSTEMS)
    unknown = [n for n in names if n not in SYSTEMS]
    if unknown:
        p.error(f"unknown system {unknown[0]!r}; choose from {', '.join(SYSTEMS)}")
    print(f"# load average (uptime) before: {load_average()}", flush=True)
    col = {c: i for i, c in enumerate(COLUMNS)}
    for name in names:
        t0 = time.perf_counter()
        system = SYSTEMS[name](False)
        system.key = name
        if args.scores:
            print("\n".join(scores(system)), flush=True)
            continue
        for row in latticedft_rows(system):
            print(
                f"{system.name} ({system.range_note}): {row[col['model']]}; terms {row[col['terms']]}, "
                f"served {row[col['served']]:.3g}, leapfrog {row[col['leapfrog']]:.3g}, ratio {row[col['ratio']]:.3g}"
                f" ({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )
    print(f"# load average (uptime) after: {load_average()}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
