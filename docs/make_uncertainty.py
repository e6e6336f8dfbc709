"""Measure how well an ensemble's spread bounds the error on the cases of cases/, and draw the band figure.

    python docs/make_uncertainty.py                     # the default cases (minutes on two cores)
    python docs/make_uncertainty.py oscillator-sin      # some of them
    python docs/make_uncertainty.py --members 5         # another ensemble size

Each case is copied into a scratch folder (its data made by its own make_data.py when the copy has none) and
run with ``python -m latticedft run`` and its own case.toml plus ``--set train.ensemble=N`` and
``--set train.calibrate=false`` (the members' own spread; export: figures
only). Every task with a reference reports its ``calibration`` in ``summary.json``; this script prints them
as the markdown table of docs/uncertainty.md, and draws the figure of one task (``oscillator-sin``, task
``test_m0.60``) as ``docs/uncertainty_band.png`` (70 dpi).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # this checkout's latticedft, also when another one is installed
    sys.path.insert(0, str(REPO))

#: The cases measured by default. ``wave-2d`` and ``kepler`` are left out of the default (their training
#: and serving take minutes per member on two cores) but may be named.
CASES = ["oscillator-sin", "oscillator-wells", "wave", "klein-gordon-periodic", "sine-gordon"]
ALL = [*CASES, "wave-2d", "kepler"]
#: The task whose figure is docs/uncertainty_band.png.
BAND = ("oscillator-sin", "test_m0.60")


def _run(cmd: list[str], cwd: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    if proc.returncode not in (0, 3):  # 3: a task stopped part-way; its record says so
        sys.exit(f"{' '.join(cmd)} (in {cwd}) failed with exit status {proc.returncode}:\n{proc.stderr[-2000:]}")


def measure(case: str, scratch: Path, members: int) -> dict:
    """Run ``case`` with an ensemble of ``members`` in ``scratch``; its summary.json."""
    copy = scratch / case
    if not copy.exists():
        shutil.copytree(REPO / "cases" / case, copy, ignore=shutil.ignore_patterns("results*", "*.png"))
    data = copy / "data"
    if not data.is_dir() or not any(data.glob("*.nc")):
        _run([sys.executable, "make_data.py"], copy)
    cmd = [sys.executable, "-m", "latticedft", "run", str(copy), "-q", "--overwrite"]
    sets = ["--set", f"train.ensemble={members}", "--set", "train.calibrate=false"]  # the members' own spread
    _run([*cmd, *sets, "--set", 'export.formats=["figures"]'], scratch)
    return json.loads((copy / "results" / "summary.json").read_text())


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.0f} %"


def _num(x: float | None) -> str:
    return "-" if x is None else f"{x:.2g}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cases", nargs="*", metavar="CASE", help=f"cases: {', '.join(ALL)} (default: {CASES})")
    parser.add_argument("--members", type=int, default=9, help="ensemble members (default 9)")
    args = parser.parse_args(argv)
    cases = args.cases or CASES
    unknown = [c for c in cases if c not in ALL]
    if unknown:
        parser.error(f"unknown case(s) {', '.join(unknown)}; cases: {', '.join(ALL)}")
    rows = [
        "| case | task | complete | slices | within 2 std | within 3 std | mean std / mean error |",
        "|---" * 7 + "|",
    ]
    with tempfile.TemporaryDirectory(prefix="uncertainty-") as tmp:
        scratch = Path(tmp)
        for case in cases:
            summary = measure(case, scratch, args.members)
            for name, task in summary["tasks"].items():
                cal = task.get("calibration")
                if not cal:
                    continue
                rows.append(
                    f"| {case} | {name} | {'yes' if task['complete'] else 'no'} | {cal['slices']} | "
                    f"{_pct(cal['within_2std'])} | {_pct(cal['within_3std'])} | {_num(cal['std_over_error'])} |"
                )
            print(f"{case}: done", file=sys.stderr, flush=True)
            if case == BAND[0]:
                from latticedft.io.figures import save_figure, task_figure

                path = scratch / case / "results" / f"{BAND[1]}.nc"
                title = f"cases/{case}, task {BAND[1]}, {args.members} members"
                save_figure(task_figure(path, title=title), REPO / "docs" / "uncertainty_band.png", dpi=70)
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
