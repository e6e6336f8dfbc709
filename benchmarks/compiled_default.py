"""The compiled kernels as the default, measured on the cases' own models: CPU seconds of ``serve`` with the
default options against ``set_options(compiled_kernels=False)`` (numpy forms and autograd), in one process,
alternating, the least of three each.

    python -m benchmarks.compiled_default [--quick]

The models are trained here from the cases' data by ``latticedft train`` (cases/wave and cases/wave-2d: a
polynomial (2, 2), which is not quadratic in the stencil values, served on the folded polynomial kernels;
cases/sine-gordon: a polynomial (2, 12), the same; cases/klein-gordon-periodic/mlp: a kinetic-potential MLP
served by its closed forms), then the cases' test fields are served from their first two slices (and, with
Dirichlet ends, their boundary strips). Each figure is the least of three calls; the first call of each
is printed too (the process's first default serve loads the kernel module from the cache, and imports numba).
The load average is printed before and after. ``--quick``: the kink-antikink task only, one repetition (that
it runs, not its figures).
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

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
CASES = ROOT / "cases"

#: (label, case folder, test file relative to it, boundary, quick)
TASKS = [
    ("wave test (41 sites, 401 slices)", "wave", "data/test.nc", "dirichlet", False),
    ("wave-2d test", "wave-2d", "data/test.nc", "dirichlet", False),
    ("sine-gordon breather", "sine-gordon", "data/breather.nc", "dirichlet", False),
    ("sine-gordon kink_antikink", "sine-gordon", "data/kink_antikink.nc", "dirichlet", True),
    ("klein-gordon-periodic/mlp test400", "klein-gordon-periodic/mlp", "../data/test.nc", "periodic", False),
]


def _copy(case: str, tmp: Path) -> Path:
    """A copy of the case's top folder in ``tmp`` (its data made there where the repository has none: the
    repository is never written); the case's folder in the copy."""
    top = case.split("/")[0]
    dest = tmp / top
    if not dest.exists():
        shutil.copytree(CASES / top, dest, ignore=shutil.ignore_patterns("results*"))
        if not any((dest / "data").glob("*.nc")) and (dest / "make_data.py").exists():
            subprocess.run([sys.executable, "make_data.py"], cwd=dest, check=True, capture_output=True)
    return tmp / case


def _train(folder: Path) -> Path:
    """``latticedft train`` of the case ``folder`` into ``folder/trained``; its model file."""
    out = folder / "trained"
    cmd = [sys.executable, "-m", "latticedft", "train", str(folder), "--out", str(out), "-q"]
    subprocess.run(cmd, check=True, env=dict(os.environ, OMP_NUM_THREADS="1"))
    return out / "model.pt"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.compiled_default", description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="the kink-antikink task only, one repetition")
    args = p.parse_args(argv)
    import torch

    import latticedft as ldft

    torch.set_num_threads(1)
    tasks = [t for t in TASKS if t[4] or not args.quick]
    repeats = 1 if args.quick else 3
    print("load average before:", os.getloadavg())
    with tempfile.TemporaryDirectory() as tmp:
        folders = {c: _copy(c, Path(tmp)) for c in {t[1] for t in tasks}}
        models = {c: _train(folder) for c, folder in folders.items()}
        print(
            "| task | field | default CPU s | its first call | compiled_kernels=False CPU s | its first call "
            "| ratio | largest difference / max |"
        )
        print("|---|---|---|---|---|---|---|---|")
        for label, case, test, boundary, _ in tasks:
            model = ldft.load_model(models[case])
            field = ldft.io.read_field(folders[case] / test)
            init = field if boundary == "dirichlet" else field.isel(t=slice(0, 2))
            kw = dict(slices=field.sizes["t"], boundary=boundary, progress=False)
            seconds: dict[bool, list[float]] = {True: [], False: []}
            served: dict[bool, np.ndarray] = {}
            for _ in range(repeats):
                for on in (True, False):
                    with ldft.set_options(compiled_kernels=on):
                        t0 = time.process_time()
                        result = ldft.serve(model, init, **kw)
                        seconds[on].append(time.process_time() - t0)
                    served[on] = np.asarray(result.field.values)
            a, b = min(seconds[True]), min(seconds[False])
            diff = float(np.nanmax(np.abs(served[True] - served[False])) / np.nanmax(np.abs(served[False])))
            sizes = " x ".join(str(n) for n in field.sizes.values())
            first = f"{seconds[True][0]:.3f} | {b:.3f} | {seconds[False][0]:.3f}"
            print(f"| {label} | {sizes} | {a:.3f} | {first} | {a / b:.2f} | {diff:.1e} |")
    print("load average after:", os.getloadavg())
    return 0


if __name__ == "__main__":
    sys.exit(main())
