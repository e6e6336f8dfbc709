"""Profiles behind docs/performance.md: ``python -m benchmarks.profiles [NAME ...]``.

Each target is one call of the library at a benchmark's size, run once to warm up and then under cProfile;
the top functions by own time are printed. Names: ``wave-1+1d`` (the wave L_d, 256 x 256 periodic: its
affine recurrence), ``mlp-1+1d`` (slice-Newton, the Klein-Gordon MLP of the serving benchmark, 256 x 256
periodic), ``membrane-2+1d`` (the wave L_d on a 256 x 256 membrane, 30 slices: affine recurrence and
its DEL check), ``kepler-1d`` (one Kepler MLP trajectory, 500 steps), ``poly-1d`` (the fidelity benchmark's
polynomial L_d, 1000 steps), ``exact-learn`` (polynomial (4, 8) exact solve, paper Example 1).
"""

from __future__ import annotations

import cProfile
import io
import pstats
import sys
import time

import torch

import latticedft as ldft
from latticedft import systems

from ._fixtures import kepler_inits, kepler_mlp, kg_force, kg_mlp, membrane_field, string_field


def _wave():
    _, da = string_field(256, 256, "periodic")
    return lambda: ldft.serve(ldft.lagrangians.wave(), da, progress=False)


def _mlp():
    model = kg_mlp(False)
    _, da = string_field(256, 256, "periodic", kg_force)
    return lambda: ldft.serve(model, da, progress=False)


def _membrane():
    _, da = membrane_field(256, 30)
    return lambda: ldft.serve(ldft.lagrangians.wave(), da, progress=False)


def _kepler():
    model, init = kepler_mlp(True), kepler_inits(1)[0]
    return lambda: ldft.serve(model, init, slices=502, progress=False)


def _poly():
    from .fidelity import TRAIN

    model = ldft.PolynomialLagrangian(orders=(4, 8))
    ldft.learn(model, [systems.oscillator_wells(p, n=101) for p in TRAIN], progress=False)
    init = systems.oscillator_wells(1.55, n=2)
    return lambda: ldft.serve(model, init, slices=1002, progress=False)


def _exact():
    data = systems.oscillator_sin(1.2, n=51, dt=1.0)
    return lambda: ldft.learn(ldft.PolynomialLagrangian(orders=(4, 8)), data, progress=False)


TARGETS = {
    "wave-1+1d": _wave,
    "mlp-1+1d": _mlp,
    "membrane-2+1d": _membrane,
    "kepler-1d": _kepler,
    "poly-1d": _poly,
    "exact-learn": _exact,
}


def main(argv: list[str] | None = None) -> int:
    names = (argv if argv is not None else sys.argv[1:]) or list(TARGETS)
    torch.set_num_threads(1)
    for name in names:
        if name not in TARGETS:
            print(f"unknown profile {name!r}; choose from {', '.join(TARGETS)}", file=sys.stderr)
            return 2
        fn = TARGETS[name]()
        fn()  # warm-up: lazy imports, first-call costs
        prof = cProfile.Profile()
        t0 = time.perf_counter()
        prof.enable()
        fn()
        prof.disable()
        wall = time.perf_counter() - t0
        print(f"== {name}: {wall:.3f} s under cProfile", flush=True)
        for key, top in (("tottime", 12), ("cumulative", 10)):
            buf = io.StringIO()
            pstats.Stats(prof, stream=buf).strip_dirs().sort_stats(key).print_stats(top)
            lines = [ln for ln in buf.getvalue().splitlines() if ln.strip()]
            start = next((k for k, ln in enumerate(lines) if ln.lstrip().startswith("ncalls")), 0)
            print(f"-- by {key} time\n" + "\n".join(lines[start:]) + "\n", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
