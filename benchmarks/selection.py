"""Model selection by serving (``latticedft.select``, ``[model] select = "auto"``) against hand-set models.

    python -m benchmarks.selection [--quick] [--only NAME ...]

Systems (each: the hand-set model, then ``select = "auto"``, both learned from the same data and served
on the same test):

- ``pendulum``: ``q'' = -sin q`` from rest at 2.9 rad (near the separatrix), h = 0.1, trained on the first
  101 slices, served 3,000 steps; error over the horizon.
- ``cases``: the repository's 1D cases ``oscillator-sin`` and ``oscillator-wells`` (the double well) run by
  the command line
  with and without ``--set model.select="auto"``; largest task error.
- ``kepler``: one orbit from q0 = (1, 0), v0 = (0, 0.6), h = 0.1, 50 steps, ``preset = "radial"``; test orbits
  from q0 = (1.1, -0.01), v0 = (0, 1.0) and (0, 0.9) (outside the training radii); error over the 200 steps,
  after 50 and after 200 steps; also the preset with ``scale = false``.
- ``wave``: a fixed-end string of 1024 sites trained on 200 slices (default polynomial), served 200 slices.

``--quick``: the pendulum only, short (seconds to a minute). Wall times are measured on the machine the
benchmark runs on; the selection's own cost (every candidate learned and served once) is in column ``time``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr
from scipy.integrate import solve_ivp

import latticedft as ldft
from latticedft import systems

NAME = "selection"
REPO = Path(__file__).resolve().parents[1]


def _pendulum(q0: float, n: int, h: float = 0.1) -> xr.DataArray:
    t = np.arange(n) * h
    sol = solve_ivp(
        lambda _, y: [y[1], -np.sin(y[0])], (0, t[-1]), [q0, 0.0], t_eval=t, method="DOP853", rtol=1e-12, atol=1e-12
    )
    return xr.DataArray(sol.y[0], dims="t", coords={"t": t}, name="psi")


def _kepler(q0: tuple[float, float], v0: tuple[float, float], n: int, h: float) -> xr.DataArray:
    def rhs(_: float, y: np.ndarray) -> list[float]:
        r3 = (y[0] ** 2 + y[1] ** 2) ** 1.5
        return [y[2], y[3], -y[0] / r3, -y[1] / r3]

    t = np.arange(n) * h
    sol = solve_ivp(rhs, (0, t[-1]), [*q0, *v0], t_eval=t, method="DOP853", rtol=1e-12, atol=1e-12)
    return xr.DataArray(sol.y[:2].T, dims=("t", "component"), coords={"t": t, "component": ["x", "y"]}, name="psi")


def _error(model: Any, test: xr.DataArray, slices: int | None = None, at: tuple[int, ...] = ()) -> list[float]:
    """Largest error over the served slices (and after each step count in ``at``); ``inf`` where it stopped."""
    try:
        pred = ldft.serve(model, test, slices=slices, progress=False).field.values
    except ldft.ServeError as exc:
        pred = exc.result.field.values
    ref = test.values
    err = np.abs(pred - ref[: pred.shape[0]]).reshape(pred.shape[0], -1).max(1)
    full = len(err) == (slices or ref.shape[0])
    out = [float(err.max()) if full and np.isfinite(err).all() else float("inf")]
    out += [float(err[: k + 1].max()) if k < len(err) else float("inf") for k in at]
    return out


def _compare(name: str, model: Any, train: Any, tests: dict[str, xr.DataArray], slices: int | None, at=(), **kw: Any):
    """Rows ``[system, model, error, (errors after ``at`` steps), wall time, chosen]`` per test: the hand-set
    model learned as it is, then ``select(model, train, "auto")``."""
    hand = ldft.MODELS[model.kind](**model.options())
    t0 = time.perf_counter()
    ldft.learn(hand, train, progress=False, **kw)
    wall_hand = time.perf_counter() - t0
    t0 = time.perf_counter()
    rep = ldft.select(model, train, "auto", **kw)
    wall = time.perf_counter() - t0
    print("\n".join(f"    {line}" for line in rep.table_lines()), flush=True)
    rows = []
    for tname, test in tests.items():
        rows.append([f"{name} {tname}", "hand-set", *_error(hand, test, slices, at), wall_hand, ""])
        rows.append(
            [f"{name} {tname}", "auto", *_error(rep.model, test, slices, at), wall, rep.rows[rep.chosen]["label"]]
        )
    return rows


def pendulum(quick: bool) -> list[list]:
    train = _pendulum(2.9, 101)
    test = _pendulum(2.9, 301 if quick else 3001)
    return _compare("pendulum 2.9 rad", ldft.PolynomialLagrangian((4, 8)), train, {"": test}, None)


def kepler(quick: bool) -> list[list]:
    train = _kepler((1.0, 0.0), (0.0, 0.6), 51, 0.1)
    tests = {f"v0=(0,{vy})": _kepler((1.1, -0.01), (0.0, vy), 201, 0.1) for vy in (1.0, 0.9)}
    rows = _compare("kepler", ldft.MLPLagrangian(preset="radial"), train, tests, 201, at=(50, 200), max_time=60)
    unscaled = ldft.MLPLagrangian(preset="radial", scale=False)  # the other scaling, learned on all the data
    t0 = time.perf_counter()
    ldft.learn(unscaled, train, progress=False, max_time=60)
    wall = time.perf_counter() - t0
    for tname, test in tests.items():
        rows.append([f"kepler {tname}", "scale=False", *_error(unscaled, test, 201, (50, 200)), wall, ""])
    return rows


def wave(quick: bool) -> list[list]:
    field = systems.wave_string([(1, 1.0), (3, 0.3), (7, 0.05)], nx=1024, nt=200)
    return _compare("wave 1024 fixed ends", ldft.PolynomialLagrangian((4, 8)), field, {"": field}, None)


def cases(quick: bool) -> list[list]:
    rows = []
    for name in ("oscillator-sin", "oscillator-wells"):
        for label, extra in (("hand-set", []), ("auto", ["--set", 'model.select="auto"'])):
            with tempfile.TemporaryDirectory() as tmp:
                case = Path(tmp) / name
                shutil.copytree(REPO / "cases" / name, case, ignore=shutil.ignore_patterns("results*"))
                t0 = time.perf_counter()
                cmd = [sys.executable, "-m", "latticedft", "run", str(case), "--set", "export.formats=[]", *extra]
                subprocess.run(cmd, check=False, capture_output=True)
                wall = time.perf_counter() - t0
                summary = json.loads((case / "results" / "summary.json").read_text())
                errs = [t.get("max_error") for t in summary["tasks"].values()]
                worst = max((e if e is not None else float("inf")) for e in errs)
                chosen = (summary["train"].get("selection") or {}).get("chosen_label", "")
                rows.append([f"case {name}", label, worst, wall, chosen])
    return rows


SYSTEMS = {"pendulum": pendulum, "cases": cases, "kepler": kepler, "wave": wave}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.selection", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="the pendulum only, 300 steps")
    p.add_argument("--only", action="append", default=[], metavar="NAME", help=f"among {', '.join(SYSTEMS)}")
    args = p.parse_args(argv)
    names = args.only or (["pendulum"] if args.quick else list(SYSTEMS))
    for name in names:
        print(f"== {name}", flush=True)
        for row in SYSTEMS[name](args.quick):
            nums = " ".join(f"{v:10.3e}" if isinstance(v, float) else str(v) for v in row[2:-1])
            print(f"  {row[0]:<24} {row[1]:<9} {nums}  {row[-1]}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
