"""Work run in a fresh Python (see ``_common.in_subprocess``) so its peak resident memory is its own.

Each probe warms up, builds its inputs, resets the kernel's resident-set high-water mark and reads the
resident memory (the baseline: interpreter, torch, inputs), does the work, and reads the high-water mark
(see ``_common.PeakRSS``). It counts torch's and numpy's allocations and the allocator's slack alike.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch

import latticedft as ldft
from latticedft import systems

from ._common import PeakRSS
from ._fixtures import DT, DX, membrane_field, string_field


def _warm_up_serving() -> None:
    """Load the lazily imported code paths (scipy.sparse, autograd kernels) on a tiny lattice first."""
    ldft.serve(ldft.lagrangians.wave(), membrane_field(6, 4)[1], progress=False)
    for boundary in ("dirichlet", "periodic"):
        ldft.serve(ldft.lagrangians.wave(), string_field(8, 4, boundary)[1], boundary=boundary, progress=False)


def serve_membrane(n: int, nt: int) -> dict[str, Any]:
    _warm_up_serving()
    ref, da = membrane_field(n, nt)
    h = float(da["x"][1] - da["x"][0])
    dt = float(da["t"][1] - da["t"][0])
    t0 = time.perf_counter()
    lf = systems.leapfrog(ref[0], ref[1], nt - 1, dt, h, boundary_values=ref)
    t_lf = time.perf_counter() - t0
    mem = PeakRSS()
    t0 = time.perf_counter()
    res = ldft.serve(ldft.lagrangians.wave(), da, progress=False)
    t_newton = time.perf_counter() - t0
    out = {
        "sites": (nt - 2) * (n - 2) ** 2,
        "t_newton": t_newton,
        "t_leapfrog": t_lf,
        "solver": res.solver,
        "iterations": res.newton_iterations,
        "error": float(np.abs(res.field.values - lf).max()),
        "rss_before": mem.before,
        "rss_peak": mem.peak(),
        "reset": mem.reset,
        "field_mib": ref.nbytes / 2**20,
    }
    del res
    mem = PeakRSS()
    t0 = time.perf_counter()
    forced = ldft.serve(ldft.lagrangians.wave(), da, progress=False, affine=False)
    out.update(
        t_forced=time.perf_counter() - t0,
        forced_iterations=forced.newton_iterations,
        forced_error=float(np.abs(forced.field.values - lf).max()),
        forced_rss_before=mem.before,
        forced_rss_peak=mem.peak(),
    )
    return out


def serve_string(nx: int, nt: int, boundary: str) -> dict[str, Any]:
    _warm_up_serving()
    ref, da = string_field(nx, nt, boundary)
    mem = PeakRSS()
    t0 = time.perf_counter()
    ldft.serve(ldft.lagrangians.wave(), da, boundary=boundary, progress=False)
    return {
        "seconds": time.perf_counter() - t0,
        "rss_before": mem.before,
        "rss_peak": mem.peak(),
        "reset": mem.reset,
        "field_mib": ref.nbytes / 2**20,
    }


def train_kg_mlp(n: int, iterations: int) -> dict[str, Any]:
    data = systems.klein_gordon_training_set(n=n, steps=20, seed=0)
    model = ldft.MLPLagrangian(hidden=[10, 10], activation="tanh", form="kinetic-potential", seed=0)
    ldft.learn(
        ldft.MLPLagrangian(hidden=[10, 10], activation="tanh", form="kinetic-potential"),
        data[:1],
        optimizer="lbfgs",
        max_iter=1,
        progress=False,
    )  # warm-up
    mem = PeakRSS()
    rep = ldft.learn(model, data, optimizer="lbfgs", max_iter=iterations, progress=False)
    return {
        "seconds": rep.wall_time,
        "iterations": rep.iterations,
        "sites": rep.n_sites,
        "rss_before": mem.before,
        "rss_peak": mem.peak(),
        "reset": mem.reset,
    }


def train_kepler_paper(iterations: int, planets: list[str]) -> dict[str, Any]:
    data = [systems.planet_orbit(p, dt=0.05) for p in planets]
    model = ldft.MLPLagrangian(preset="paper", seed=0)
    ldft.learn(ldft.MLPLagrangian(preset="paper"), data[:1], optimizer="lbfgs", max_iter=1, progress=False)
    mem = PeakRSS()
    rep = ldft.learn(model, data, optimizer="lbfgs", max_iter=iterations, progress=False)
    return {
        "seconds": rep.wall_time,
        "iterations": rep.iterations,
        "sites": rep.n_sites,
        "rss_before": mem.before,
        "rss_peak": mem.peak(),
        "reset": mem.reset,
    }


PROBES = {f.__name__: f for f in (serve_membrane, serve_string, train_kg_mlp, train_kepler_paper)}


def run(name: str, threads: int, kwargs: dict[str, Any]) -> dict[str, Any]:
    torch.set_num_threads(threads)
    return PROBES[name](**kwargs)


__all__ = ["run", "PROBES", "DT", "DX"]
