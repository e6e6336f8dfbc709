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
import latticedft.io
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


def scale_fields(n: int, nx: int, nt: int, first: int = 0) -> list[Any]:
    """Fields ``first .. n - 1`` of a family of 1+1D wave-string fields (``nx`` sites, ``nt`` slices): two
    modes each, different per field."""
    return [systems.wave_string([(1 + k % 7, 0.5), (2 + k % 5, 0.2, 0.1 * k)], nx=nx, nt=nt) for k in range(first, n)]


def train_scale(
    n: int, nx: int, nt: int, orders: list[int], chunk_sites: int | None, files: str | None = None
) -> dict[str, Any]:
    """The exact solve of a polynomial L_d on ``n`` fields, in memory (``chunk_sites=0``) or streamed;
    ``files``: a folder to write the fields to first and train from their paths (read lazily)."""
    data: list[Any]
    if files is None:
        data = scale_fields(n, nx, nt)
    else:  # written one at a time (and kept for the next call): none of them is in this process's memory
        from pathlib import Path

        folder = Path(files)
        folder.mkdir(parents=True, exist_ok=True)
        data = []
        for k in range(n):
            path = folder / f"field_{nx}x{nt}_{k:06d}.nc"
            if not path.exists():
                (f,) = scale_fields(k + 1, nx, nt, first=k)
                ldft.io.write_field(path, {"psi": f})
            data.append(str(path))
    ldft.learn(ldft.PolynomialLagrangian(tuple(orders)), scale_fields(1, 16, 12), chunk_sites=chunk_sites)  # warm-up
    mem = PeakRSS()
    model = ldft.PolynomialLagrangian(tuple(orders))
    t0 = time.perf_counter()
    rep = ldft.learn(model, data, chunk_sites=chunk_sites, progress=False)
    seconds = time.perf_counter() - t0
    return {
        "seconds": seconds,
        "rss_before": mem.before,
        "rss_peak": mem.peak(),
        "reset": mem.reset,
        "sites": rep.n_sites,
        "rel_res": rep.rel_res,
        "coef": model.coef.detach().tolist(),
        "data_mib": n * nx * nt * 8 / 2**20,
    }


PROBES = {f.__name__: f for f in (serve_membrane, serve_string, train_kg_mlp, train_kepler_paper, train_scale)}


def run(name: str, threads: int, kwargs: dict[str, Any]) -> dict[str, Any]:
    torch.set_num_threads(threads)
    return PROBES[name](**kwargs)


__all__ = ["run", "PROBES", "DT", "DX"]
