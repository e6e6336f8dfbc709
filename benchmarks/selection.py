"""Model selection by serving (``latticedft.select``, ``[model] select = "auto"``) against hand-set models.

    python -m benchmarks.selection [--quick] [--only NAME ...]

Systems (each: the hand-set model, then ``select = "auto"``, both learned from the same data and served
on the same test):

- ``pendulum``: ``q'' = -sin q`` from rest at 2.9 rad (near the separatrix), h = 0.1, trained on the first
  101 slices, served 3,000 steps; error over the horizon.
- ``cases``: the repository's 1D cases ``oscillator-sin`` and ``oscillator-wells`` (the double well) run by
  the command line
  with and without ``--set model.select="auto"`` in a temporary copy; per task its largest error, then the
  run's wall time, the selection's (the candidates' times summed) and the choice (with its score and the
  hand-set one's).
- ``fields``: the field cases ``wave``, ``klein-gordon-periodic`` and ``sine-gordon`` the same way (their data
  made by the case's ``make_data.py`` in the temporary copy where they are not committed); every task's error.
  ``--case NAME`` runs any one case so (``--case kepler``, ``--case wave-2d``).
- ``scores``: ``oscillator-sin``'s ``"auto"`` candidates scored on held-out windows (``hold_out`` 0.3 and
  0.5) and with each training sequence left out, beside their test errors (learned on all three sequences).
- ``kepler``: one orbit from q0 = (1, 0), v0 = (0, 0.6), h = 0.1, 50 steps, ``preset = "radial"``; test orbits
  from q0 = (1.1, -0.01), v0 = (0, 1.0) and (0, 0.9) (outside the training radii); error over the 200 steps,
  after 50 and after 200 steps; also the preset with ``scale = false``.
- ``kepler-seeds``: the same training orbit, the ``radial`` preset at seeds 0, 1, 2 with and without input
  scaling, learned from the exact orbit and from a Störmer-Verlet one (step 0.1: the form fits it exactly); then
  a 5-member ensemble and the calibration of its spread on the two test orbits. Columns: the error over 200
  steps for v0 = (0, 1.0) and (0, 0.9), the training ``rel_res``, the ``rel_res`` of the learned DEL on the
  v0 = (0, 1.0) test orbit, the wall time; the ensemble row also gives the error of its mean, psi_mean.
- ``wave``: fixed-end strings of 1024 sites (modes 1, 3, 7; mode 1 alone) trained on 200 slices (the
  polynomial (4, 8)), served 1,024 slices from the same start; also orders (2, 2) learned on all 200 slices.

``--quick``: the pendulum only, short (seconds to a minute). Wall times are measured on the machine the
benchmark runs on; the selection's own cost (every candidate learned and served once) is in column ``time``.
"""

from __future__ import annotations

import argparse
import copy
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


def _kepler_leapfrog(q0: tuple[float, float], v0: tuple[float, float], n: int, h: float) -> xr.DataArray:
    """The orbit as Störmer-Verlet with step ``h`` computes it: data the ``radial`` form can fit exactly."""
    q, v = np.array(q0, dtype=float), np.array(v0, dtype=float)
    out = [q.copy()]
    for _ in range(n - 1):
        v = v - 0.5 * h * q / np.linalg.norm(q) ** 3
        q = q + h * v
        v = v - 0.5 * h * q / np.linalg.norm(q) ** 3
        out.append(q.copy())
    t = np.arange(n) * h
    return xr.DataArray(np.array(out), dims=("t", "component"), coords={"t": t, "component": ["x", "y"]}, name="psi")


def kepler_seeds(quick: bool) -> list[list]:
    """The Kepler setup of ``kepler`` with the ``radial`` preset at seeds 0, 1, 2 and both scalings, on the
    exact orbits and on Störmer-Verlet ones (step 0.1, which the form fits exactly); then a 5-member ensemble
    (its own seeds per member) with the calibration of its spread on the test orbits. Rows: data, model,
    error after 200 steps for v0 = (0, 1.0) and (0, 0.9), training ``rel_res``, ``rel_res`` of the learned
    DEL on the v0 = (0, 1.0) test orbit (``diagnose``), wall time."""
    rows = []
    for data, make in (("exact", _kepler), ("leapfrog", _kepler_leapfrog)):
        train = make((1.0, 0.0), (0.0, 0.6), 51, 0.1)
        tests = [make((1.1, -0.01), (0.0, vy), 201, 0.1) for vy in (1.0, 0.9)]
        for scale in (True, False):
            for seed in (0, 1, 2):
                model = ldft.MLPLagrangian(preset="radial", scale=scale, seed=seed)
                t0 = time.perf_counter()
                rep = ldft.learn(model, train, progress=False, max_time=60)
                wall = time.perf_counter() - t0
                errs = [_error(model, t, 201)[0] for t in tests]
                test_res = ldft.diagnose(model, tests[0])["rel_res"]
                rows.append([f"kepler {data}", f"scale={scale} seed={seed}", *errs, rep.rel_res, test_res, wall])
                print(" | ".join(str(c) for c in rows[-1]), flush=True)
        model = ldft.MLPLagrangian(preset="radial")
        t0 = time.perf_counter()
        rep = ldft.learn(model, train, progress=False, max_time=60, ensemble=5)
        wall = time.perf_counter() - t0
        errs, cals = [], []
        for t in tests:
            out = ldft.serve(model.ensemble_, t, slices=201, progress=False)
            errs.append(float(np.abs(out.field.values - t.values).max()))
            cal = ldft.calibration(out.field, out.std, t)
            mean_err = float(np.abs(out.mean.values - t.values).max())
            cals.append(f"{100 * cal['within_2std']:.0f} % / {cal['std_over_error']:.2g} / {mean_err:.2g}")
        label = "ensemble of 5 (within 2 std / std over error / error of psi_mean: " + ", ".join(cals) + ")"
        rows.append([f"kepler {data}", label, *errs, rep.rel_res, float("nan"), wall])
        print(" | ".join(str(c) for c in rows[-1]), flush=True)
    return rows


def wave(quick: bool) -> list[list]:
    rows = []
    for label, modes in (("modes 1, 3, 7", [(1, 1.0), (3, 0.3), (7, 0.05)]), ("mode 1", [(1, 1.0)])):
        train = systems.wave_string(modes, nx=1024, nt=200)
        test = systems.wave_string(modes, nx=1024, nt=1024)
        name = f"wave 1024, {label}"
        rows += _compare(name, ldft.PolynomialLagrangian((4, 8)), train, {"1024 slices": test}, 1024)
        quadratic = ldft.PolynomialLagrangian((2, 2))  # the exact form's orders, learned on all 200 slices
        t0 = time.perf_counter()
        ldft.learn(quadratic, train, progress=False)
        rows.append(
            [f"{name} 1024 slices", "orders=[2, 2]", *_error(quadratic, test, 1024), time.perf_counter() - t0, ""]
        )
    return rows


def _run_case(name: str, extra: list[str]) -> tuple[dict[str, Any], float, str]:
    """Run ``cases/<name>`` by the command line in a temporary copy (its data made there by ``make_data.py``
    when they are not in the repository); ``(summary, wall time, error text)``."""
    with tempfile.TemporaryDirectory() as tmp:
        case = Path(tmp) / name
        shutil.copytree(REPO / "cases" / name, case, ignore=shutil.ignore_patterns("results*"))
        if not any(p.suffix == ".nc" for p in (case / "data").glob("*")) and (case / "make_data.py").exists():
            subprocess.run([sys.executable, "make_data.py"], cwd=case, check=False, capture_output=True)
        t0 = time.perf_counter()
        cmd = [sys.executable, "-m", "latticedft", "run", str(case), "--set", "export.formats=[]", *extra]
        proc = subprocess.run(cmd, check=False, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        path = case / "results" / "summary.json"
        if not path.exists():
            return {}, wall, (proc.stderr.strip().splitlines() or ["no summary.json"])[-1]
        return json.loads(path.read_text()), wall, ""


def run_cases(names: tuple[str, ...]) -> list[list]:
    """Each case hand-set and with ``select = "auto"``: one row per task and model with the task's largest
    error, the run's wall time and the selection's (every candidate learned and served once), and the choice."""
    rows = []
    for name in names:
        for label, extra in (("hand-set", []), ("auto", ["--set", 'model.select="auto"'])):
            summary, wall, failed = _run_case(name, extra)
            if failed:
                rows.append([f"case {name}", label, float("inf"), wall, float("nan"), f"run failed: {failed}"])
                continue
            sel = summary["train"].get("selection") or {}
            sel_time = float(sum(c.get("wall_time") or 0.0 for c in sel.get("candidates", [])))
            chosen = sel.get("chosen_label", "")
            if sel:
                best, hand = (sel["candidates"][i].get("score") for i in (sel["chosen"], 0))
                chosen += f" (score {best:.1e}, hand-set {hand:.1e})" if best is not None and hand is not None else ""
            for task, rec in summary["tasks"].items():
                err = rec.get("max_error")
                err = float("inf") if err is None else float(err)
                rows.append([f"{name} {task}", label, err, wall, sel_time if sel else float("nan"), chosen])
    return rows


def cases(quick: bool) -> list[list]:
    return run_cases(("oscillator-sin", "oscillator-wells"))


def fields(quick: bool) -> list[list]:
    return run_cases(("wave", "klein-gordon-periodic", "sine-gordon"))


def _fitted(hand: Any, change: dict, fields: list[xr.DataArray]) -> Any:
    """The candidate ``change`` of the hand-set model (``ridge = "auto"`` unless it changes it), learned."""
    from latticedft import _select as sel

    kind, options, ridge = sel._spec(hand, change, "auto")
    model = copy.deepcopy(hand) if not change else sel._build(hand, kind, options)
    ldft.learn(model, fields, ridge=ridge, progress=False)
    return model


def scores(quick: bool) -> list[list]:
    """``cases/oscillator-sin``: every candidate of ``"auto"`` scored three ways (served held-out windows with
    ``hold_out`` 0.3, the default, and 0.5; each training sequence served by the candidate learned from the
    other two) beside the case's task errors of the candidate learned from all three sequences."""
    from latticedft import _select as sel

    data = REPO / "cases" / "oscillator-sin" / "data"
    train = [xr.open_dataarray(data / f"train_{a}.nc").load() for a in ("1.20", "0.80", "0.40")]
    tests = [xr.open_dataarray(data / f"{n}.nc").load() for n in ("test_m0.60", "test_0.10", "train_1.20")]
    hand = ldft.PolynomialLagrangian((4, 8))
    print(
        "  candidate: held-out score (hold_out 0.3, 0.5), sequence 1.2 / 0.8 / 0.4 left out;"
        " tasks test_m0.60, test_0.10, train"
    )
    rows = []
    for change in [{}, *sel.auto_candidates(hand, 1, "auto")]:

        def score(fit: list[xr.DataArray], served: list[xr.DataArray], change: dict = change) -> float:
            try:
                return sel._score(_fitted(hand, change, fit), served, None)
            except ldft.LatticeDFTError:
                return float("inf")

        out = [score(sel._split(train, h), train) for h in (0.3, 0.5)]
        out += [score([f for j, f in enumerate(train) if j != i], [train[i]]) for i in range(len(train))]
        model = _fitted(hand, change, train)
        out += [_error(model, t)[0] for t in tests]
        rows.append([sel._label(change), f"{model.n_parameters()}", *out, ""])
    return rows


SYSTEMS = {
    "pendulum": pendulum,
    "cases": cases,
    "fields": fields,
    "scores": scores,
    "kepler": kepler,
    "kepler-seeds": kepler_seeds,
    "wave": wave,
}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.selection", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="the pendulum only, 300 steps")
    p.add_argument("--only", action="append", default=[], metavar="NAME", help=f"among {', '.join(SYSTEMS)}")
    p.add_argument("--case", action="append", default=[], metavar="CASE", help="a repository case (cases/CASE)")
    args = p.parse_args(argv)
    names = args.only or ([] if args.case else ["pendulum"] if args.quick else list(SYSTEMS))
    runs = [(name, lambda name=name: SYSTEMS[name](args.quick)) for name in names]
    runs += [(f"case {c}", lambda c=c: run_cases((c,))) for c in args.case]
    for name, run in runs:
        print(f"== {name}", flush=True)
        for row in run():
            nums = " ".join(f"{v:10.3e}" if isinstance(v, float) else str(v) for v in row[2:-1])
            print(f"  {row[0]:<24} {row[1]:<9} {nums}  {row[-1]}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
