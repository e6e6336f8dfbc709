"""Draw the pictures of docs/gallery.md: one per case of cases/, from a `latticedft run` of the case.

    python docs/make_gallery.py                 # every case (a few minutes on two cores)
    python docs/make_gallery.py wave kepler     # some of them
    python docs/make_gallery.py --keep /tmp/g   # keep the runs' folders there (to open them in ParaView)
    python docs/make_gallery.py --keep /tmp/g --redraw   # redraw from the runs kept there

Each case is copied into a scratch folder (its data made by its own make_data.py when the copy has none),
run with ``python -m latticedft run`` and its own case.toml (export: figures only), and the figure of one
task is drawn from that run's ``results/<task>.nc`` with :func:`latticedft.io.figures.task_figure`: the
same figure as ``results/<task>.png`` with the case in its title, saved smaller (80 dpi) as
``docs/gallery/<case>.png``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "docs" / "gallery"
if str(REPO) not in sys.path:  # this checkout's latticedft, also when another one is installed
    sys.path.insert(0, str(REPO))

#: case -> (folder of the case to run, relative to cases/; the task drawn; the figure's title)
GALLERY: dict[str, tuple[str, str, str]] = {
    "wave": ("wave", "test", "cases/wave, task test: a string with fixed ends, served 5x longer than trained"),
    "wave-2d": ("wave-2d", "test", "cases/wave-2d, task test: a membrane with a fixed frame"),
    "klein-gordon-periodic": (
        "klein-gordon-periodic/mlp",
        "test400",
        "cases/klein-gordon-periodic/mlp, task test400: an MLP L_d, 400 steps of an unseen mode",
    ),
    "sine-gordon": (
        "sine-gordon",
        "kink_antikink",
        "cases/sine-gordon, task kink_antikink: a collision, learned from one breather",
    ),
    "oscillator-sin": ("oscillator-sin", "test_m0.60", "cases/oscillator-sin, task test_m0.60 (Qin 2020, Fig. 3)"),
    "oscillator-wells": (
        "oscillator-wells",
        "test_left",
        "cases/oscillator-wells, task test_left: the left small well (Qin 2020, Fig. 8)",
    ),
    "kepler": ("kepler", "earth_1.13", "cases/kepler, task earth_1.13: launched from Earth's aphelion at 1.13"),
}


def _run(cmd: list[str], cwd: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    if proc.returncode not in (0, 3):  # 3: a task stopped part-way; its figure says so
        sys.exit(f"{' '.join(cmd)} (in {cwd}) failed with exit status {proc.returncode}:\n{proc.stderr[-2000:]}")


def draw(case: str, scratch: Path, *, rerun: bool = True) -> Path:
    """Run ``case`` in ``scratch`` (unless ``rerun`` is false and a run is there) and draw its picture."""
    from latticedft.io.figures import save_figure, task_figure

    folder, task, title = GALLERY[case]
    root = folder.split("/")[0]
    copy = scratch / root
    if not copy.exists():
        shutil.copytree(REPO / "cases" / root, copy, ignore=shutil.ignore_patterns("results*", "*.png"))
    data = copy / "data"
    if not data.is_dir() or not any(data.glob("*.nc")):
        _run([sys.executable, "make_data.py"], copy)
    run_dir = scratch / folder
    task_file = run_dir / "results" / f"{task}.nc"
    if rerun or not task_file.is_file():
        cmd = [sys.executable, "-m", "latticedft", "run", str(run_dir), "-q", "--overwrite"]
        _run([*cmd, "--set", 'export.formats=["figures"]'], scratch)
    OUT.mkdir(parents=True, exist_ok=True)
    target = OUT / f"{case}.png"
    save_figure(task_figure(task_file, title=title), target, dpi=80)
    return target


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cases", nargs="*", metavar="CASE", help=f"cases to draw: {', '.join(GALLERY)} (default: all)")
    parser.add_argument("--keep", type=Path, help="run the cases in this folder and keep it")
    parser.add_argument("--redraw", action="store_true", help="with --keep: reuse the runs found there")
    args = parser.parse_args(argv)
    cases = args.cases or list(GALLERY)
    unknown = [c for c in cases if c not in GALLERY]
    if unknown:
        parser.error(f"unknown case(s) {', '.join(unknown)}; cases: {', '.join(GALLERY)}")
    with tempfile.TemporaryDirectory(prefix="gallery-") as tmp:
        scratch = args.keep or Path(tmp)
        scratch.mkdir(parents=True, exist_ok=True)
        for case in cases:
            start = time.perf_counter()
            path = draw(case, scratch, rerun=not (args.redraw and args.keep))
            size, wall = path.stat().st_size // 1024, time.perf_counter() - start
            print(f"{case}: {path.relative_to(REPO)} ({size} KiB, {wall:.0f} s)", flush=True)
    total = sum(p.stat().st_size for p in OUT.glob("*.png"))
    print(f"docs/gallery: {total / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
