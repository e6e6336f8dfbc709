"""The noise correction's Hessian products: the assembled sparse Hessian against a double backward pass.

    python -m benchmarks.noise_hessian [--sizes small,medium] [--repeat 2] [--new-only large]

The correction of a field toward the learned DEL (``latticedft._learn._noise``) solves its Gauss-Newton steps by
conjugate gradients whose products are Hessian-vector products of the action. They are taken from the action's
Hessian assembled once per step as a sparse matrix (:func:`latticedft._action.action_hessian`); this prints, side
by side in one process, the same work with a double backward pass of the action through the model per product (as
the correction was first built), on the fields of ``cases/sine-gordon`` (a breather, dx = 0.1, dt = 0.05, the
case's polynomial (2, 12) even in time) and ``cases/wave-2d`` (its membrane modes, dx = 1/64, dt = dx / 2,
polynomial (2, 2)), noise ``1e-3`` of the amplitude (seed 0), the model learned plainly on the noisy field.
Sizes (time x space): ``small`` 41 x 61 and 11 x 17 x 17, ``medium`` 101 x 201 and 21 x 33 x 33, ``large`` the
cases' own 401 x 401 and 41 x 65 x 65 (with ``--new-only``: the double backward for one product alone).

Per field: one product (the double backward, against the assembly and one sparse product), one correction round of
the noise-aware fit (strength 30, one step) and one denoised start (the first 20 slices, strength 1e5, two steps):
the time of each path, the shorter of ``--repeat`` runs, and the largest difference of their results relative to
the largest move of the field. One torch thread.

``--solvers``: on each field's denoised-start window instead, the system of its first Gauss-Newton step solved by
scipy's conjugate gradients (products with the assembled Hessian) to the correction's residual ``1e-10``, without
and with a diagonal (Jacobi) preconditioner, and (1+1D fields only: on a 2+1D window it had not finished within two
minutes) by a sparse direct solve: iterations and times.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch
import xarray as xr

import latticedft as ldft
from latticedft import systems
from latticedft._action import _action, action_hessian
from latticedft._lattice import LatticeField, as_lattice_field, interior_slices
from latticedft._learn import _noise

#: The training modes of ``cases/wave-2d/make_data.py``.
MODES = [(1, 1, 1.0), (2, 1, 0.4, 0.3), (1, 3, 0.25, 1.0), (3, 2, 0.15, 2.0)]
SIZES = {
    "sine-gordon": {"small": (41, 61), "medium": (101, 201), "large": (401, 401)},
    "wave-2d": {"small": (11, 17), "medium": (21, 33), "large": (41, 65)},
}


def _field(case: str, nt: int, nx: int) -> tuple[ldft.AbstractLagrangian, LatticeField]:
    """The case's kind of field on ``nt`` slices and ``nx`` sites per side (the case's spacings), noise 1e-3 of
    its amplitude, and the case's model learned on it."""
    if case == "sine-gordon":
        half = 0.1 * (nx - 1) / 2
        f = systems.sine_gordon_breather(0.3, xlim=(-half, half), nx=nx, nt=nt, dt=0.05)
        model: ldft.AbstractLagrangian = ldft.PolynomialLagrangian(orders=(2, 12), time_symmetric=True)
    else:
        side = (nx - 1) / 64  # the case's spacing 1/64 (and dt = dx / 2), on a smaller square for fewer sites
        f = systems.wave_membrane(MODES, nx=nx, ny=nx, nt=nt, length_x=side, length_y=side)
        model = ldft.PolynomialLagrangian(orders=(2, 2))
    noisy = f + 1e-3 * float(abs(f).max()) * np.random.default_rng(0).standard_normal(f.shape)
    ldft.learn(model, noisy, progress=False)
    return model, as_lattice_field(noisy, source="field")


def autograd_products(
    model: ldft.AbstractLagrangian, f: LatticeField, psi: torch.Tensor
) -> tuple[torch.Tensor, Callable[[torch.Tensor], torch.Tensor]]:
    """The products by a double backward pass of the action through the model (the path replaced)."""
    x = psi.clone().requires_grad_(True)
    with torch.enable_grad():
        (g,) = torch.autograd.grad(_action(model, x, f.spacing, f.boundary, 0), x, create_graph=True)

    def hv(v: torch.Tensor) -> torch.Tensor:
        (out,) = torch.autograd.grad(g, x, grad_outputs=v, retain_graph=True)
        return out.detach()

    return g.detach(), hv


PATHS = {"sparse": _noise._products, "autograd": autograd_products}


def _timed(fn: Callable[[], Any], repeat: int) -> tuple[Any, float]:
    """``fn``'s result and the shortest of ``repeat`` run times (s)."""
    best, out = math.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


def _product_times(model: ldft.AbstractLagrangian, f: LatticeField, repeat: int) -> dict[str, float]:
    """One Hessian-vector product by each path; the assembly of the sparse Hessian on its own."""
    psi = f.values.detach().clone()
    v = torch.randn(psi.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    _, hv = autograd_products(model, f, psi)
    hv(v)  # the first double backward pass sets up what the others reuse
    _, t_auto = _timed(lambda: hv(v), repeat)
    (_, hess), t_asm = _timed(lambda: action_hessian(model, psi, f.spacing, f.boundary), repeat)
    vn = v.reshape(-1).numpy()
    _, t_one = _timed(lambda: hess @ vn, max(repeat, 20))
    return {"autograd": t_auto, "assembly": t_asm, "sparse": t_one, "nnz": hess.nnz}


def _solve(model: ldft.AbstractLagrangian, f: LatticeField, path: str, strength: float, steps: int) -> torch.Tensor:
    """:func:`latticedft._learn._noise._correct_one` of ``f`` with the products of ``path``."""
    saved = _noise._products
    _noise._products = PATHS[path]  # type: ignore[assignment]
    try:
        return _noise._correct_one(model, f, f.values, strength, steps)
    finally:
        _noise._products = saved


def _compare(model: ldft.AbstractLagrangian, f: LatticeField, what: str, repeat: int, paths: list[str]) -> str:
    """One correction round or one denoised start by each path: times, ratio, difference over the move."""
    sub, strength, steps = (f, _noise.STRENGTH, 1)
    if what == "denoised start":
        sub = f.with_values(f.values[: _noise.DENOISE_SLICES].clone())
        strength, steps = _noise.DENOISE_STRENGTH, 2
    out, times = {}, {}
    for p in paths:
        out[p], times[p] = _timed(lambda p=p: _solve(model, sub, p, strength, steps), repeat)
    line = f"{what}: sparse {times['sparse']:.3g} s"
    if "autograd" in out:
        move = float((out["autograd"] - sub.values).abs().max())
        diff = float((out["sparse"] - out["autograd"]).abs().max())
        line += (
            f", double backward {times['autograd']:.3g} s ({times['autograd'] / times['sparse']:.0f}x); "
            f"max |difference| {diff:.1e} = {diff / move:.1e} of the largest move {move:.1e}"
        )
    return line


def _solvers(model: ldft.AbstractLagrangian, f: LatticeField) -> str:
    """The first Gauss-Newton step of a denoised start on ``f``'s first slices, solved three ways."""
    sub = f.with_values(f.values[: _noise.DENOISE_SLICES].clone())
    g, hess = action_hessian(model, sub.values, sub.spacing, sub.boundary)
    mask = torch.zeros_like(sub.values)
    mask[interior_slices(sub.shape, model.stencil, sub.boundary)] = 1.0
    jac = scipy.sparse.diags(mask.reshape(-1).numpy()) @ hess
    gen = torch.Generator().manual_seed(0)  # the correction's estimate of the mean squared row norm
    probes = [torch.randint(0, 2, (hess.shape[0],), generator=gen, dtype=torch.float64).numpy() * 2 - 1 for _ in "abcd"]
    w = _noise.DENOISE_STRENGTH * float(mask.sum()) / (sum(float(((jac @ z) ** 2).sum()) for z in probes) / 4)
    n = hess.shape[0]
    op = scipy.sparse.linalg.LinearOperator((n, n), matvec=lambda v: w * (jac.T @ (jac @ v)) + v, dtype=np.float64)
    rhs = -w * (jac.T @ (jac @ g.reshape(-1).numpy()))
    diag = w * np.asarray(jac.power(2).sum(axis=0)).ravel() + 1.0
    parts = []
    for name, pre in (("cg", None), ("jacobi cg", scipy.sparse.diags(1.0 / diag))):
        count: list[int] = []
        t0 = time.perf_counter()
        x, _ = scipy.sparse.linalg.cg(
            op, rhs, rtol=1e-10, maxiter=20000, M=pre, callback=lambda _x, c=count: c.append(1)
        )
        res = np.linalg.norm(rhs - op @ x) / np.linalg.norm(rhs)
        parts.append(f"{name} {len(count)} iterations, {time.perf_counter() - t0:.3g} s (residual {res:.1e})")
    if f.ndim == 2:
        t0 = time.perf_counter()
        x = scipy.sparse.linalg.spsolve((w * (jac.T @ jac) + scipy.sparse.identity(n)).tocsc(), rhs)
        res = np.linalg.norm(rhs - op @ x) / np.linalg.norm(rhs)
        parts.append(f"direct {time.perf_counter() - t0:.3g} s (residual {res:.1e})")
    return "; ".join(parts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--sizes", default="small,medium", help="sizes with both paths (small, medium, large)")
    ap.add_argument("--new-only", default="", help="sizes with the sparse path only, besides one product of each")
    ap.add_argument("--repeat", type=int, default=2, help="runs of each measurement; the shortest is printed")
    ap.add_argument("--cases", default="sine-gordon,wave-2d")
    ap.add_argument("--solvers", action="store_true", help="compare the solvers of a denoised start's first step")
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load average {os.getloadavg()[0]:.1f}, 1 thread")
    both = [s for s in args.sizes.split(",") if s]
    alone = [s for s in args.new_only.split(",") if s]
    for case in [c for c in args.cases.split(",") if c]:
        for size in both + alone:
            nt, nx = SIZES[case][size]
            model, f = _field(case, nt, nx)
            if args.solvers:
                print(f"{case} {size} {tuple(f.shape)}, denoised-start window: {_solvers(model, f)}", flush=True)
                continue
            pt = _product_times(model, f, args.repeat)
            print(
                f"{case} {size} {tuple(f.shape)}: one product: double backward {pt['autograd']:.3g} s, "
                f"sparse {pt['sparse']:.2g} s ({pt['autograd'] / pt['sparse']:.0f}x) after an assembly of "
                f"{pt['assembly']:.3g} s ({pt['assembly'] / pt['autograd']:.2f} products; {pt['nnz']} nonzeros)",
                flush=True,
            )
            paths = ["sparse"] if size in alone else ["sparse", "autograd"]
            for what in ("correction round", "denoised start"):
                print(f"  {_compare(model, f, what, args.repeat, paths)}", flush=True)
            print(f"  load average {os.getloadavg()[0]:.1f}", flush=True)


if __name__ == "__main__":
    xr.set_options(keep_attrs=True)
    main()
