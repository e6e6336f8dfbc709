"""A sparse model served by its numpy closed forms against its torch closed forms, on the discovery rows.

``python -m benchmarks.sparse_serve [SYSTEM ...]`` builds, for each system of
:mod:`benchmarks._discovery_systems` (default: the sparse rows), the model ``select = "auto"`` chooses, and
serves its test from its first two slices twice in one process: by the numpy forms
(``SparseLagrangian.numpy_derivatives``: the 1D numpy Newton loop, n-D slice-Newton's cells in numpy) and with
them withheld (the torch closed forms: the 1D torch loop). It prints the best of 3 serving times, their ratio,
the Newton iterations of both and the largest difference of the served fields over the field's largest value.
``--tile K`` serves the lattice rows' tests tiled ``K`` times along each space axis (their first 30 slices; a
periodic test stays periodic), the time-only rows skipped.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import os
import time
from typing import Any

import numpy as np
import xarray as xr

import latticedft as ldft
from latticedft._case._schema import ModelConfig

from . import _discovery_systems as systems_mod
from .discovery import lattice_dims

#: The discovery rows whose ``select = "auto"`` model is sparse.
SPARSE_ROWS = (
    "oscillator-wells",
    "kepler",
    "charged-particle",
    "pendulum",
    "double-pendulum",
    "sine-gordon-1d",
    "phi4-1d",
    "nlkg-string",
    "sine-gordon-2d",
    "phi4-2d",
)


def _tiled(test: xr.DataArray, k: int) -> xr.DataArray:
    """The first 30 slices of ``test`` repeated ``k`` times along each space axis, the coordinates extended."""
    head = test.isel({test.dims[0]: slice(0, 30)})
    reps = [1] + [1 if d == "component" else k for d in head.dims[1:]]
    coords = {}
    for d, r in zip(head.dims, reps):
        c = np.asarray(head[d].values)
        coords[d] = c if r == 1 else c[0] + np.arange(len(c) * r) * (c[1] - c[0])
    return xr.DataArray(np.tile(head.values, reps), dims=head.dims, coords=coords, attrs=head.attrs, name=head.name)


def _serve(model: Any, system: systems_mod.System, torch_forms: bool) -> tuple[float, Any]:
    """Best of 3 serving times of ``model`` (a fresh copy: its cached forms are its own) and the last result."""
    model = copy.deepcopy(model)
    if torch_forms:
        model.numpy_derivatives = lambda pairs: None  # withheld: the torch closed forms serve
    times, out = [], None
    for _ in range(3):
        t0 = time.perf_counter()
        try:
            out = ldft.serve(model, system.test, slices=system.slices, boundary=system.boundary, progress=False)
        except ldft.ServeError as exc:
            out = exc.result
        times.append(time.perf_counter() - t0)
    return min(times), out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("systems", nargs="*", default=list(SPARSE_ROWS))
    p.add_argument("--tile", type=int, default=1, metavar="K", help="lattice rows' tests tiled K times in space")
    args = p.parse_args(argv)
    names = args.systems
    print(f"# load average (uptime) before: {', '.join(f'{x:.2f}' for x in _load())}")
    for name in names:
        system = systems_mod.SYSTEMS[name](False)
        if args.tile > 1:
            if lattice_dims(system.test) == 1:
                continue
            system = dataclasses.replace(system, test=_tiled(system.test, args.tile), slices=30)
        hand = ModelConfig(select="auto").build(lattice_dims(system.test))
        model = ldft.select(hand, system.train, "auto", boundary=system.boundary).model
        t_torch, slow = _serve(model, system, True)
        t_numpy, fast = _serve(model, system, False)
        a, b = np.asarray(slow.field.values, float), np.asarray(fast.field.values, float)
        diff = np.nanmax(np.abs(a - b)) / np.nanmax(np.abs(a)) if a.shape == b.shape else float("nan")
        print(
            f"{name}: {model.kind} {tuple(a.shape)}: torch forms {t_torch * 1e3:.1f} ms, numpy forms "
            f"{t_numpy * 1e3:.1f} ms ({t_torch / t_numpy:.1f}x); Newton iterations {slow.newton_iterations} and "
            f"{fast.newton_iterations}; fields differ by {diff:.1e} of the max",
            flush=True,
        )
    print(f"# load average (uptime) after: {', '.join(f'{x:.2f}' for x in _load())}")


def _load() -> tuple[float, float, float]:
    return os.getloadavg()


if __name__ == "__main__":
    main()
