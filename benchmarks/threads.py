"""Torch threads under load: each solver with 1 and 2 threads, on an idle machine and beside a busy process.

    python -m benchmarks.threads [--quick] [--repeat N] [--only NAMES] [--policy]

For every thread count and load (``idle``: nothing added; ``busy``: one extra ``python -c "while True: pass"``
process, started before and killed after), a fresh Python (``OMP_NUM_THREADS`` and ``torch.set_num_threads``
set before any work) times each workload below: the best of three batches of calls (a batch lasts at least
0.3 s), after a warm-up call. The table gives the
seconds and the ratio of 2 threads to 1 in the same run; ``uptime`` is printed before and after. This is how
the default of ``[run] threads`` was chosen (docs/performance.md, *Threads under load*).

Workloads (small and large lattices): the affine recurrence, slice-Newton and the site-by-site sweep of
1+1D serving (the wave ``L_d``), a batch of 1D Kepler orbits, the exact polynomial solve, L-BFGS training
of a neural ``L_d`` (double backward), and the ``cases/wave`` case's own serving task.

``--policy`` compares the two thread policies instead, one thread each, idle and busy: ``torch`` bounds only
torch's pool (``torch.set_num_threads(1)``, no ``OMP_NUM_THREADS``: numpy's BLAS keeps a thread per core, as
before ``[run] threads`` went through ``latticedft.limit_threads``) and ``all`` bounds torch and every
BLAS/OpenMP pool (``latticedft.limit_threads(1)``). It gives wall and CPU seconds (``time.process_time``,
all the process's threads) per call, and the ratios torch/all.
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

ROOT = Path(__file__).resolve().parent.parent

#: name -> (what, small?) in table order
WORKLOADS = {
    "affine-small": "1+1D affine recurrence (wave L_d), 64 x 200",
    "affine-large": "1+1D affine recurrence (wave L_d), 1024 x 400",
    "newton-small": "1+1D slice-Newton (wave L_d, affine=False), 64 x 100",
    "newton-large": "1+1D slice-Newton (wave L_d, affine=False), 256 x 100",
    "sweep-small": "1+1D site-by-site sweep (wave L_d), 16 x 12",
    "sweep-large": "1+1D site-by-site sweep (wave L_d), 64 x 6",
    "batch1d-small": "1D Kepler-Verlet, 1 orbit x 100",
    "batch1d-large": "1D Kepler-Verlet, 32 orbits x 100",
    "exact-small": "exact solve, polynomial (4, 8), 3 oscillator fields",
    "exact-large": "exact solve, polynomial (2, 2), membrane 33 x 33 x 41",
    "exact-dense": "exact solve, polynomial (2, 12) time-symmetric, membrane 33 x 33 x 41",
    "lbfgs-small": "L-BFGS, kinetic-potential MLP [10, 10], 4 KG fields, 20 its",
    "lbfgs-large": "L-BFGS, kinetic-potential MLP [32, 32], 16 KG fields, 20 its",
    "wave-case": "cases/wave: learn (polynomial (2, 2)) and serve test (41 x 401)",
}
QUICK = ("affine-small", "newton-small", "batch1d-small", "exact-small", "lbfgs-small")


def _workload(name: str) -> Any:
    """A function that does the work of ``name`` (inputs built beforehand)."""
    import numpy as np

    import latticedft as ldft
    from latticedft import lagrangians, systems
    from latticedft.io import read_field

    wave = lagrangians.wave()
    if name.startswith(("affine", "newton", "sweep")):
        nx, nt = {
            "affine-small": (64, 200),
            "affine-large": (1024, 400),
            "newton-small": (64, 100),
            "newton-large": (256, 100),
            "sweep-small": (16, 12),
            "sweep-large": (64, 6),
        }[name]
        field = systems.wave_string([(1, 1.0), (3, 0.3, 0.5)], nx=nx, nt=nt)
        mode = "sweep" if name.startswith("sweep") else "newton"
        return lambda: ldft.serve(wave, field, mode=mode, affine=name.startswith("affine"), progress=False)
    if name.startswith("batch1d"):
        k = 1 if name.endswith("small") else 32
        dt = 0.05
        inits = [
            systems.make_field([[1.0, 0.0], [1.0, v * dt]], ["t"], spacing=dt, components=["x", "y"])
            for v in np.linspace(0.9, 1.1, k)
        ]
        return lambda: ldft.serve(lagrangians.kepler(), inits, slices=100, progress=False)
    if name == "exact-small":
        data = [systems.oscillator_sin(a, n=51) for a in (0.4, 0.8, 1.2)]
        return lambda: ldft.learn(ldft.PolynomialLagrangian(orders=(4, 8)), data)
    if name in ("exact-large", "exact-dense"):
        data = systems.wave_membrane([(1, 1, 1.0), (2, 1, 0.4)], nx=33, ny=33, nt=41)
        dense = name == "exact-dense"
        orders = (2, 12) if dense else (2, 2)
        return lambda: ldft.learn(ldft.PolynomialLagrangian(orders=orders, time_symmetric=dense), data)
    if name.startswith("lbfgs"):
        small = name.endswith("small")
        data = systems.klein_gordon_training_set(n=4 if small else 16, steps=20, seed=0)
        hidden = [10, 10] if small else [32, 32]

        def train() -> Any:
            model = ldft.MLPLagrangian(hidden=hidden, activation="tanh", form="kinetic-potential", seed=0)
            return ldft.learn(model, data, boundary="periodic", max_iter=20)

        return train
    if name == "wave-case":
        case = ROOT / "cases" / "wave" / "data"
        train, test = read_field(case / "train.nc"), read_field(case / "test.nc")

        def run_case() -> Any:
            model = ldft.PolynomialLagrangian(orders=(2, 2))
            ldft.learn(model, train)
            return ldft.serve(model, test, boundary="dirichlet", progress=False)

        return run_case
    raise KeyError(name)


#: A timed batch of calls lasts at least this long (short workloads are called several times per batch).
MIN_BATCH_S = 0.3


def _seconds_per_call(fn: Any) -> float:
    """Seconds of one call of ``fn``: the best of three batches of calls, after a warm-up call (first-call
    costs such as allocations are not the threads' effect)."""
    t0 = time.perf_counter()
    fn()
    reps = max(1, int(MIN_BATCH_S / max(time.perf_counter() - t0, 1e-6)))
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(reps):
            fn()
        best = min(best, (time.perf_counter() - t0) / reps)
    return best


def _wall_and_cpu_per_call(fn: Any) -> list[float]:
    """Wall and CPU seconds of one call of ``fn``: the batch of least wall time of three, after a warm-up."""
    t0 = time.perf_counter()
    fn()
    reps = max(1, int(MIN_BATCH_S / max(time.perf_counter() - t0, 1e-6)))
    best = [float("inf"), float("inf")]
    for _ in range(3):
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in range(reps):
            fn()
        wall, cpu = (time.perf_counter() - t0) / reps, (time.process_time() - c0) / reps
        best = min(best, [wall, cpu])
    return best


def policy_child(policy: str, names: list[str]) -> dict[str, list[float]]:
    """In the measuring process: wall and CPU seconds per call of each workload under ``policy``."""
    import torch

    import latticedft as ldft

    if policy == "all":
        ldft.limit_threads(1)
    else:
        torch.set_num_threads(1)
    return {name: _wall_and_cpu_per_call(_workload(name)) for name in names}


def _measure_policy(policy: str, busy: bool, names: list[str]) -> dict[str, list[float]]:
    drop = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
    env = {k: v for k, v in os.environ.items() if k not in drop} | {"PYTHONPATH": str(ROOT)}
    return _in_a_child(["--policy-child", policy, ",".join(names)], env, busy)


def _in_a_child(args: list[str], env: dict[str, str], busy: bool) -> Any:
    """``python -m benchmarks.threads ARGS`` in a fresh process (beside one busy process when ``busy``); the
    JSON of its last line."""
    load = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if busy else None
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "benchmarks.threads", *args],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
            check=True,
        )
    finally:
        if load is not None:
            load.kill()
            load.wait()
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _print_table(cols: list[str], rows: list[list[str]]) -> None:
    widths = [max(len(str(x)) for x in col) for col in zip(cols, *rows)]
    for j, row in enumerate([cols, *rows]):
        print("  ".join(str(c).ljust(w) if k == 0 else str(c).rjust(w) for k, (c, w) in enumerate(zip(row, widths))))
        if j == 0:
            print("  ".join("-" * w for w in widths))


def policy_table(names: list[str]) -> None:
    """Wall and CPU seconds per call with torch's threads bounded alone and with every pool bounded."""
    t0 = time.perf_counter()
    got = {(pol, busy): _measure_policy(pol, busy, names) for busy in (False, True) for pol in ("torch", "all")}
    for busy in (False, True):
        load = "busy" if busy else "idle"
        cols = ["workload", "torch wall", "all wall", "wall torch/all", "torch CPU", "all CPU", "CPU torch/all"]
        rows = []
        for n in names:
            (tw, tc), (aw, ac) = got["torch", busy][n], got["all", busy][n]
            rows.append(
                [WORKLOADS[n], f"{tw:.3f}", f"{aw:.3f}", f"{tw / aw:.2f}", f"{tc:.3f}", f"{ac:.3f}", f"{tc / ac:.2f}"]
            )
        print(f"\n== thread policy, {load}: seconds per call, one thread ({time.perf_counter() - t0:.0f} s so far)")
        _print_table(cols, rows)


def child(threads: int, names: list[str]) -> dict[str, float]:
    """In the measuring process: seconds per call of each workload."""
    import torch

    torch.set_num_threads(threads)
    return {name: _seconds_per_call(_workload(name)) for name in names}


def _measure(threads: int, busy: bool, names: list[str]) -> dict[str, float]:
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads), PYTHONPATH=str(ROOT))
    return _in_a_child(["--child", str(threads), ",".join(names)], env, busy)


def _uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "load average: " + ", ".join(f"{x:.2f}" for x in os.getloadavg())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.threads", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help=f"only the small workloads {', '.join(QUICK)}")
    p.add_argument("--repeat", type=int, default=1, help="runs of the whole table (default 1)")
    p.add_argument("--only", default="", help="comma-separated workloads (default: all)")
    p.add_argument("--policy", action="store_true", help="torch's threads bounded alone vs every pool bounded")
    p.add_argument("--child", nargs=2, metavar=("THREADS", "NAMES"), help=argparse.SUPPRESS)
    p.add_argument("--policy-child", nargs=2, metavar=("POLICY", "NAMES"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        print(json.dumps(child(int(args.child[0]), args.child[1].split(","))))
        return 0
    if args.policy_child:
        print(json.dumps(policy_child(args.policy_child[0], args.policy_child[1].split(","))))
        return 0
    names = [n for n in args.only.split(",") if n] or (list(QUICK) if args.quick else list(WORKLOADS))
    unknown = [n for n in names if n not in WORKLOADS]
    if unknown:
        p.error(f"unknown workloads {unknown}; choose from {', '.join(WORKLOADS)}")
    print(f"cores: {os.cpu_count()}; before: {_uptime()}", flush=True)
    if args.policy:
        for _ in range(args.repeat):
            policy_table(names)
            print(f"after: {_uptime()}", flush=True)
        return 0
    for r in range(args.repeat):
        t0 = time.perf_counter()
        got = {(k, busy): _measure(k, busy, names) for busy in (False, True) for k in (1, 2)}
        cols = ["workload", "1 thr idle", "2 thr idle", "2/1 idle", "1 thr busy", "2 thr busy", "2/1 busy"]
        rows = []
        for n in names:
            i1, i2, b1, b2 = got[1, False][n], got[2, False][n], got[1, True][n], got[2, True][n]
            rows.append(
                [WORKLOADS[n], f"{i1:.3f}", f"{i2:.3f}", f"{i2 / i1:.2f}", f"{b1:.3f}", f"{b2:.3f}", f"{b2 / b1:.2f}"]
            )
        print(f"\n== run {r + 1} of {args.repeat}: seconds per call ({time.perf_counter() - t0:.0f} s)")
        _print_table(cols, rows)
        print(f"after: {_uptime()}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
