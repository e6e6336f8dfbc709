"""Shared pieces of the benchmarks: tables, targets, timing, machine description, peak memory."""

from __future__ import annotations

import json
import os
import platform
import resource
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np


@dataclass
class Config:
    """What one run of the runner asks of every benchmark."""

    quick: bool = False
    out: Path | None = None
    threads: int = 1
    fidelity_steps: int | None = None  # None: 1e5 (300 when quick)
    scale_fields: int | None = None  # None: 100 (the largest training set of train_scale)


@dataclass
class Check:
    """One benchmark target and whether this run met it."""

    target: str
    measured: str
    met: bool


@dataclass
class Table:
    """The figures of one benchmark: a header, rows (numbers or text), notes and target checks."""

    name: str
    title: str
    columns: list[str]
    rows: list[list[Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    checks: list[Check] = field(default_factory=list)
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "title": self.title,
            "columns": self.columns,
            "rows": self.rows,
            "notes": self.notes,
            "checks": [c.__dict__ for c in self.checks],
            "seconds": self.seconds,
        }


def fmt(v: Any) -> str:
    """A number in a table cell: 3 significant digits, thousands as ``1.23e+06``."""
    if isinstance(v, bool) or v is None:
        return "-" if v is None else str(v)
    if isinstance(v, (int, np.integer)):
        return f"{int(v):,}" if abs(int(v)) < 10**7 else f"{float(v):.3g}"
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if v != v:
            return "nan"
        if v == 0:
            return "0"
        if 1e-2 <= abs(v) < 1e5:
            return f"{v:.3g}" if abs(v) < 100 else f"{v:,.0f}"
        return f"{v:.2e}"
    return str(v)


def markdown(table: Table) -> str:
    """A table as GitHub markdown, notes as a list below it."""

    def cell(v: Any) -> str:
        return fmt(v).replace("|", "\\|")

    lines = [
        f"### {table.title}",
        "",
        "| " + " | ".join(cell(c) for c in table.columns) + " |",
        "|" + "|".join("---" for _ in table.columns) + "|",
    ]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in table.rows]
    if table.notes:
        lines.append("")
        lines += [f"- {n}" for n in table.notes]
    return "\n".join(lines)


def text(table: Table) -> str:
    """A table as aligned plain text for the terminal."""
    cells = [table.columns] + [[fmt(v) for v in row] for row in table.rows]
    widths = [max(len(r[k]) for r in cells) for k in range(len(table.columns))]
    out = [f"== {table.title} ({table.seconds:.1f} s)"]
    for j, r in enumerate(cells):
        out.append("  ".join(c.rjust(w) if j and k else c.ljust(w) for k, (c, w) in enumerate(zip(r, widths))))
        if j == 0:
            out.append("  ".join("-" * w for w in widths))
    out += [f"  * {n}" for n in table.notes]
    return "\n".join(out)


def best_time(fn: Callable[[], Any], repeat: int = 3) -> tuple[float, Any]:
    """Smallest wall time of ``repeat`` calls (the least disturbed by other load) and the last result."""
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def best_times(fn: Callable[[], Any], repeat: int = 3) -> tuple[float, float, Any]:
    """Wall and CPU seconds (``time.process_time``: every thread of the process) of the call of least wall
    time among ``repeat``, and the last result."""
    best, out = (float("inf"), float("inf")), None
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        best = min(best, (time.perf_counter() - t0, time.process_time() - c0))
    return best[0], best[1], out


def load_average() -> str:
    """The 1, 5 and 15 minute load averages, as ``uptime`` prints them."""
    return ", ".join(f"{x:.2f}" for x in os.getloadavg())


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def machine(threads: int) -> dict[str, Any]:
    """The machine and software a run was taken on (no host names, no paths)."""
    import scipy
    import torch

    import latticedft

    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "torch_threads": threads,
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "latticedft": latticedft.__version__,
        "platform": platform.platform(terse=True),
    }


def maxrss_mib() -> float:
    """Peak resident memory of this process so far (Linux ``ru_maxrss`` is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _status_mib(key: str) -> float | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        pass
    return None


class PeakRSS:
    """Peak resident memory of a stretch of work: the kernel's high-water mark ``VmHWM``, reset at the start
    (``echo 5 > /proc/self/clear_refs``, Linux); where that is not possible, ``ru_maxrss`` (a process-wide
    high-water mark, so then the start's own peak may hide the work's)."""

    def __init__(self) -> None:
        try:
            Path("/proc/self/clear_refs").write_text("5")
            self.reset = _status_mib("VmHWM") is not None
        except OSError:
            self.reset = False
        self.before = _status_mib("VmRSS") if self.reset else maxrss_mib()

    def peak(self) -> float:
        value = _status_mib("VmHWM") if self.reset else None
        return value if value is not None else maxrss_mib()


def in_subprocess(probe: str, threads: int, inline: bool = False, **kwargs: Any) -> dict[str, Any]:
    """Run ``benchmarks._probes.<probe>(**kwargs)`` in a fresh Python and return its JSON answer.

    The probe reports its own ``ru_maxrss`` before the work (after imports, a warm-up and building its
    inputs) and after it, so the peak of one task is measured apart from the runner's own memory.
    ``inline=True`` (the ``--quick`` smoke run) calls it in this process instead, saving the interpreter's
    start-up; its memory figures are then the runner's.
    """
    if inline:
        from . import _probes

        return json.loads(json.dumps(_probes.run(probe, threads, kwargs)))
    root = Path(__file__).resolve().parent.parent
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    code = (
        "import json, sys; from benchmarks import _probes; "
        f"print('@@' + json.dumps(_probes.run({probe!r}, {threads}, json.loads(sys.argv[1]))))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, json.dumps(kwargs)], cwd=root, env=env, capture_output=True, text=True, check=False
    )
    for line in proc.stdout.splitlines():
        if line.startswith("@@"):
            return json.loads(line[2:])
    raise RuntimeError(f"probe {probe} failed (exit {proc.returncode}): {proc.stderr.strip()[-2000:]}")


def run_alone(run: Callable[[Config], Table], doc: str | None, argv: list[str] | None = None) -> int:
    """``python -m benchmarks.<module> [--quick] [--threads N]``: the module's default table, printed alone.

    The threads are bounded as by the runner (torch and every BLAS/OpenMP pool, ``latticedft.limit_threads``);
    the load average before and after is printed beside the table, whose times are absolute.
    """
    import argparse

    import latticedft

    p = argparse.ArgumentParser(description=(doc or "").strip().split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="tiny sizes: checks that it runs (seconds)")
    p.add_argument("--threads", type=int, default=1, help="threads of torch and BLAS (default 1)")
    args = p.parse_args(argv)
    latticedft.limit_threads(args.threads)
    print(f"# load average before: {load_average()}", flush=True)
    t0 = time.perf_counter()
    table = run(Config(quick=args.quick, threads=args.threads))
    table.seconds = time.perf_counter() - t0
    print_table(table)
    print(f"# load average after: {load_average()}", flush=True)
    return 0


def print_table(table: Table) -> None:
    """The table as text, then its targets, met or not."""
    print(text(table))
    for c in table.checks:
        print(f"  [{'met' if c.met else 'NOT met'}] {c.target}: {c.measured}")
