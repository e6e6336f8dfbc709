"""1D serving of a polynomial ``L_d`` in numpy: one trajectory against the torch loop, batches against a
hand-written vectorised numpy Störmer–Verlet (scale items 4-5)."""

from __future__ import annotations

import math
import sys
import time
from unittest import mock

import numpy as np
import torch
import xarray as xr

import latticedft as ldft
from latticedft._serve import _onedim

from ._common import Check, Config, Table

NAME = "serve-fast1d"
TITLE = "1D serving in numpy (27-term polynomial, quartic oscillator, dt = 0.1): steps per second"
DT = 0.1


def _init(a: float) -> xr.DataArray:
    """The first two slices of the quartic oscillator from rest at amplitude ``a`` (a Taylor step)."""
    q1 = a - 0.5 * DT**2 * (a + a**3)
    return xr.DataArray([a, q1], dims="t", coords={"t": [0.0, DT]}, name="psi")


def _model(quick: bool) -> ldft.PolynomialLagrangian:
    """``PolynomialLagrangian(orders=(2, 8))`` (27 terms) learned on three Störmer–Verlet trajectories."""
    truth = ldft.lagrangians.verlet(lambda q: 0.5 * q**2 + 0.25 * q**4)
    slices = 40 if quick else 120
    data = [ldft.serve(truth, _init(a), slices=slices, progress=False).field for a in (0.4, 0.8, 1.2)]
    model = ldft.PolynomialLagrangian(orders=(2, 8))
    ldft.learn(model, data)
    return model


def verlet(amps: np.ndarray, steps: int) -> np.ndarray:
    """Hand-written vectorised Störmer–Verlet of ``V = q^2/2 + q^4/4`` on a batch: ``(steps + 2, batch)``."""
    q = np.empty((steps + 2, amps.size))
    q[0] = amps
    q[1] = amps - 0.5 * DT**2 * (amps + amps**3)
    for i in range(1, steps + 1):
        q[i + 1] = 2 * q[i] - q[i - 1] - DT**2 * (q[i] + q[i] ** 3)
    return q


def _serve(model, init, steps: int, torch_loop: bool = False):
    t0 = time.perf_counter()
    if torch_loop:
        with mock.patch.object(_onedim, "numpy_derivatives_of", lambda model: None):
            out = ldft.serve(model, init, slices=steps + 2, progress=False)
    else:
        out = ldft.serve(model, init, slices=steps + 2, progress=False)
    return out, time.perf_counter() - t0


def run(cfg: Config) -> Table:
    torch.manual_seed(0)
    model = _model(cfg.quick)
    n_torch, n_one, n_batch, sizes = (20, 200, 10, (16, 64)) if cfg.quick else (1000, 20000, 200, (64, 1024))
    table = Table(
        NAME,
        TITLE,
        ["serving", "trajectories x steps", "wall time (s)", "trajectory-steps/s", "ratio", "max |q - q_ref|"],
    )
    slow, t_slow = _serve(model, _init(1.0), n_torch, torch_loop=True)
    fast, t_fast = _serve(model, _init(1.0), n_one)
    rate_torch, rate_one = n_torch / t_slow, n_one / t_fast
    diff = float(np.abs(fast.field.values[: n_torch + 2] - slow.field.values).max())
    table.rows.append(["torch loop, one trajectory (reference)", f"1 x {n_torch}", t_slow, rate_torch, 1.0, 0.0])
    table.rows.append(["numpy loop, one trajectory", f"1 x {n_one}", t_fast, rate_one, rate_one / rate_torch, diff])
    rng = np.random.default_rng(0)
    ratio = float("nan")
    for size in sizes:
        amps = rng.uniform(0.3, 1.2, size)
        t_sv = math.inf
        for _ in range(5):  # the best of five: one pass takes milliseconds, a load spike would flatter the ratio
            t0 = time.perf_counter()
            ref = verlet(amps, n_batch)
            t_sv = min(t_sv, time.perf_counter() - t0)
        many, t_many = _serve(model, [_init(float(a)) for a in amps], n_batch)
        loop = many[0].wall_time  # to the end of the Newton loop, before the results are built
        served = np.stack([r.field.values for r in many], axis=1)
        gap = float(np.abs(served - ref).max())
        work = size * n_batch
        table.rows.append(
            [f"vectorised numpy Störmer–Verlet, batch {size}", f"{size} x {n_batch}", t_sv, work / t_sv, 1.0, 0]
        )
        table.rows.append(
            [f"ldft.serve (numpy loop), batch {size}", f"{size} x {n_batch}", t_many, work / t_many, t_many / t_sv, gap]
        )
        table.rows.append(
            [f"  of which the Newton loop, batch {size}", f"{size} x {n_batch}", loop, work / loop, loop / t_sv, gap]
        )
        ratio = t_many / t_sv
    table.notes += [
        "Model: `PolynomialLagrangian(orders=(2, 8))` (27 terms), learned on three Störmer–Verlet trajectories of "
        "V = q^2/2 + q^4/4 (amplitudes 0.4, 0.8, 1.2; dt = 0.1). Ratio column: one-trajectory rows, steps/s over "
        "the torch loop's (the same serve with the numpy route switched off, same process); batch rows, wall "
        "time over the hand-written Störmer–Verlet's on the same batch (amplitudes 0.3 .. 1.2, seed 0; its best "
        "of five passes).",
        "max |q - q_ref|: one trajectory against the torch loop (round-off); batches against Störmer–Verlet "
        "(the learned L_d's own error).",
        "'of which the Newton loop': ServeResult.wall_time, the time to the end of the stepping; the rest of the "
        "serve call checks the inputs and builds one xarray result (field, training-range record) per trajectory.",
    ]
    table.checks.append(
        Check(">= 1e4 steps/s for one trajectory (numpy loop)", f"{rate_one:.3g} steps/s", rate_one >= 1e4)
    )
    table.checks.append(
        Check(
            f"batch {sizes[-1]} within 10x of a vectorised numpy Störmer–Verlet",
            f"{ratio:.3g}x its wall time",
            ratio <= 10,
        )
    )
    return table


if __name__ == "__main__":
    from ._common import run_alone

    sys.exit(run_alone(run, __doc__))
