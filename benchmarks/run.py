"""The benchmark runner: ``python -m benchmarks [--quick] [--only NAME ...] [--out DIR] [--threads N]``.

Prints one table per benchmark as it finishes, then every target
with the measured figure and whether it was met. With ``--out DIR`` it also
writes ``results.json``, ``results.md`` and the figures there (the folder is
the user's; nothing is committed). Exit status 0 when every benchmark ran
(targets missed are reported, not failures), 1 when one raised.
"""

from __future__ import annotations

import argparse
import cProfile
import importlib
import io
import json
import os
import pstats
import shlex
import sys
import time
import traceback
from pathlib import Path

from ._common import Config, Table, machine, markdown, text

BENCHMARKS = [
    "serve_1p1d",
    "serve_2p1d",
    "serve_1d",
    "train",
    "fidelity",
    "memory",
    "noether",
    "train_scale",
    "serve_nd",  # n-D slice solvers against a numpy leapfrog
    "serve_fast1d",  # 1D serving in numpy against Stormer-Verlet
    "ensemble",  # the cost of an ensemble's error bar
    "serve_scale",  # peak memory of serving with an output cadence
    "serve_dist",  # serving split into slabs over processes
    "discovery",  # select = "auto" on known systems against the true leapfrog
    "calibration",  # calibrated error bars: coverage with and without an ensemble
]


def _load():
    return {m.NAME: m for m in (importlib.import_module(f"benchmarks.{name}") for name in BENCHMARKS)}


def _profile_text(prof: cProfile.Profile, top: int = 15) -> str:
    buf = io.StringIO()
    stats = pstats.Stats(prof, stream=buf)
    stats.strip_dirs().sort_stats("tottime").print_stats(top)
    lines = [ln for ln in buf.getvalue().splitlines() if ln.strip()]
    start = next((k for k, ln in enumerate(lines) if ln.lstrip().startswith("ncalls")), 0)
    return "\n".join(lines[start:])


def _targets(tables: list[Table]) -> Table:
    out = Table("targets", "Targets", ["benchmark", "target", "measured", "met"])
    for t in tables:
        out.rows += [[t.name, c.target, c.measured, "yes" if c.met else "NO"] for c in t.checks]
    return out


def main(argv: list[str] | None = None) -> int:
    mods = _load()
    p = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="tiny sizes: checks that everything runs (seconds)")
    p.add_argument(
        "--only",
        action="append",
        default=[],
        metavar="NAME",
        help=f"run only these benchmarks (repeat or comma-separate): {', '.join(mods)}",
    )
    p.add_argument("--out", type=Path, help="folder for results.json, results.md and figures")
    p.add_argument(
        "--threads", type=int, default=1, help="threads of torch and BLAS/OpenMP (default 1; the machine is shared)"
    )
    p.add_argument(
        "--profile",
        action="store_true",
        help="run each benchmark under cProfile and print (and write) its top functions by own time",
    )
    p.add_argument(
        "--fidelity-steps",
        type=int,
        metavar="N",
        help="steps of the long-run fidelity benchmark (default 100000; 300 with --quick)",
    )
    p.add_argument(
        "--scale-fields",
        type=int,
        metavar="N",
        help="fields of the largest training set of train_scale (default 100; 6 with --quick)",
    )
    args = p.parse_args(argv)
    only = [n for item in args.only for n in item.split(",") if n]
    unknown = [n for n in only if n not in mods]
    if unknown:
        p.error(f"unknown benchmark {unknown[0]!r}; choose from {', '.join(mods)}")
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))  # for the probes' fresh processes
    import latticedft

    latticedft.limit_threads(args.threads)  # torch and every BLAS/OpenMP pool of this process
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
    cfg = Config(
        quick=args.quick,
        out=args.out,
        threads=args.threads,
        fidelity_steps=args.fidelity_steps,
        scale_fields=args.scale_fields,
    )
    command = "python -m benchmarks " + " ".join(shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    info = machine(args.threads)
    print(
        f"# {command}\n# {info['cpu']}, {info['cores']} cores, torch threads {args.threads}, "
        f"load average {info['load_average']}",
        flush=True,
    )
    tables: list[Table] = []
    failed: list[str] = []
    t_all = time.perf_counter()
    for name, mod in mods.items():
        if only and name not in only:
            continue
        t0 = time.perf_counter()
        prof = cProfile.Profile() if args.profile else None
        try:
            if prof is not None:
                prof.enable()
            table = mod.run(cfg)
        except Exception as exc:  # report and go on: one broken benchmark must not hide the others
            traceback.print_exc()
            failed.append(name)
            table = Table(name, mod.TITLE, ["error"], [[f"{type(exc).__name__}: {exc}"]])
        finally:
            if prof is not None:
                prof.disable()
        table.seconds = time.perf_counter() - t0
        tables.append(table)
        print("\n" + text(table), flush=True)
        if prof is not None:
            report = _profile_text(prof)
            print(f"\n-- cProfile of {name} (top functions by own time; subprocess probes not included)\n{report}")
            if args.out is not None:
                (args.out / f"profile_{name}.txt").write_text(report)
    targets = _targets(tables)
    print("\n" + text(targets).replace(" (0.0 s)", ""))
    info["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    total = time.perf_counter() - t_all
    print(f"# total {total:.1f} s, load average after {info['load_average_after']}", flush=True)
    if args.out is not None:
        payload = {
            "command": command,
            "machine": info,
            "quick": args.quick,
            "seconds": total,
            "benchmarks": [t.to_dict() for t in tables],
            "failed": failed,
        }
        (args.out / "results.json").write_text(json.dumps(payload, indent=2, default=float) + "\n")
        md = [
            f"Command: `{command}`",
            "",
            f"Machine: {info['cpu']}, {info['cores']} cores, torch {info['torch']} with "
            f"{args.threads} thread(s), Python {info['python']}, numpy {info['numpy']}, scipy {info['scipy']}; "
            f"load average {info['load_average']} before, {info['load_average_after']} after; "
            f"total {total:.0f} s.",
            "",
        ]
        md += [markdown(t) + "\n" for t in tables] + [markdown(targets).replace("### ", "### ") + "\n"]
        (args.out / "results.md").write_text("\n".join(md))
        print(f"# wrote {args.out / 'results.json'} and {args.out / 'results.md'}")
    return 1 if failed else 0
