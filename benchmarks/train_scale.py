"""Scale of training: seconds and peak memory of the exact solve against the number of fields, in memory
vs streamed (chunks of sites), and streamed from field files read lazily.

``python -m benchmarks.train_scale --workers N`` measures instead the case pipeline: the peak memory of each
process of ``latticedft train CASE`` run by N processes (each holds its share of the training files) against
one process, on a case of files written first (``--quick``: tiny ones).
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import latticedft as ldft

from ._common import Check, Config, Table, in_subprocess
from ._probes import scale_fields

NAME = "train_scale"
TITLE = "Scale: training memory and time against the data size (polynomial exact solve)"


def run(cfg: Config) -> Table:
    table = Table(
        NAME,
        TITLE,
        [
            "data",
            "fields",
            "sites",
            "field data (MiB)",
            "wall time (s)",
            "peak RSS (MiB)",
            "growth (MiB)",
            "growth per field (MiB)",
            "rel_res",
            "coef vs in memory",
        ],
    )
    if cfg.quick:
        nx, nt, orders, sizes, big = 16, 20, [2, 4], (1, 2, 4), 6
    else:
        nx, nt, orders, sizes, big = 128, 200, [4, 8], (1, 10, 30), cfg.scale_fields or 100
    ref: dict[int, np.ndarray] = {}
    results = []
    folder = tempfile.mkdtemp(prefix="latticedft-scale-")
    try:
        runs = [(n, mode) for n in sizes for mode in ("in memory", "streamed")]
        runs += [(big, "streamed"), (big, "streamed, files")]
        for n, mode in runs:
            r = in_subprocess(
                "train_scale",
                cfg.threads,
                inline=cfg.quick,
                n=n,
                nx=nx,
                nt=nt,
                orders=orders,
                chunk_sites=0 if mode == "in memory" else None,
                files=folder if "files" in mode else None,
            )
            coef = np.array(r["coef"])
            if mode == "in memory":
                ref[n] = coef
            diff = float(np.abs(coef - ref[n]).max() / np.abs(ref[n]).max()) if n in ref else None
            growth = r["rss_peak"] - r["rss_before"]
            results.append((n, mode, r, growth, diff))
            table.rows.append(
                [
                    mode,
                    n,
                    r["sites"],
                    r["data_mib"],
                    r["seconds"],
                    r["rss_peak"],
                    growth,
                    growth / n,
                    r["rel_res"],
                    diff,
                ]
            )
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    table.notes += [
        f"Fields: `latticedft.systems.wave_string` on {nx} sites x {nt} slices (Dirichlet ends), two modes each, "
        f"different per field; model `PolynomialLagrangian({tuple(orders)})`; `ldft.learn` with its defaults "
        "(unit-mass gauge, ridge 0): the whole call, diagnostics included.",
        "in memory: `chunk_sites=0` (the residual matrix of every field held and solved at once); streamed: the "
        "default chunks (rows folded into a QR triangle chunk by chunk); files: the same fields written as "
        "netCDF field files first, then their paths passed to `learn` (read a slab at a time).",
        "Each row runs in a fresh Python (with --quick: in the runner itself). Peak RSS: the kernel's high-water "
        "mark `VmHWM`, reset just before the call; growth: that peak minus the resident memory just before it "
        "(the fields themselves, in memory, are already resident; files are not).",
        "coef vs in memory: max |coef - coef_in_memory| / max |coef_in_memory| at the same number of fields. The "
        "135-term basis on these fields is ill-conditioned (the singular values of the constrained residual matrix "
        "fall smoothly to ~1e-9 of the largest, just above the solve's cut-off): coefficients are determined to "
        "~eps x cond only, whatever the path (with one field the in-memory solve itself moves by 8e-10 when the "
        "rows of R are permuted); the learned L_d's residual (rel_res) is the same.",
    ]
    stream_big = [r for n, mode, r, g, d in results if n == big and mode == "streamed"][0]
    growth_big = stream_big["rss_peak"] - stream_big["rss_before"]
    files_big = [g for n, mode, r, g, d in results if n == big and "files" in mode][0]
    table.checks.append(
        Check(
            f"{big} fields of {nx} x {nt}, streamed: < 20 s",
            f"{stream_big['seconds']:.3g} s",
            stream_big["seconds"] < 20,
        )
    )
    table.checks.append(
        Check(
            f"{big} fields streamed: < 500 MB growth (memory and files)",
            f"{growth_big:.0f} MiB / {files_big:.0f} MiB",
            max(growth_big, files_big) * 2**20 < 500e6,
        )
    )
    pairs = [
        (r["rel_res"], [q for m, mode2, q, g2, d2 in results if m == n and mode2 == "in memory"][0]["rel_res"])
        for n, mode, r, g, d in results
        if mode == "streamed" and d is not None
    ]
    worst = max(abs(a - b) / (b + 1e-9) for a, b in pairs)  # a round-off fit (rel_res ~1e-14) is round-off
    table.checks.append(
        Check(
            "streamed rel_res equals the in-memory one to 3 significant digits (every size; round-off fits: 1e-12)",
            f"worst relative difference {worst:.2g}",
            worst < 5e-4,
        )
    )
    return table


def _case(root: Path, n: int, nx: int, nt: int) -> Path:
    """A case of ``n`` wave-string training files (``nx`` sites, ``nt`` slices each) and no serving task,
    trained in chunks of :data:`CASE_CHUNK` sites (so that the data, not one chunk's work, fill the memory)."""
    (root / "data").mkdir(parents=True)
    (root / "case.toml").write_text(
        '[model]\nkind = "polynomial"\norders = [2, 2]\n\n[train]\ndata = ["data/train_*.nc"]\n'
        f"chunk_sites = {CASE_CHUNK}\n"
    )
    for k in range(n):
        (f,) = scale_fields(k + 1, nx, nt, first=k)
        ldft.io.write_field(root / "data" / f"train_{k:03d}.nc", {"psi": f})
    return root


#: ``[train] chunk_sites`` of the case of :func:`case_workers`.
CASE_CHUNK = 2048


def _ranks(case: Path, out: Path, n: int) -> list[dict[str, float]]:
    """``latticedft train CASE`` as the ``n`` ranks ``--workers n`` starts (one process for ``n = 1``): each
    rank's wall time and peak RSS (its ``ru_maxrss``, from ``wait4``)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", MASTER_ADDR="127.0.0.1", MASTER_PORT=str(_free_port()))
    if n > 1:
        env.update(WORLD_SIZE=str(n), LOCAL_WORLD_SIZE=str(n))
    cmd = [sys.executable, "-m", "latticedft", "train", str(case), "--out", str(out), "--overwrite", "-q"]
    t0 = time.perf_counter()
    procs = [subprocess.Popen(cmd, env=dict(env, RANK=str(r), LOCAL_RANK=str(r)) if n > 1 else env) for r in range(n)]
    out_ = []
    for p in procs:
        _, status, usage = os.wait4(p.pid, 0)
        p.returncode = os.waitstatus_to_exitcode(status)
        if p.returncode:
            raise RuntimeError(f"latticedft train failed (exit {p.returncode})")
        out_.append({"seconds": time.perf_counter() - t0, "peak": usage.ru_maxrss / 1024})
    return out_


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def case_workers(cfg: Config, workers: int = 2) -> Table:
    """Peak memory of each process of ``latticedft train CASE --workers N`` against one process."""
    n, nx, nt = (4, 16, 40) if cfg.quick else (8, 256, 3000)
    table = Table(
        NAME + "_workers",
        f"Scale: latticedft train in 1 and {workers} processes, {n} training files of {nx} x {nt}",
        [
            "processes",
            "rank",
            "wall (s)",
            "peak RSS (MiB)",
            "peak RSS, tiny case (MiB)",
            "growth with the data (MiB)",
            "growth / one process's",
            "load (1 min)",
        ],
    )
    folder = Path(tempfile.mkdtemp(prefix="latticedft-share-"))
    try:
        case, tiny = _case(folder / "case", n, nx, nt), _case(folder / "tiny", workers, 16, 40)
        coefs, one = [], 0.0
        for size in (1, workers):
            load = os.getloadavg()[0]
            base = _ranks(tiny, folder / f"tiny{size}", size)
            ranks = _ranks(case, folder / f"out{size}", size)
            coefs.append(ldft.load_model(folder / f"out{size}" / "model.pt").coef.detach().numpy())
            for r, (m, b) in enumerate(zip(ranks, base)):
                growth = m["peak"] - b["peak"]
                one = one or growth
                table.rows.append([size, r, m["seconds"], m["peak"], b["peak"], growth, growth / one, f"{load:.2f}"])
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    diff = float(np.abs(coefs[1] - coefs[0]).max() / np.abs(coefs[0]).max())
    table.notes += [
        f"Training data: {n} files of {nx * nt * 8 / 2**20:.1f} MiB each ({n * nx * nt * 8 / 2**20:.0f} MiB); "
        f"model `polynomial`, orders (2, 2), the exact solve streamed in chunks of {CASE_CHUNK} sites. The "
        f"{workers} ranks are started as `--workers` starts them (the loopback, one thread each); peak RSS is "
        "each process's `ru_maxrss`.",
        f"Growth with the data: the peak minus that of the same command on a tiny case ({workers} files of "
        "16 x 40, one a rank): what the training data add, beyond the interpreter, the package and the fixed "
        "cost of training.",
        f"The model of {workers} processes against one process's: max |coef difference| / max |coef| = {diff:.1e}.",
    ]
    table.checks.append(Check(f"{workers} processes learn one process's model to 1e-10", f"{diff:.1e}", diff < 1e-10))
    return table


if __name__ == "__main__":
    from ._common import run_alone

    if "--workers" in sys.argv:
        at = sys.argv.index("--workers")
        count = int(sys.argv[at + 1])
        del sys.argv[at : at + 2]
        sys.exit(run_alone(lambda cfg: case_workers(cfg, count), __doc__))
    sys.exit(run_alone(run, __doc__))
