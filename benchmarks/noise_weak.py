"""A weak form of the sparse fit under noise, tried and not kept: rows summed against smooth test functions in time.

    python -m benchmarks.noise_weak [--only SYSTEM ...] [--sigmas S ...] [--widths W ...]

The DEL residual of a :class:`latticedft.SparseLagrangian` is linear in its coefficients, ``EL = R coef``. The weak
form replaces the rows of ``R`` (one per interior site and time) by their sums over time windows against a smooth,
compactly supported test function ``phi(s) = (1 - s^2)^4`` (``s`` in ``(-1, 1)`` over ``2 w + 1`` slices, windows
every ``w / 2`` slices, each site on its own): summed by parts, the second time differences fall on ``phi``, whose
differences are small, so the noise of the data's second differences averages out. The same sparse fit (the
thresholds, the backward path and the held-out served choice of :mod:`latticedft._learn._sparse`) then runs on
these rows; this benchmark routes them in by patching the module's ``residual_matrices`` and ``residual_matrix``
for the run.

Each system of :mod:`benchmarks._discovery_systems` (noise as in :mod:`benchmarks.discovery_noise`, seed 0) is
learned with the default library of its lattice and ``threshold = "auto"``, and served from the clean test's first
two slices. Two tables:

- *fixed support*: the largest relative coefficient error of the true terms alone (fitted under the gauge, the
  largest coefficient normalised to 1) against the same fit on the clean samples, from the plain rows
  (``w = 0``) and the weak rows of each half width ``w``, with the support of each size on the backward path of
  the noisy rows (the sparsest four);
- *the fit*: terms, coefficient error and served error over 50 steps / sigma (as in
  :mod:`benchmarks.discovery_noise`) for ``noise = "auto"`` (errors in variables), the weak rows alone
  (``noise = "none"``), and both (the weak rows inside the corrected fit).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import time
from typing import Any
from unittest import mock

import numpy as np

import latticedft as ldft
from latticedft._lattice import LatticeField, interior_slices
from latticedft._learn import _api, _sparse
from latticedft._learn._exact import mean_mixed_hessian, residual_matrices, residual_matrix
from latticedft._models._sparse import SparseLagrangian, default_library

from . import _discovery_systems as systems_mod
from ._common import load_average
from .discovery_noise import STEPS, _recovery, _served, noisy

SYSTEMS = ("sine-gordon-1d", "phi4-1d", "oscillator-wells", "pendulum")
#: The true terms in the default library's names (None: the true potential is not in the library).
TRUE_TERMS: dict[str, list[str] | None] = {
    "sine-gordon-1d": ["Dtq**2", "Dxq**2", "cos(q)"],
    "phi4-1d": ["Dtq**2", "Dxq**2", "q**2", "q**4"],
    "oscillator-wells": None,
    "pendulum": ["Dtq**2", "cos(q)"],
}
POWER = 4


def weak(r: np.ndarray, nt: int, w: int) -> np.ndarray:
    """The rows ``r`` (time-major over ``nt`` interior slices) summed against the test function of half width ``w``
    over windows every ``w / 2`` slices (``r`` itself for ``w = 0`` or too few slices)."""
    w = min(w, (nt - 1) // 2)
    if w < 1 or r.shape[0] % nt:
        return r
    c = r.shape[1]
    r3 = r.reshape(nt, -1, c)
    s = np.linspace(-1.0, 1.0, 2 * w + 3)[1:-1]
    phi = (1 - s**2) ** POWER
    phi /= np.linalg.norm(phi)
    rows = [np.tensordot(phi, r3[k : k + 2 * w + 1], axes=(0, 0)) for k in range(0, nt - 2 * w, max(1, w // 2))]
    return np.concatenate(rows).reshape(-1, c)


def _interior_times(model: SparseLagrangian, f: LatticeField) -> int:
    return len(range(f.shape[0])[interior_slices(f.shape, model.stencil, f.boundary)[0]])


def _weak_patch(w: int) -> Any:
    """The sparse fit on weak rows: ``residual_matrices``, ``residual_matrix`` and the held-out heads of
    :mod:`latticedft._learn._sparse` (the fit's rows come from ``residual_matrices``, the held-out choice's from
    the other two)."""

    def rows(model: SparseLagrangian, f: LatticeField) -> np.ndarray:
        return weak(residual_matrix(model, f), _interior_times(model, f), w)

    def many(model: SparseLagrangian, fields: list[LatticeField], mean: bool) -> tuple[list[np.ndarray], Any]:
        rs, hessian = residual_matrices(model, fields, mean)
        return [weak(r, _interior_times(model, f), w) for r, f in zip(rs, fields)], hessian

    def head(model: SparseLagrangian, f: LatticeField, r: np.ndarray, keep: int) -> np.ndarray:
        return rows(model, f.with_values(f.values[:keep]))

    return mock.patch.multiple(_sparse, residual_matrices=many, residual_matrix=rows, _head=head)


def _system_rows(system: systems_mod.System, data: list[Any]) -> tuple[SparseLagrangian, Any, list[Any]]:
    """The bound model, the gauge rows and ``(rows, interior slices)`` of every training field as the fit sees
    them (scaled by ``1 / sqrt(sites)``)."""
    seen: dict[str, Any] = {}
    real = _api.learn_sparse

    def spy(model: Any, fields: Any, gauge: Any, ridge: Any, nsites: int, shared: Any = None) -> Any:
        seen.update(fields=fields, gauge=gauge, nsites=nsites)
        return real(model, fields, gauge, ridge, nsites, shared)

    n = sum(1 for d in system.test.dims if d != "component")
    model = SparseLagrangian(default_library(n, 1), threshold=0.1)
    with mock.patch.object(_api, "learn_sparse", spy):
        ldft.learn(model, data, boundary=system.boundary)
    fields, gauge = seen["fields"], seen["gauge"]
    g = gauge.constraint(mean_mixed_hessian(model, fields), model.spacing[0]) if gauge.fixes else None
    rows = [(residual_matrix(model, f) / math.sqrt(seen["nsites"]), _interior_times(model, f)) for f in fields]
    return model, g, rows


def fixed_support(name: str, sigma: float, widths: list[int]) -> None:
    """Print the fixed-support coefficient error and the backward path per width."""
    system = systems_mod.build(name)
    model, g0, clean = _system_rows(system, system.train)
    _, gn, rows = _system_rows(system, noisy(system.train, sigma, 0)[0])
    names = [t.name for t in model.terms]
    truth = TRUE_TERMS[name]
    for w in widths:

        def factor(rs: list[Any], w: int = w) -> np.ndarray:
            return _sparse._stack(_sparse._blocks([weak(r, nt, w) for r, nt in rs], len(names)))

        tc, tn = factor(clean), factor(rows)
        out = []
        if truth is not None:
            act = np.array([t in truth for t in names])
            a, b = _sparse._fit(tc, g0, 0.0, act), _sparse._fit(tn, gn, 0.0, act)
            k = int(np.argmax(np.abs(a)))
            a, b = a / a[k], b / b[k]
            out.append(f"coef. error {float(np.max(np.abs(b - a)[act] / np.abs(a[act]))):.3g}")
        for theta in _sparse.backward(tn, gn, 0.0)[-4:]:
            out.append(" + ".join(t for t, c in zip(names, theta) if c != 0))
        print(f"| {name} | {sigma:g} | {w} | " + " | ".join(out) + " |", flush=True)


def fits(name: str, sigma: float, width: int) -> None:
    """Print the three fits' terms, coefficient error and served error."""
    system = systems_mod.build(name)
    train, scale = noisy(system.train, sigma, 0)
    n = sum(1 for d in system.test.dims if d != "component")
    ref = np.asarray(system.test.values, dtype=float)
    slices = min(STEPS + 2, system.slices)
    for label, mode, weak_rows in (
        ("errors in variables", "auto", False),
        ("weak", "none", True),
        ("both", "auto", True),
    ):
        t0 = time.perf_counter()
        model = SparseLagrangian(default_library(n, 1), threshold="auto")
        with _weak_patch(width) if weak_rows else contextlib.nullcontext():
            ldft.learn(model, train, boundary=system.boundary, noise=mode)
        terms, coef, _, _ = _recovery(model, system)
        err = systems_mod.max_errors(_served(model, system, STEPS), ref, slices)[0] / scale
        kept = " + ".join(t.name for t, c in zip(model.terms, model.coef.detach().numpy()) if c != 0)
        coef_text = coef if isinstance(coef, str) else f"{coef:.3g}"
        seconds = time.perf_counter() - t0
        print(
            f"| {name} | {sigma:g} | {label} | {terms} | {coef_text} | {err:.3g} | {kept} | {seconds:.0f} |", flush=True
        )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.noise_weak", description=__doc__.split("\n\n")[0])
    p.add_argument("--only", action="append", default=[], metavar="SYSTEM", help=", ".join(SYSTEMS))
    p.add_argument("--sigmas", type=float, nargs="+", default=[1e-3, 1e-2], help="noise levels (default 1e-3 1e-2)")
    p.add_argument("--widths", type=int, nargs="+", default=[0, 4, 8, 16], help="half widths w (0: plain rows)")
    p.add_argument("--fit-width", type=int, default=4, help="half width of the weak rows in the fits (default 4)")
    args = p.parse_args(argv)
    names = tuple(n for item in args.only for n in item.split(",") if n) or SYSTEMS
    unknown = [n for n in names if n not in SYSTEMS]
    if unknown:
        p.error(f"unknown system {unknown[0]!r}; choose from {', '.join(SYSTEMS)}")
    ldft.limit_threads(1)
    print(f"# load average (uptime) before: {load_average()}", flush=True)
    print("| system | sigma | w | fixed support | backward path (sparsest four) |")
    for name in names:
        for sigma in args.sigmas:
            fixed_support(name, sigma, args.widths)
    print("| system | sigma | fit | terms | coef. error | served 50 / sigma | kept | s |")
    for name in names:
        for sigma in args.sigmas:
            fits(name, sigma, args.fit_width)
    print(f"# load average (uptime) after: {load_average()}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
