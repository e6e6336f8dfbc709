"""n-D serving by slice-Newton: the slice solvers (site-wise, Krylov, LU) against a hand-written numpy leapfrog.

``python -m benchmarks --only serve-nd``, or alone: ``python -m benchmarks.serve_nd [--quick]`` (``--quick``:
tiny lattices, the first kernel build timed in 1+1D only; seconds). Some rows alone, their targets only:
``python -m benchmarks.serve_nd --only polynomial --dims 3`` (``--only`` words of the L_d column, repeatable;
``--repeat N``: the least of N timed serves a row, for a figure steadier under load than one serve).
"""

from __future__ import annotations

import contextlib
import functools
import math
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
import torch

import latticedft as ldft
from latticedft import systems
from latticedft._action import CellDerivatives
from latticedft._lattice import as_lattice_field, gather_cells
from latticedft._serve._slices import _SliceSystem
from latticedft._serve._solvers import factor_step

from ._common import Check, Config, PeakRSS, Table, best_times, load_average

NAME = "serve-nd"
TITLE = "n-D serving: slice-Newton (site-wise / Krylov / LU steps) vs an in-place numpy leapfrog, periodic sine-Gordon"

H = 0.05  # the spacing of every lattice (a learned L_d belongs to its lattice); the domain grows with the sites
COURANT = 0.4  # dt = COURANT * h


def _sizes(quick: bool) -> dict[int, list[int]]:
    """Spatial sizes per dimension (sites per axis)."""
    if quick:
        return {1: [64], 2: [16], 3: [8]}
    return {1: [1024, 4096, 16384], 2: [64, 128, 256], 3: [32, 48, 64]}


def _slices(n_sites: int, quick: bool, most: int = 66) -> int:
    """Time slices served: enough for ~2e6 site updates, between 6 and ``most``."""
    return 6 if quick else int(min(most, max(6, 2 + 2_000_000 // n_sites)))


def _initial(ndim: int, n: int) -> tuple[np.ndarray, float, float]:
    """A smooth periodic field of ``n`` sites per axis at rest, its spacing h and time step dt."""
    h = H
    x = np.arange(n) / n
    u = np.ones([n] * ndim)
    for k in range(ndim):
        shape = [1] * ndim
        shape[k] = n
        u = u * (np.sin if k % 2 == 0 else np.cos)(2 * np.pi * x).reshape(shape)
    return 0.8 * u, h, COURANT * h


def _neighbour_slices(ndim: int) -> list[tuple[tuple[slice, ...], tuple[slice, ...]]]:
    """(target, source) index pairs that add each site's two periodic neighbours along every axis, in the
    order ``np.roll(b, 1, k)`` then ``np.roll(b, -1, k)`` for k = 0, 1, ...: the same sums, to the bit."""
    every = slice(None)
    pairs = []
    for k in range(ndim):

        def at(s: slice, k: int = k) -> tuple[slice, ...]:
            return (every,) * k + (s,)

        pairs += [(at(slice(1, None)), at(slice(None, -1))), (at(slice(0, 1)), at(slice(-1, None)))]
        pairs += [(at(slice(None, -1)), at(slice(1, None))), (at(slice(-1, None)), at(slice(0, 1)))]
    return pairs


def leapfrog(u0: np.ndarray, u1: np.ndarray, steps: int, dt: float, h: float) -> np.ndarray:
    """Hand-written numpy leapfrog of ``psi_tt = Laplacian psi - sin psi``, periodic: the last slice.

    In place: four arrays allocated once, the periodic neighbours added by slicing, no array allocated per
    step (the fair baseline of a vectorised integrator). Each step evaluates
    ``2 b - a + c lap - dt^2 sin b`` in that order, so the slices are those of the textbook ``np.roll`` form
    to the bit."""
    a, b = u0.copy(), u1.copy()
    lap, tmp = np.empty_like(b), np.empty_like(b)
    c, dt2 = (dt / h) ** 2, dt**2
    pairs = _neighbour_slices(b.ndim)
    for _ in range(steps):
        np.multiply(b, -2 * b.ndim, out=lap)
        for target, source in pairs:
            lap[target] += b[source]
        np.multiply(b, 2, out=tmp)
        np.subtract(tmp, a, out=a)
        lap *= c
        a += lap
        np.sin(b, out=tmp)
        tmp *= dt2
        a -= tmp
        a, b = b, a
    return b


def sine_gordon() -> ldft.AnalyticLagrangian:
    """The sine-Gordon ``L_d`` on the first-order stencil: it serves exactly :func:`leapfrog`. Its closed form
    (for the compiled DEL kernel) is the same expression written with sympy."""

    def fn(cells: torch.Tensor, h: tuple[float, ...]) -> torch.Tensor:
        u = cells[..., 0, 0]
        out = 0.5 * ((cells[..., 1, 0] - u) / h[0]) ** 2 - (1 - torch.cos(u))
        for k in range(1, len(h)):
            out = out - 0.5 * ((cells[..., k + 1, 0] - u) / h[k]) ** 2
        return out

    def closed(cells: Any, h: tuple[float, ...]) -> Any:
        import sympy

        u = cells[0, 0]
        out = 0.5 * ((cells[1, 0] - u) / h[0]) ** 2 - (1 - sympy.cos(u))
        for k in range(1, len(h)):
            out = out - 0.5 * ((cells[k + 1, 0] - u) / h[k]) ** 2
        return out

    return ldft.AnalyticLagrangian(fn, name="sine-Gordon", closed_form=closed)


def _field(u: np.ndarray, h: float, dt: float) -> Any:
    ndim = u.ndim - 1
    dims = ("t", *"zyx"[3 - ndim :])
    attrs = {d: {"periodic": "true", "period": u.shape[1] * h} for d in dims[1:]}
    return systems.make_field(u, dims, spacing=(dt, *[h] * ndim), coord_attrs=attrs)


def training_field(ndim: int, quick: bool) -> Any:
    """The small periodic sine-Gordon field of the dimension that the benchmark's polynomials learn from."""
    n = {1: 32, 2: 12, 3: 6}[ndim]
    nt = 12 if quick else 24
    u0, h, dt = _initial(ndim, n)
    u = np.empty((nt, *u0.shape))
    u[0] = u[1] = u0
    for i in range(1, nt - 1):
        u[i + 1] = leapfrog(u[i - 1], u[i], 1, dt, h)
    return _field(u, h, dt)


@functools.lru_cache(maxsize=4)
def learned_polynomial(ndim: int, quick: bool) -> ldft.PolynomialLagrangian:
    """The sine-Gordon case's polynomial class (orders (2, 12), time-symmetric) learned on a small periodic
    sine-Gordon field of the dimension (:func:`training_field`)."""
    model = ldft.PolynomialLagrangian(orders=(2, 12), time_symmetric=True)
    ldft.learn(model, training_field(ndim, quick), progress=False)
    return model


def _serve_row(
    label: str, model: Any, ndim: int, n: int, quick: bool, most: int = 66, repeat: int = 1
) -> tuple[list[Any], float]:
    """One row: serving ``model`` against the in-place leapfrog, wall and CPU time (the least of ``repeat`` timed
    serves of the same field); the CPU-time ratio."""
    u0, h, dt = _initial(ndim, n)
    nt = _slices(n**ndim, quick, most)
    lf_wall, lf_cpu, last = best_times(lambda: leapfrog(u0, u0, nt - 2, dt, h), repeat=3)
    init = np.stack([u0, u0])
    da = _field(init, h, dt)
    ldft.serve(model, da, slices=3, progress=False)  # warm-up (binding, first-call costs)
    mem = PeakRSS()
    wall, cpu = math.inf, math.inf
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        res = ldft.serve(model, da, slices=nt, progress=False)
        wall, cpu = min(wall, time.perf_counter() - t0), min(cpu, time.process_time() - c0)
    sites = (nt - 2) * n**ndim
    err = float(np.abs(res.field.values[-1] - last).max())
    fresh = "-"
    if res.slice_solver == "sitewise":  # once more on a lattice not seen before (its index tables built anew)
        _forget_lattices()
        c0 = time.process_time()
        ldft.serve(model, da, slices=nt, progress=False)
        fresh = (time.process_time() - c0) / lf_cpu
    row = [
        f"{n}^{ndim} x {nt}" if ndim > 1 else f"{n} x {nt}",
        f"{ndim}+1D",
        label,
        res.solver,
        res.slice_solver or "-",
        sites / cpu,
        sites / lf_cpu,
        cpu / lf_cpu,
        fresh,
        wall / lf_wall,
        res.newton_iterations / (nt - 2),
        err,
        mem.peak(),
    ]
    return row, cpu / lf_cpu


def _forget_lattices() -> None:
    """Drop the slice systems and index tables that serving keeps for the last lattices it served."""
    from latticedft._serve import _field, _fused

    _field._SYSTEMS.clear()
    _fused._TABLES.clear()


def _coupled_3d() -> ldft.AnalyticLagrangian:
    """A non-quadratic 3+1D ``L_d`` on the first-order stencil whose time difference mixes with the spatial ones
    (``eps d_t d_k`` terms): its slice Jacobian couples every unknown to its 6 neighbours."""
    eps = 0.2

    def fn(c: torch.Tensor, h: tuple[float, ...]) -> torch.Tensor:
        u = c[..., 0, 0]
        dt = (c[..., 1, 0] - u) / h[0]
        out = 0.5 * dt**2 - (1 - torch.cos(u))
        for k in range(1, len(h)):
            dk = (c[..., k + 1, 0] - u) / h[k]
            out = out - 0.5 * dk**2 + eps * dt * dk
        return out

    return ldft.AnalyticLagrangian(fn, name="coupled sine-Gordon")


def _lu_vs_krylov(table: Table, n: int) -> None:
    """Factor and solve time of one slice-Newton step's linear system, sparse LU against preconditioned GMRES."""
    model = _coupled_3d()
    u0, h, dt = _initial(3, n)
    f = as_lattice_field(_field(np.stack([u0, u0]), h, dt), source="init", min_slices=2)
    model.bind(f.ndim, f.ncomp, f.spacing, f.components)
    sys = _SliceSystem(model, f)
    cells = gather_cells(f.values[:2], model.stencil, f.boundary)
    ev = CellDerivatives(model, cells)
    blocks = ev.blocks(sys.pairs)
    vol = math.prod(model.spacing)
    rhs = np.random.default_rng(0).standard_normal(sys.n * sys.m)
    out = {}
    for name in ("krylov", "lu"):
        t0 = time.perf_counter()
        solve, _ = factor_step(sys, blocks, vol, name, 1e-10 * float(np.abs(rhs).max()))
        t1 = time.perf_counter()
        x = solve(rhs)
        t2 = time.perf_counter()
        out[name] = (t1 - t0, t2 - t1, x)
    diff = float(np.abs(out["krylov"][2] - out["lu"][2]).max() / np.abs(out["lu"][2]).max())
    table.rows.append([f"{n}^3", sys.n, out["lu"][0], out["lu"][1], out["krylov"][0], out["krylov"][1], diff])


def _sizes_of(ndim: int, quick: bool) -> list[int]:
    return _sizes(quick)[ndim]


@functools.lru_cache(maxsize=2)
def learned_mlp(quick: bool) -> Any:
    """A kinetic-plus-potential MLP (``hidden=[16, 16]``, tanh) trained briefly on a small 2+1D sine-Gordon field."""
    u0, h, dt = _initial(2, 12)
    u = np.empty((12, *u0.shape))
    u[0] = u[1] = u0
    for i in range(1, 11):
        u[i + 1] = leapfrog(u[i - 1], u[i], 1, dt, h)
    model = ldft.MLPLagrangian(hidden=[16, 16], activation="tanh", form="kinetic-potential", seed=0)
    ldft.learn(model, _field(u, h, dt), max_iter=5 if quick else 40, progress=False)
    return model


@contextlib.contextmanager
def _empty_kernel_folder() -> Iterator[None]:
    """An empty kernel folder (``LATTICEDFT_KERNEL_CACHE``) and no kernel loaded in the process, for a block."""
    import os
    import tempfile

    from latticedft._kernel import _LOADED

    before = os.environ.get("LATTICEDFT_KERNEL_CACHE")
    with tempfile.TemporaryDirectory() as folder:
        os.environ["LATTICEDFT_KERNEL_CACHE"] = folder
        try:
            _LOADED.clear()
            yield
        finally:
            _LOADED.clear()
            if before is None:
                os.environ.pop("LATTICEDFT_KERNEL_CACHE", None)
            else:
                os.environ["LATTICEDFT_KERNEL_CACHE"] = before


def _kernel_builds(ndim: int) -> tuple[float, float]:
    """Seconds of the first build of the analytic sine-Gordon's compiled kernels (in an empty kernel folder) and
    of their load from that folder (as in a later run): both apart from serving."""
    from latticedft._action import compiled_closed_forms
    from latticedft._kernel import _LOADED

    with _empty_kernel_folder():
        t0 = time.perf_counter()
        compiled_closed_forms(sine_gordon_bound(ndim), torch.zeros(0, dtype=torch.float64))
        first = time.perf_counter() - t0
        _LOADED.clear()
        t0 = time.perf_counter()
        compiled_closed_forms(sine_gordon_bound(ndim), torch.zeros(0, dtype=torch.float64))
        return first, time.perf_counter() - t0


def _folded_builds() -> tuple[float, float]:
    """Seconds of the first build of the folded polynomial kernels (one module for every polynomial) and of
    their load from the kernel folder: both apart from serving."""
    from latticedft._kernel import _LOADED
    from latticedft._kernel_folded import folded_kernels

    with _empty_kernel_folder():
        t0 = time.perf_counter()
        folded_kernels()
        first = time.perf_counter() - t0
        _LOADED.clear()
        t0 = time.perf_counter()
        folded_kernels()
        return first, time.perf_counter() - t0


def sine_gordon_bound(ndim: int) -> ldft.AnalyticLagrangian:
    model = sine_gordon()
    model.bind(ndim + 1, 1, (COURANT * H, *[H] * ndim))
    return model


def _oscillator_steps(quick: bool) -> float:
    """Steps per CPU second of one trajectory of the 27-term polynomial oscillator (``serve_fast1d``'s model)."""
    from . import serve_fast1d

    model = serve_fast1d._model(quick)
    steps = 500 if quick else 20_000
    with ldft.set_options(compiled_numpy_models=True):  # its compiled trajectory loop (first build apart)
        ldft.serve(model, serve_fast1d._init(0.8), slices=5, progress=False)
        c0 = time.process_time()
        ldft.serve(model, serve_fast1d._init(0.8), slices=steps + 2, progress=False)
        return steps / (time.process_time() - c0)


def _runs(
    cfg: Config, keep: Callable[[str, int], bool] = lambda label, ndim: True
) -> list[tuple[str, Any, int, int, int, bool]]:
    """(label, model, dims, sites per axis, most slices, compiled kernels on) of every serving row that ``keep``
    (label, dims) keeps; a model is learned only for a row kept."""
    runs = []
    for ndim, ns in _sizes(cfg.quick).items():
        # the learned polynomial's derivatives cost ~100x the sine-Gordon's: fewer slices, and in 3+1D two sizes
        poly_ns = ns if ndim < 3 or cfg.quick else [32, 64]
        target = {1: 16384, 2: 128, 3: 32}[ndim] if not cfg.quick else ns[-1]
        if keep(POLY + ", compiled", ndim) or keep(POLY + ", numpy forms", ndim):
            poly = learned_polynomial(ndim, cfg.quick)
            runs += [(POLY + ", compiled", poly, ndim, n, 10, True) for n in poly_ns]
            runs.append((POLY + ", numpy forms", poly, ndim, target, 10, False))
        runs += [("sine-Gordon, analytic, compiled", sine_gordon(), ndim, n, 66, True) for n in ns]
        runs.append(("sine-Gordon, analytic, not compiled", sine_gordon(), ndim, ns[-1], 66, False))
    big2 = _sizes(cfg.quick)[2][-2 if not cfg.quick else -1]
    if keep(MLP, 2):
        runs.append((MLP, learned_mlp(cfg.quick), 2, big2, 6, True))
    return [r for r in runs if keep(r[0], r[2])]


def keeper(only: Sequence[str] = (), dims: Sequence[int] = ()) -> Callable[[str, int], bool]:
    """Whether a row (label, dims) is measured: its label holds one of ``only`` (case-insensitive; none: every
    label) and its dimension is one of ``dims`` (none: every dimension)."""
    words = [w.lower() for w in only]

    def keep(label: str, ndim: int) -> bool:
        return (not words or any(w in label.lower() for w in words)) and (not dims or ndim in dims)

    return keep


MLP = "MLP (kinetic-potential, 16x16), learned"
POLY = "polynomial (2, 12), learned"


def _targets(table: Table, worst: dict[str, float], per_site: dict[str, list[float]], steps: float) -> None:
    """The targets' checks: CPU-time ratios at >= 128^2 and >= 32^3 sites (1+1D: >= 16384), 1D steps per second,
    cost linear in sites (the analytic rows' sites per CPU second within 1.5x over the sizes of a dimension from
    4096, 128^2 and 32^3 sites: below, the fixed cost of a call dominates)."""
    _ratio_checks(table, worst, every=True)
    table.checks.append(Check("1D polynomial oscillator, one trajectory: >= 2e5 steps/s", f"{steps:.3g}", steps >= 2e5))
    spread = max((max(v) / min(v) for v in per_site.values() if len(v) > 1), default=1.0)
    table.checks.append(
        Check("cost linear in sites: analytic sites/CPU s within 1.5x over the sizes", f"{spread:.2f}x", spread <= 1.5)
    )


def _ratio_checks(table: Table, worst: dict[str, float], every: bool) -> None:
    """The CPU-ratio targets: of every row kind and dimension (``every``; one not measured reads inf), or of those
    measured only."""
    for key, bound, dims in (
        ("sine-Gordon, analytic, compiled", 2.0, (1, 2, 3)),
        (POLY + ", compiled", 10.0, (1, 2, 3)),
        (MLP, 30.0, (2,)),
    ):
        for d in dims:
            if not every and f"{key} {d}+1D" not in worst:
                continue
            v = worst.get(f"{key} {d}+1D", math.inf)
            name = "MLP" if key == MLP else key
            table.checks.append(
                Check(f"{name} {d}+1D: CPU <= {bound:g}x the in-place leapfrog", f"{v:.3g}x", v <= bound)
            )


def run(cfg: Config, only: Sequence[str] = (), dims: Sequence[int] = (), repeat: int = 1) -> Table:
    """The table; with ``only`` (words of the L_d column) or ``dims``, of those rows alone (:func:`keeper`), without
    the kernel builds, the 1D oscillator and the linear-solver notes, and with the measured rows' targets only;
    ``repeat``: the timed serves of a row, of which the least time is reported (1: one, as the full run)."""
    table = Table(
        NAME,
        TITLE,
        [
            "lattice (sites x slices)",
            "dims",
            "L_d",
            "solver",
            "slice solver",
            "serve sites/CPU s",
            "leapfrog sites/CPU s",
            "serve / leapfrog CPU",
            "same, lattice new",
            "serve / leapfrog wall",
            "iters/slice",
            "max |served - leapfrog| (last slice)",
            "peak RSS (MiB)",
        ],
    )
    before = load_average()
    whole = not only and not dims
    builds = {d: _kernel_builds(d) for d in ((1,) if cfg.quick else (1, 2, 3))} if whole else {}  # quick: once
    worst: dict[str, float] = {}
    per_site: dict[str, list[float]] = {}
    for label, model, ndim, n, most, compiled in _runs(cfg, keeper(only, dims)):
        with ldft.set_options(compiled_kernels=compiled, compiled_numpy_models=compiled):
            row, ratio = _serve_row(label, model, ndim, n, cfg.quick, most, repeat)
        table.rows.append(row)
        if n**ndim >= {1: 16384, 2: 128**2, 3: 32**3}[ndim] or cfg.quick:
            key = f"{label} {ndim}+1D"
            worst[key] = max(worst.get(key, 0.0), ratio)
        if (
            label.startswith("sine-Gordon")
            and label.endswith(", compiled")
            and (n**ndim >= {1: 4096, 2: 128**2, 3: 32**3}[ndim] or cfg.quick)
        ):
            per_site.setdefault(f"{ndim}", []).append(float(row[5]))
    if not whole:
        table.notes.append(
            f"Rows of L_d {', '.join(map(repr, only)) or 'any'} in dimensions {', '.join(map(str, dims)) or 'any'} "
            f"alone; load average before {before}, after {load_average()}. The targets of the rows measured only."
            + (f" Serve times: the least of {repeat} timed serves of each row." if repeat > 1 else "")
        )
        _ratio_checks(table, worst, every=False)
        return table
    builds[0] = _folded_builds()
    steps = _oscillator_steps(cfg.quick)
    _notes(table, cfg, before, builds, steps)
    _targets(table, worst, per_site, steps)
    return table


def _notes(table: Table, cfg: Config, before: str, builds: dict[int, tuple[float, float]], steps: float) -> None:
    factor = Table(
        NAME, "", ["lattice", "unknowns", "LU factor (s)", "LU solve (s)", "Krylov setup (s)", "GMRES (s)", "rel. diff"]
    )
    for n in [6] if cfg.quick else [16, 24, 32]:
        _lu_vs_krylov(factor, n)
    for r in factor.rows:
        table.notes.append(
            f"One Newton step's linear system of a coupled 3+1D Jacobian (first-order stencil with eps d_t d_k "
            f"terms, 3 off-diagonal blocks per row), {r[0]} ({r[1]:,} unknowns): sparse LU factor {r[2]:.3g} s "
            f"+ solve {r[3]:.3g} s; "
            f"Krylov setup {r[4]:.3g} s + GMRES {r[5]:.3g} s; steps differ by {r[6]:.1e} (relative)."
        )
    folded = builds.pop(0)
    built = "; ".join(f"{d}+1D {a:.2f} s first build, {b:.2f} s loaded from the cache" for d, (a, b) in builds.items())
    table.notes += [
        "Every lattice periodic, the field at rest at t = 0; sites = time slices served minus the two given, times "
        "the sites of a slice. Serve time: the whole `ldft.serve` call after a 3-slice warm-up (which builds or "
        "loads the compiled kernel: reported apart below); leapfrog: "
        "the numpy leapfrog of psi_tt = Laplacian psi - sin psi written in this benchmark, in place (four arrays "
        "allocated once, neighbours added by slicing, nothing allocated per step), the call of least wall time "
        "of 3, in the same process. Serving keeps the slice system and the compiled kernel's index tables of "
        "the last lattices it served, so the timed call (after the warm-up on the same lattice) reuses them; "
        "'same, lattice new': the CPU ratio of one more call after dropping them (a field on a lattice not "
        "served before), for the rows the compiled slice Newton serves.",
        "CPU: `time.process_time` (every thread of the process); wall: `time.perf_counter`. The ratios are "
        f"serve / leapfrog; load average before {before}, after {load_average()} (the wall ratio suffers "
        "from other load, the CPU ratio much less).",
        f"Compiled DEL kernel of the analytic sine-Gordon (sympy -> numba, outside the serve times): {built}.",
        f"Folded polynomial kernels (one numba module for every polynomial, its folded coefficients as data; "
        f"outside the serve times): {folded[0]:.2f} s first build, {folded[1]:.2f} s loaded from the cache.",
        f"1D: one trajectory of the 27-term polynomial oscillator of serve-fast1d: {steps:.3g} steps per CPU second.",
        "slice solver: `ServeResult.slice_solver` chosen by solver='auto': site-wise for sine-Gordon (its "
        "first-order slice Jacobian is block diagonal; 'compiled': every slice after the first in the compiled "
        "slice Newton kernel; 'not compiled': today's torch path); the polynomial's cell mean couples "
        "neighbouring unknowns, so LU in 1+1D and Krylov beyond ('compiled': its folded coefficients on the "
        "compiled folded kernels, the default; 'numpy forms': `set_options(compiled_kernels=False)`).",
        "L_d: 'learned' is `PolynomialLagrangian(orders=(2, 12), time_symmetric=True)` (the class of "
        "cases/sine-gordon) learned by exact least squares on a small sine-Gordon field of the same dimension; "
        "its last-slice column is the learned model's error. 'analytic' is the sine-Gordon L_d written in closed form "
        "(`AnalyticLagrangian` with its sympy `closed_form`); it serves the leapfrog exactly (round-off). 'MLP' is "
        "trained briefly (a timing, not an accurate model) and served by default (its "
        "potential's derivative in closed form, batched over sites).",
        "Peak RSS: the kernel's high-water mark reset before serving (the process's whole memory, inputs included).",
    ]


def main(argv: list[str] | None = None) -> int:
    import argparse

    from ._common import print_table

    p = argparse.ArgumentParser(prog="python -m benchmarks.serve_nd", description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="tiny lattices (seconds)")
    p.add_argument("--threads", type=int, default=1, help="threads of torch and BLAS (default 1)")
    p.add_argument(
        "--only", action="append", default=[], metavar="WORDS", help="rows whose L_d holds WORDS ('polynomial', 'MLP')"
    )
    p.add_argument("--dims", type=int, nargs="+", default=[], choices=(1, 2, 3), help="space dimensions of the rows")
    p.add_argument(
        "--repeat", type=int, default=1, metavar="N", help="time N serves of each row, report the least (default 1)"
    )
    args = p.parse_args(argv)
    if args.repeat < 1:
        p.error("--repeat: expected a count of at least 1")
    ldft.limit_threads(args.threads)
    print(f"# load average before: {load_average()}", flush=True)
    t0 = time.perf_counter()
    table = run(Config(quick=args.quick, threads=args.threads), tuple(args.only), tuple(args.dims), args.repeat)
    table.seconds = time.perf_counter() - t0
    print_table(table)
    print(f"# load average after: {load_average()}", flush=True)
    if not table.rows:
        print("serve_nd: no row matches --only/--dims", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
