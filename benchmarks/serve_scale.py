"""Memory of serving with an output cadence: peak RSS flat in the number of slices served.

    python -m benchmarks.serve_scale [--quick]

The wave ``L_d`` (exactly quadratic: the affine recurrence serves it) on periodic 2+1D and 3+1D lattices,
served from two slices with ``every = 100`` (every 100th slice and the last kept), each size in a fresh
Python: its peak resident memory (``VmHWM`` reset before serving, ``benchmarks._common.PeakRSS``) and wall
time. ``every = 1`` (the whole field held) at the smallest size, in the same run, for the ratio. About 9
minutes on a loaded core; ``--point N DIMS SLICES EVERY`` measures one size (e.g. ``--point 128 3 12 10``);
``--quick``: tiny lattices, in this process (seconds). Also run by ``python -m benchmarks --only serve_scale``.
``--case N SLICES EVERY`` runs a case (a Dirichlet membrane whose ``from``/reference and baseline files hold
``SLICES`` slices of ``N^2`` sites) twice, its files read whole and left on disk, side by side.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from ._common import Check, Config, PeakRSS, Table, markdown

NAME = "serve_scale"
TITLE = "Serving with an output cadence: peak memory against slices served (wave L_d, periodic, every = 100)"

#: (spatial size n, spatial dims, slices, every): n^d sites per slice
FULL = [
    (256, 2, 500, 100),
    (256, 2, 1000, 100),
    (256, 2, 2000, 100),
    (256, 2, 500, 1),
    (512, 2, 400, 100),
    (64, 3, 200, 100),
]
QUICK = [(24, 2, 30, 10), (24, 2, 60, 10), (24, 2, 120, 10), (24, 2, 30, 1), (8, 3, 20, 10)]


def probe(n: int, dims: int, slices: int, every: int) -> dict[str, Any]:
    """Serve one periodic wave field of ``n^dims`` sites for ``slices`` slices; its peak RSS and wall time."""
    import latticedft as ldft
    from latticedft import systems

    h = 1.0 / n
    x = h * np.arange(n)
    grids = np.meshgrid(*([x] * dims), indexing="ij")
    u0 = 0.5 * np.prod([np.sin(2 * np.pi * (k + 1) * g) for k, g in enumerate(grids)], axis=0)
    names = ("z", "y", "x")[3 - dims :]
    attrs = {d: {"periodic": "true", "period": 1.0} for d in names}
    two = systems.make_field(np.stack([u0, u0]), ("t", *names), spacing=(0.5 * h, *([h] * dims)), coord_attrs=attrs)
    model = ldft.lagrangians.wave()
    ldft.serve(model, two.isel({d: slice(0, 8) for d in names}), slices=4, every=2, progress=False)  # warm-up
    mem = PeakRSS()
    t0 = time.perf_counter()
    out = ldft.serve(model, two, slices=slices, every=every, progress=False)
    return {
        "seconds": time.perf_counter() - t0,
        "rss_before": mem.before,
        "rss_peak": mem.peak(),
        "kept": int(out.field.sizes["t"]),
        "slice_mib": u0.nbytes / 2**20,
        "solver": out.solver,
    }


def case_probe(n: int, slices: int, every: int, whole: bool) -> dict[str, Any]:
    """Run a case (a Dirichlet membrane of ``n^2`` sites, ``slices`` slices in ``from``, which is also the
    reference, and a baseline of the same size; ``every``) with ``latticedft run``: its peak RSS and wall time.
    ``whole``: its files read whole, as before a task with ``every > 1`` left them on disk."""
    import shutil
    import tempfile
    import textwrap

    import latticedft._run._data as pipeline
    from latticedft import systems
    from latticedft.cli import main
    from latticedft.io.fields import read_field, write_field

    root = Path(tempfile.mkdtemp(prefix="serve_scale_case_"))
    try:
        (root / "data").mkdir()
        train = systems.wave_membrane([(1, 1, 1.0), (2, 1, 0.4)], nx=n, ny=n, nt=40)
        write_field(root / "data" / "train.nc", {"psi": train})
        test = systems.wave_membrane([(1, 2, 0.6), (3, 1, 0.3)], nx=n, ny=n, nt=slices)
        write_field(root / "data" / "test.nc", {"psi": test})
        field_mib = test.nbytes / 2**20
        del train, test
        shutil.copy(root / "data" / "test.nc", root / "data" / "base.nc")
        text = f"""
            [model]
            kind = "polynomial"
            orders = [2, 2]
            [train]
            data = ["data/train.nc"]
            [[serve]]
            name = "test"
            from = "data/test.nc"
            boundary = "dirichlet"
            baseline = "data/base.nc"
            every = {every}
            [run]
            threads = 1
            [export]
            formats = []
        """
        (root / "case.toml").write_text(textwrap.dedent(text))
        if whole:
            pipeline.read_field = lambda *a, lazy=False, **kw: read_field(*a, **kw)  # type: ignore[assignment]
        _trim()
        mem = PeakRSS()
        t0 = time.perf_counter()
        code = main(["run", str(root), "-q"])
        if code != 0:
            raise RuntimeError(f"latticedft run exited {code}")
        return {
            "seconds": time.perf_counter() - t0,
            "rss_before": mem.before,
            "rss_peak": mem.peak(),
            "field_mib": field_mib,
        }
    finally:
        shutil.rmtree(root, ignore_errors=True)


def _trim() -> None:
    from latticedft._serve._stream import _trim as trim

    trim()


def _fresh(kwargs: dict[str, Any], threads: int, probe: str = "probe") -> dict[str, Any]:
    root = Path(__file__).resolve().parent.parent
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    code = (
        f"import json, sys, torch; from benchmarks.serve_scale import {probe} as probe; "
        f"torch.set_num_threads({threads}); print('@@' + json.dumps(probe(**json.loads(sys.argv[1]))))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, json.dumps(kwargs)], cwd=root, env=env, capture_output=True, text=True, check=False
    )
    for line in proc.stdout.splitlines():
        if line.startswith("@@"):
            return json.loads(line[2:])
    raise RuntimeError(f"serve_scale probe failed (exit {proc.returncode}): {proc.stderr.strip()[-2000:]}")


def run(cfg: Config) -> Table:
    table = Table(
        NAME,
        TITLE,
        ["lattice", "slices", "every", "kept", "slice (MiB)", "wall (s)", "peak RSS (MiB)", "growth (MiB)"],
    )
    growth: dict[tuple[int, int, int, int], float] = {}
    for n, dims, slices, every in QUICK if cfg.quick else FULL:
        kw = {"n": n, "dims": dims, "slices": slices, "every": every}
        r = probe(**kw) if cfg.quick else _fresh(kw, cfg.threads)
        g = r["rss_peak"] - r["rss_before"]
        growth[(n, dims, slices, every)] = g
        table.rows.append(
            [f"{n}^{dims} ({dims}+1D)", slices, every, r["kept"], r["slice_mib"], r["seconds"], r["rss_peak"], g]
        )
    sizes = QUICK if cfg.quick else FULL
    flat = [growth[s] for s in sizes[:3]]
    whole = growth[sizes[3]]
    table.notes += [
        "Each row in a fresh Python (with --quick: in the runner itself, so its memory figures are the "
        "runner's). Peak RSS: VmHWM reset just before serving; growth: that peak minus the resident memory "
        "just before serving (the interpreter and torch are ~300-400 MiB).",
        "Kept slices: 0, every, 2 every, ... and the last; the served field holds only those, the window of "
        "slices the stencil needs is refilled chunk by chunk (about 32 MiB of slices).",
        f"Growth of the first three rows (slices x2, x4): {', '.join(f'{v:.0f}' for v in flat)} MiB; every = 1 "
        f"at the first size: {whole:.0f} MiB ({whole / max(flat[0], 1e-9):.1f}x the cadenced run's).",
    ]
    if not cfg.quick:
        spread = max(flat) - min(flat)
        kept_mib = 2000 // 100 * 0.5  # the kept slices of the largest run (256^2 doubles: 0.5 MiB each)
        table.checks.append(
            Check(
                "peak memory flat in the slices served (growth from 500 to 2000 slices below 64 MiB)",
                f"{spread:.0f} MiB (kept slices: {kept_mib:.0f} MiB)",
                spread < 64,
            )
        )
    return table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.serve_scale", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="tiny lattices in this process (seconds)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument(
        "--point",
        nargs=4,
        type=int,
        metavar=("N", "DIMS", "SLICES", "EVERY"),
        help="measure one size only (N^DIMS sites, in a fresh Python), e.g. --point 128 3 12 10",
    )
    parser.add_argument(
        "--case",
        nargs=3,
        type=int,
        metavar=("N", "SLICES", "EVERY"),
        help="a case run (Dirichlet membrane N^2, reference and baseline of SLICES slices) with its files read "
        "whole and left on disk, each in a fresh Python, e.g. --case 128 1500 100",
    )
    args = parser.parse_args(argv)
    if args.case:
        n, slices, every = args.case
        rows = {}
        for whole in (True, False):
            kw = {"n": n, "slices": slices, "every": every, "whole": whole}
            rows["read whole" if whole else "block by block"] = _fresh(kw, args.threads, "case_probe")
        print(f"case run: {n}^2 Dirichlet membrane, {slices} slices, every = {every} (peak RSS, MiB)")
        for name, r in rows.items():
            print(
                f"  files {name:14s} field {r['field_mib']:.0f} MiB  peak {r['rss_peak']:.0f}  "
                f"growth {r['rss_peak'] - r['rss_before']:.0f}  wall {r['seconds']:.0f} s"
            )
        a, b = (r["rss_peak"] - r["rss_before"] for r in rows.values())
        print(f"  growth ratio (whole / block by block): {a / max(b, 1e-9):.2f}")
        return 0
    if args.point:
        n, dims, slices, every = args.point
        print(json.dumps(_fresh({"n": n, "dims": dims, "slices": slices, "every": every}, args.threads)))
        return 0
    print(markdown(run(Config(quick=args.quick, threads=args.threads))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
