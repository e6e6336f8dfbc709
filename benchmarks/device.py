"""Serving and MLP training on a GPU against the CPU, measured side by side in one run.

    python -m benchmarks.device [--device cuda] [--quick] [--threads N]

Workloads (each timed on the CPU and on ``--device``, same data, same model, same seed):

- 2+1D serving, 1024 x 1024 sites per slice (``--quick`` or without CUDA: 64 x 64), and 3+1D serving,
  128^3 sites per slice (``--quick`` or without CUDA: 16^3): a kinetic-plus-potential MLP ``L_d`` (hidden
  [32, 32], tanh), learned by a few L-BFGS iterations on a small field of the same spacing, serves 2 slices
  after the two initial ones by slice-Newton (its gradients and Hessian blocks by autograd on the device);
- MLP training: the same model form, 10 L-BFGS iterations on a 2+1D field of 256 x 256 x 8 sites (without
  CUDA: 32 x 32 x 8), all data in one chunk.

- sine-Gordon, sites per second (``--sg``, the default with CUDA: 3+1D at 128^3 and 256^3, 2+1D at 1024^2;
  ``--quick`` or without CUDA: 16^3): the analytic sine-Gordon ``L_d`` of ``benchmarks.serve_nd`` served by
  slice-Newton on the device (``serve(device=...)``: every slice after the first solved there,
  :mod:`latticedft._serve._ondevice`) against a leapfrog of the same equation in torch on the same device,
  and on the CPU the compiled kernel (its closed form) against the in-place numpy leapfrog. The served rate
  is per slice after the first (two runs of different lengths, their difference), so that the first Newton
  slice (on the host) and the set-up are not in it.

The first table gives seconds on each device, their ratio (CPU / device: above 1 the device is faster) and the
largest difference between the two results (served field, or final training loss relative). Not in the
default benchmark run (it needs a GPU); without CUDA it says so and measures the CPU alone at small sizes.
``uptime`` is printed before and after.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import time
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

NAME = "device"
TITLE = "GPU against CPU: 2+1D and 3+1D serving by an MLP L_d, MLP training"

#: lattice spacing (every axis but time) and time step of every field: one discrete theory serves them all
H, DT = 0.01, 0.005


def standing_wave(n: int, nt: int, ndim: int) -> Any:
    """``prod_k sin(2 pi x_k) cos(w t)`` on ``n^ndim`` sites of spacing :data:`H`, ``nt`` slices of :data:`DT`."""
    from latticedft import systems

    x = H * np.arange(n)
    space = np.ones([n] * ndim)
    for k in range(ndim):
        shape = [1] * ndim
        shape[k] = n
        space = space * (0.5 * np.sin(2 * np.pi * x)).reshape(shape)
    w = 2 * np.pi * math.sqrt(ndim)
    t = DT * np.arange(nt)
    values = np.cos(w * t).reshape(-1, *[1] * ndim) * space[None]
    return systems.make_field(values, ("t", *("z", "y", "x")[3 - ndim :]), spacing=(DT, *[H] * ndim))


def mlp(seed: int = 0) -> Any:
    import latticedft as ldft

    return ldft.MLPLagrangian(hidden=[32, 32], activation="tanh", form="kinetic-potential", seed=seed)


def _sync(device: str) -> None:
    if device.startswith("cuda") and torch.cuda.is_available():
        torch.cuda.synchronize()


def _timed(fn: Callable[[], Any], device: str) -> tuple[float, Any]:
    _sync(device)
    t0 = time.perf_counter()
    out = fn()
    _sync(device)
    return time.perf_counter() - t0, out


def serving(ndim: int, n: int, device: str) -> dict[str, Any]:
    """Seconds to serve 2 slices of ``n^ndim`` sites on the CPU and on ``device``, and the largest difference."""
    import latticedft as ldft

    model = mlp()
    ldft.learn(model, standing_wave(12 if ndim == 3 else 24, 8, ndim), max_iter=5, progress=False)
    field = standing_wave(n, 4, ndim)
    out = []
    for where in ("cpu", device):
        ldft.serve(model, standing_wave(8, 4, ndim), affine=False, progress=False, device=where)  # warm-up
        out.append(_timed(lambda w=where: _served(model, field, w), where))
    (t_cpu, a), (t_dev, b) = out
    return {
        "sites": n**ndim * 2,
        "cpu": t_cpu,
        "device": t_dev,
        "diff": float(np.abs(a.field.values - b.field.values).max()),
        "label": b.device,
        "complete": a.complete and b.complete,
    }


def _served(model: Any, field: Any, device: str) -> Any:
    import latticedft as ldft

    try:
        return ldft.serve(model, field, affine=False, progress=False, device=device)
    except ldft.ServeError as err:  # timed all the same; the table says it stopped
        return err.result


def training(n: int, device: str) -> dict[str, Any]:
    """Seconds of 10 L-BFGS iterations on an ``n x n x 8`` field on the CPU and on ``device``."""
    import latticedft as ldft

    data = standing_wave(n, 8, 2)
    out = []
    for where in ("cpu", device):
        model = mlp()
        ldft.learn(mlp(), standing_wave(8, 8, 2), max_iter=2, progress=False, device=where)  # warm-up
        out.append(
            _timed(
                lambda m=model, w=where: ldft.learn(m, data, max_iter=10, chunk_sites=0, progress=False, device=w),
                where,
            )
        )
    (t_cpu, a), (t_dev, b) = out
    return {
        "sites": n * n * 8,
        "cpu": t_cpu,
        "device": t_dev,
        "diff": abs(a.loss - b.loss) / max(abs(a.loss), 1e-300),
        "label": b.device,
        "complete": True,
    }


def _uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "load average: " + ", ".join(f"{x:.2f}" for x in os.getloadavg())


def _print(title: str, cols: list[str], rows: list[list[Any]]) -> None:
    widths = [max(len(str(x)) for x in col) for col in zip(cols, *rows)]
    print(f"\n== {title}")
    for j, row in enumerate([cols, *rows]):
        print("  ".join(str(c).ljust(w) if k == 0 else str(c).rjust(w) for k, (c, w) in enumerate(zip(row, widths))))
        if j == 0:
            print("  ".join("-" * w for w in widths))


def _mlp_table(big: bool, device: str) -> None:
    rows = []
    for what, run in (
        (f"serve 2+1D {1024 if big else 64}^2 x 2 slices", lambda: serving(2, 1024 if big else 64, device)),
        (f"serve 3+1D {128 if big else 16}^3 x 2 slices", lambda: serving(3, 128 if big else 16, device)),
        (f"train MLP 2+1D {256 if big else 32}^2 x 8, 10 L-BFGS its", lambda: training(256 if big else 32, device)),
    ):
        r = run()
        rows.append(
            [
                what,
                f"{r['sites']:.3g}",
                f"{r['cpu']:.3f}",
                f"{r['device']:.3f}",
                f"{r['cpu'] / r['device']:.2f}",
                f"{r['diff']:.1e}",
                r["label"] + ("" if r["complete"] else " (stopped)"),
            ]
        )
        print(f"  done: {what}", flush=True)
    _print(TITLE, ["workload", "sites", "cpu s", "device s", "cpu / device", "max diff", "device"], rows)


def torch_leapfrog(a: torch.Tensor, b: torch.Tensor, steps: int, dt: float, h: float) -> torch.Tensor:
    """The leapfrog of ``psi_tt = Laplacian psi - sin psi``, periodic, in torch on the tensors' device: the last
    slice. Two work arrays allocated once; the neighbours by ``torch.roll`` (the device's caching allocator
    serves its temporaries)."""
    a, b = a.clone(), b.clone()
    lap, tmp = torch.empty_like(b), torch.empty_like(b)
    c, dt2 = (dt / h) ** 2, dt**2
    for _ in range(steps):
        torch.mul(b, -2 * b.ndim, out=lap)
        for k in range(b.ndim):
            lap += torch.roll(b, 1, k)
            lap += torch.roll(b, -1, k)
        torch.mul(b, 2, out=tmp)
        torch.sub(tmp, a, out=a)
        lap *= c
        a += lap
        torch.sin(b, out=tmp)
        tmp *= dt2
        a -= tmp
        a, b = b, a
    return b


def _sg_rates(ndim: int, n: int, where: str, slices: int, every: int = 1) -> dict[str, Any]:
    """Sites per second of the leapfrog and of serving (per slice after the first Newton slice; every
    ``every``-th slice kept) on ``where``, and the largest difference between the two last slices."""
    import latticedft as ldft

    from .serve_nd import _field, _initial, leapfrog, sine_gordon

    u0, h, dt = _initial(ndim, n)
    model = sine_gordon()
    da = _field(np.stack([u0, u0]), h, dt)
    sites = n**ndim
    if where == "cpu":
        t_lf, last = _timed(lambda: leapfrog(u0, u0, slices - 2, dt, h), where)
        t_lf, last = _timed(lambda: leapfrog(u0, u0, slices - 2, dt, h), where)
    else:
        dev = torch.from_numpy(u0).to(where)
        torch_leapfrog(dev, dev, 2, dt, h)  # warm-up
        t_lf, out = _timed(lambda: torch_leapfrog(dev, dev, slices - 2, dt, h), where)
        last = out.cpu().numpy()
    small, _, _ = _initial(ndim, 8)
    ldft.serve(model, _field(np.stack([small, small]), h, dt), slices=5, progress=False, device=where)  # warm-up
    kw = {"progress": False, "device": where, "every": every}
    short, res = _timed(lambda: ldft.serve(model, da, slices=4, **kw), where)
    full, res = _timed(lambda: ldft.serve(model, da, slices=slices, **kw), where)
    per_slice = (full - short) / (slices - 4)
    return {
        "leapfrog": sites * (slices - 2) / t_lf,
        "served": sites / per_slice if per_slice > 0 else math.nan,
        "first": short,
        "diff": float(np.abs(res.field.values[-1] - last).max()),
        "iterations": res.newton_iterations / (slices - 2),
        "solver": res.slice_solver or res.solver,
        "label": res.device,
    }


def _sg_table(big: bool, device: str, ndim_only: int | None = None) -> None:
    """Sine-Gordon served on the device and on the CPU, sites per second against the leapfrogs."""
    sizes = [(3, 128, 26), (3, 256, 10), (2, 1024, 26)] if big else [(3, 16, 10)]
    sizes = [s for s in sizes if ndim_only in (None, s[0])]
    rows = []
    for ndim, n, slices in sizes:
        for where, every in dict.fromkeys([(device, 1), (device, 8), ("cpu", 1)]):
            if where == "cpu" and n**ndim > 2**21:
                continue  # the host at 256^3 would take minutes: the device rows are the point
            r = _sg_rates(ndim, n, where, slices, every)
            rows.append(
                [
                    f"{ndim}+1D {n}^{ndim} x {slices}",
                    r["label"].split(" (")[0],
                    "all" if every == 1 else f"1 in {every}",
                    r["solver"],
                    f"{r['leapfrog']:.3g}",
                    f"{r['served']:.3g}",
                    f"{r['leapfrog'] / r['served']:.1f}",
                    f"{r['iterations']:.2f}",
                    f"{r['first']:.2f}",
                    f"{r['diff']:.1e}",
                ]
            )
            print(f"  done: sine-Gordon {ndim}+1D {n} on {where}, every {every}", flush=True)
    cols = ["lattice", "device", "kept", "slice solver", "leapfrog sites/s", "served sites/s", "ratio", "its/slice"]
    cols += ["first 2 slices s", "max diff"]
    _print("sine-Gordon (analytic L_d): served by slice-Newton against a leapfrog on the same device", cols, rows)


def _terms(n: int, device: str) -> None:
    """Seconds of one Newton iteration's derivatives of the device slice Newton (gradients, residual part,
    Jacobian diagonal) on a 3+1D ``n^3`` sine-Gordon slice on ``device``: generated from the closed form
    against autograd, best of 5, side by side, with the largest difference of the residual parts."""
    from latticedft._lattice import as_lattice_field
    from latticedft._serve._ondevice import DeviceSlices
    from latticedft._serve._slices import _SliceSystem

    from .serve_nd import _field, _initial, sine_gordon

    u0, h, dt = _initial(3, n)
    model = sine_gordon()
    f = as_lattice_field(_field(np.stack([u0, u0]), h, dt), source="init", min_slices=2)
    model.bind(f.ndim, f.ncomp, f.spacing, f.components)
    slices = DeviceSlices(model, _SliceSystem(model, f), torch.device(device))
    lo = torch.from_numpy(u0.reshape(-1).copy()).to(device)
    hi = lo + 0.01
    rows, parts = [], []
    for label in ("closed form", "autograd"):
        if label == "autograd":
            slices.closed = None
        slices._newton_terms(lo, hi)  # warm-up (the closed form generated)
        best = min(_timed(lambda: slices._newton_terms(lo, hi), device)[0] for _ in range(5))
        parts.append(slices._newton_terms(lo, hi)[1])
        rows.append([label, f"{n}^3", f"{best * 1e3:.2f}"])
    diff = float((parts[0] - parts[1]).abs().max())
    _print(
        f"one iteration's derivatives on {device} (residual parts differ by {diff:.1e})",
        ["derivatives", "slice", "ms"],
        rows,
    )


def _profile(n: int, device: str) -> None:
    """The operations of serving 3+1D ``n^3`` sine-Gordon for 8 slices on ``device``, by device time (CPU
    time on the CPU), as torch's profiler counts them."""
    from torch.profiler import ProfilerActivity, profile

    import latticedft as ldft

    from .serve_nd import _field, _initial, sine_gordon

    u0, h, dt = _initial(3, n)
    da, model = _field(np.stack([u0, u0]), h, dt), sine_gordon()
    ldft.serve(model, da, slices=4, progress=False, device=device)  # warm-up
    gpu = device.startswith("cuda")
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if gpu else [])
    with profile(activities=activities) as prof:
        ldft.serve(model, da, slices=10, progress=False, device=device)
        _sync(device)
    key = "self_cuda_time_total" if gpu else "self_cpu_time_total"
    print(prof.key_averages().table(sort_by=key, row_limit=25, max_name_column_width=48))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.device", description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda", help="the device measured against the CPU (default cuda)")
    p.add_argument("--quick", action="store_true", help="small sizes only (seconds)")
    p.add_argument("--threads", type=int, default=1, help="torch threads of the CPU runs (default 1)")
    p.add_argument("--only", choices=("mlp", "sg"), help="one table: the MLP workloads or sine-Gordon's sites/s")
    p.add_argument(
        "--terms",
        type=int,
        metavar="N",
        help="instead: one Newton iteration's derivatives at N^3, "
        "generated from the closed form against autograd, on --device",
    )
    p.add_argument("--ndim", type=int, choices=(2, 3), help="sine-Gordon: this dimension's rows only")
    p.add_argument("--profile", type=int, metavar="N", help="instead: torch's profile of serving 3+1D N^3 sine-Gordon")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    from latticedft._device import DeviceWarning, resolve_device

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DeviceWarning)
        resolved = resolve_device(args.device)
    for w in caught:
        print(f"note: {w.message}")
    gpu = resolved.type == "cuda"
    if not gpu:
        print("CUDA is unavailable here: the CPU is measured against itself, at small sizes; no GPU figures")
    big = gpu and not args.quick
    device = str(resolved)
    print(f"cores: {os.cpu_count()}; torch threads: {args.threads}; before: {_uptime()}", flush=True)
    if args.profile:
        _profile(args.profile, device)
        return 0
    if args.terms:
        _terms(args.terms, device)
        return 0
    if args.only != "sg":
        _mlp_table(big, device)
    if args.only != "mlp":
        _sg_table(big, device, args.ndim)
    print(f"after: {_uptime()}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
