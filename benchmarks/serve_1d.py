"""1D serving: a Kepler-sized MLP, one orbit and a batch of 16, against scipy.optimize.root per step (item 3)."""

from __future__ import annotations

import sys
import time

import numpy as np
import scipy.optimize
import torch

import latticedft as ldft

from ._common import Check, Config, Table
from ._fixtures import kepler_inits, kepler_mlp

NAME = "serve-1d"
TITLE = "1D serving (Kepler-sized MLP, dt = 0.05, m = 2): trajectory-steps per second"


def root_per_step(model: ldft.AbstractLagrangian, q0: np.ndarray, q1: np.ndarray, steps: int) -> np.ndarray:
    """A peer's serving loop: per step, ``scipy.optimize.root`` (MINPACK hybr, finite-difference Jacobian) on
    the DEL residual ``d/dq_i [L(q_{i-1}, q_i) + L(q_i, q_{i+1})]`` computed with torch autograd of the model."""
    out = [np.asarray(q0, float), np.asarray(q1, float)]
    for _ in range(steps):
        prev = torch.as_tensor(out[-2])
        cur = out[-1]

        def residual(u: np.ndarray, cur: np.ndarray = cur, prev: torch.Tensor = prev) -> np.ndarray:
            q = torch.tensor(cur, requires_grad=True)
            cells = torch.stack([torch.stack([prev, q]), torch.stack([q, torch.as_tensor(u)])])
            (g,) = torch.autograd.grad(model(cells).sum(), q)
            return g.numpy()

        sol = scipy.optimize.root(residual, 2 * cur - out[-2])
        out.append(sol.x)
    return np.array(out)


def run(cfg: Config) -> Table:
    model = kepler_mlp(cfg.quick)
    n, n_base, batch = (20, 3, 16) if cfg.quick else (2000, 40, 16)
    table = Table(
        NAME,
        TITLE,
        [
            "serving",
            "trajectories x steps",
            "wall time (s)",
            "trajectory-steps/s",
            "x root-per-step baseline",
            "max |q - q_baseline|",
        ],
    )
    init = kepler_inits(1)[0]
    q = init.values
    t0 = time.perf_counter()
    base = root_per_step(model, q[0], q[1], n_base)
    t_base = time.perf_counter() - t0
    sps_base = n_base / t_base
    table.rows.append(["scipy.optimize.root per step (baseline)", f"1 x {n_base}", t_base, sps_base, 1.0, 0.0])
    t0 = time.perf_counter()
    one = ldft.serve(model, init, slices=n + 2, progress=False)
    t_one = time.perf_counter() - t0
    diff = float(np.abs(one.field.values[: n_base + 2] - base).max())
    table.rows.append(["ldft.serve, one trajectory", f"1 x {n}", t_one, n / t_one, n / t_one / sps_base, diff])
    diff_b = 0.0
    for size in (batch, 64 if cfg.quick else 256):
        inits = [init] + kepler_inits(size)[1:]
        t0 = time.perf_counter()
        many = ldft.serve(model, inits, slices=n + 2, progress=False)
        t_many = time.perf_counter() - t0
        done = sum(r.slices - 2 for r in many)
        diff_b = float(np.abs(many[0].field.values[: n_base + 2] - base).max())
        table.rows.append(
            [
                f"ldft.serve, batch of {size} (a list)",
                f"{size} x {n}",
                t_many,
                done / t_many,
                done / t_many / sps_base,
                diff_b,
            ]
        )
        if size == batch:
            ratio = done / t_many / sps_base
    table.notes += [
        "Model: `MLPLagrangian(form='kinetic-potential', hidden=[40, 40], activation='tanh', "
        "features='inverse-radius')`, V = net(1/|q|), bound to dt = 0.05, m = 2, learned briefly (L-BFGS) on the "
        "paper's planet orbits. Serving cost depends on the network's size and the Newton iterations, not on "
        "how well it was learned.",
        f"Baseline: per step `scipy.optimize.root` (hybr, finite-difference Jacobian, default tolerance) on the "
        f"DEL residual from torch autograd of the same model, {n_base} steps timed; the last column compares the "
        "first steps of the served orbit with it (root's default tolerance is ~1.5e-8).",
        "Orbits: radii 0.6 .. 2.5 au, near-circular speeds, all bound. The target is checked on the batch of "
        f"{batch}; the larger batch shows how the rate scales with the batch size.",
    ]
    table.checks.append(
        Check(">= 1e4x the root-per-step baseline per trajectory-step, batched", f"{ratio:.3g}x", ratio >= 1e4)
    )
    return table


if __name__ == "__main__":
    from ._common import run_alone

    sys.exit(run_alone(run, __doc__))
