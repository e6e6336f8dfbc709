"""Serving split into slabs over processes: the field, peak memory per process and time against one process.

    python -m benchmarks.serve_dist [--quick] [--point N SLICES EVERY] [--model kg|sg] [--full] [--grid]

A 3+1D periodic Klein-Gordon field (the discrete ``L_d`` of ``latticedft.lagrangians.klein_gordon``: affine
and explicit, the split recurrence of ``latticedft._serve._decomp.serve_slabs``), or with ``--model sg`` a
sine-Gordon one (the same kinetic and gradient terms, ``1 - cos(u)`` for the potential: split site-wise
slice-Newton), of ``N^3`` sites, served from two slices for ``SLICES`` slices with ``every = EVERY``: once by
``latticedft.serve`` in one process, then by ``serve_slabs`` in 2 and in 4 processes (gloo on the loopback,
each process a fresh Python). Per run: the largest difference from the one-process field (relative), the
peak resident memory of each process (``VmHWM`` reset before serving) and its growth over the memory before
serving, and the wall time, with the load average (``os.getloadavg()``) before and after each run. Default
``N = 48, SLICES = 60, EVERY = 20`` (Klein-Gordon); ``--full`` is the target size: sine-Gordon at
``128^3`` sites, 200 slices, ``every = 50`` (``--model sg --point 128 200 50``: about 2 GiB and, on one
core, tens of minutes a run); ``--quick``: 12^3 sites, 12 slices, 1 and 2 processes. ``--grid`` adds a
row of 4 processes in pencils, a ``2 x 2`` grid over ``(z, y)``, against the row of 4 slabs along ``z``.
Also ``python -m benchmarks --only serve-dist``.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from ._common import Check, Config, PeakRSS, Table, run_alone

NAME = "serve-dist"
TITLE = "Serving split into slabs: 3+1D periodic Klein-Gordon, 1 / 2 / 4 processes (gloo, one thread each)"

FULL = (48, 60, 20)
QUICK = (12, 12, 4)
#: the target size: sine-Gordon at 128^3 sites, 200 slices, every = 50
TARGET = (128, 200, 50)
PROCESSES = (1, 2, 4)


def _sine_gordon(cells: Any, h: tuple[float, ...]) -> Any:
    """Sine-Gordon on the first-order stencil: ``(d_t u)^2 / 2 - |grad u|^2 / 2 - (1 - cos u)``."""
    import torch

    u0 = cells[..., 0, 0]
    kin = 0.5 * ((cells[..., 1, 0] - u0) / h[0]) ** 2
    grad = sum(0.5 * ((cells[..., a + 1, 0] - u0) / h[a]) ** 2 for a in range(1, len(h)))
    return kin - grad - (1 - torch.cos(u0))


def _model(name: str) -> Any:
    import latticedft as ldft
    from latticedft._models import AnalyticLagrangian

    return ldft.lagrangians.klein_gordon(1.0) if name == "kg" else AnalyticLagrangian(_sine_gordon, name="sG")


def _init(n: int) -> Any:
    """The first two slices of a periodic field of ``n^3`` sites (a standing wave)."""
    import xarray as xr

    h = 1.0 / n
    x = h * np.arange(n)
    g = np.meshgrid(x, x, x, indexing="ij")
    u0 = 0.5 * np.sin(2 * np.pi * g[0]) * np.sin(4 * np.pi * g[1]) * np.cos(2 * np.pi * g[2])
    coords = {"t": [0.0, 0.5 * h], "z": x, "y": x, "x": x}
    da = xr.DataArray(np.stack([u0, u0]), dims=("t", "z", "y", "x"), coords=coords, name="psi")
    for d in ("z", "y", "x"):
        da[d].attrs.update(periodic="true", period=1.0)
    return da


def rank_probe(
    n: int, slices: int, every: int, out: str, model: str = "kg", grid: list[int] | None = None
) -> dict[str, Any]:
    """One process of a run (rank 0 saves the field to ``out``): its peak memory and wall time."""
    import torch

    import latticedft as ldft
    from latticedft._learn import _dist
    from latticedft._serve._decomp import serve_slabs

    torch.set_num_threads(1)
    parallel = _dist.init_from_env()
    init = _init(n)
    lagrangian = _model(model)
    mem = PeakRSS()
    t0 = time.perf_counter()
    if parallel:
        shape = None if grid is None else (grid[0], grid[1])
        report: dict[str, Any] = {}
        field = serve_slabs(lagrangian, init, slices, boundary="periodic", every=every, grid=shape, report=report)
    else:
        field = ldft.serve(lagrangian, init, slices=slices, boundary="periodic", every=every, progress=False).field
    seconds = time.perf_counter() - t0
    if field is not None:
        np.save(out, np.asarray(field.values))
    if parallel:
        import torch.distributed as dist

        dist.barrier()
        dist.destroy_process_group()
    gather = report.get("gather_seconds") if parallel else None
    return {"seconds": seconds, "rss_before": mem.before, "rss_peak": mem.peak(), "gather": gather}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _launch(
    processes: int, n: int, slices: int, every: int, out: Path, model: str = "kg", grid: list[int] | None = None
) -> list[dict[str, Any]]:
    """``processes`` fresh Pythons forming one group (``grid``: pencils); each one's answer, in rank order."""
    root = Path(__file__).resolve().parent.parent
    code = (
        "import json, sys; from benchmarks.serve_dist import rank_probe; "
        "print('@@' + json.dumps(rank_probe(**json.loads(sys.argv[1]))))"
    )
    kw = json.dumps({"n": n, "slices": slices, "every": every, "out": str(out), "model": model, "grid": grid})
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONPATH=str(root))
    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "LOCAL_WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(k, None)
    if processes > 1:
        env.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(_free_port()), WORLD_SIZE=str(processes))
        env["LOCAL_WORLD_SIZE"] = str(processes)
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", code, kw],
            cwd=root,
            env=dict(env, RANK=str(r), LOCAL_RANK=str(r)) if processes > 1 else env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for r in range(processes)
    ]
    answers = []
    for p in procs:
        stdout, stderr = p.communicate(timeout=3600)
        found = [ln[2:] for ln in stdout.splitlines() if ln.startswith("@@")]
        if p.returncode != 0 or not found:
            raise RuntimeError(f"serve_dist process failed (exit {p.returncode}): {stderr.strip()[-2000:]}")
        answers.append(json.loads(found[0]))
    return answers


def run(cfg: Config, point: tuple[int, int, int] | None = None, model: str = "kg", pencils: bool = False) -> Table:
    n, slices, every = point or (QUICK if cfg.quick else FULL)
    title = TITLE if model == "kg" else TITLE.replace("Klein-Gordon", "sine-Gordon (site-wise slice-Newton)")
    table = Table(
        NAME,
        title,
        [
            "processes",
            "lattice",
            "slices",
            "max |diff| (rel.)",
            "wall (s)",
            "gather (s)",
            "peak RSS (MiB)",
            "growth (MiB)",
            "growth by rank (MiB)",
            "load",
        ],
    )
    growth: dict[int, float] = {}
    diffs: dict[int, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        one = None
        runs: list[tuple[int, list[int] | None]] = [(p, None) for p in PROCESSES]
        runs = runs[:2] if cfg.quick and point is None else runs + ([(4, [2, 2])] if pencils else [])
        for p, grid in runs:
            out = Path(tmp) / f"field_{p}_{grid}.npy"
            load = os.getloadavg()[0]
            answers = _launch(p, n, slices, every, out, model, grid)
            field = np.load(out)
            one = field if one is None else one
            diff = float(np.abs(field - one).max() / max(np.abs(one).max(), 1e-300))
            grown = max(a["rss_peak"] - a["rss_before"] for a in answers)
            if grid is None:
                diffs[p], growth[p] = diff, grown
            peak = max(a["rss_peak"] for a in answers)
            wall = max(a["seconds"] for a in answers)
            label = p if grid is None else f"{p} (pencils {grid[0]} x {grid[1]})"
            gather = "-" if answers[0]["gather"] is None else f"{answers[0]['gather']:.2f}"
            ranks = " ".join(f"{a['rss_peak'] - a['rss_before']:.0f}" for a in answers)
            table.rows.append(
                [
                    label,
                    f"{n}^3",
                    slices,
                    diff,
                    wall,
                    gather,
                    peak,
                    grown,
                    ranks,
                    f"{load:.1f}-{os.getloadavg()[0]:.1f}",
                ]
            )
    table.notes += [
        "1 process: latticedft.serve (the one-process path); 2 and 4: latticedft._serve._decomp.serve_slabs, "
        "slabs along z, one halo plane each side exchanged after every slice, kept slices gathered to rank 0; "
        "pencils (--grid): blocks of a 2 x 2 grid over (z, y), their halo exchanged along z, then along y.",
        "Peak RSS and growth: the largest over the processes (VmHWM reset before serving; the interpreter and "
        "torch, ~300-400 MiB, are in the peak, not in the growth). Wall: the slowest process. On a machine "
        "with fewer free cores than processes the time ratio measures the load, not the scaling.",
        "Load: the 1-minute load average (os.getloadavg) before and after the run.",
        "Gather: rank 0's wall time gathering the kept slices (each process's block of one kept slice at a time, "
        "point to point) into the field it returns, within the run's wall time.",
    ]
    if 2 in diffs:
        for p in (2, 4) if 4 in growth else (2,):
            table.notes.append(
                f"time ratio {p} processes / 1: {table.rows[PROCESSES.index(p)][4] / table.rows[0][4]:.2f}"
            )
    for p, target in ((2, 0.6), (4, 0.35)) if 4 in growth else ((2, 0.6),):
        table.checks.append(
            Check(f"{p} processes: the one-process field to 1e-12", f"{diffs[p]:.1e}", diffs[p] <= 1e-12)
        )
        ratio = growth[p] / max(growth[1], 1e-9)
        table.checks.append(
            Check(
                f"{p} processes: memory growth per process at most {target}x one process's",
                f"{ratio:.2f}x",
                ratio <= target,
            )
        )
    return table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.serve_dist", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="12^3 sites, 12 slices")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--point", nargs=3, type=int, metavar=("N", "SLICES", "EVERY"), help="e.g. 128 200 50")
    parser.add_argument("--model", choices=("kg", "sg"), default="kg", help="Klein-Gordon or sine-Gordon")
    parser.add_argument("--full", action="store_true", help="the target size: sine-Gordon, 128^3, 200, every 50")
    parser.add_argument("--grid", action="store_true", help="a row of 4 processes in 2 x 2 pencils")
    args = parser.parse_args(argv)
    point, model = (TARGET, "sg") if args.full else (args.point and tuple(args.point), args.model)
    if point or model != "kg" or args.grid:
        return run_alone(lambda cfg: run(cfg, point, model, args.grid), __doc__, ["--threads", str(args.threads)])
    return run_alone(run, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
