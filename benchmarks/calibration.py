"""Calibrated error bars: does twice the served error estimate cover the error, with and without an ensemble?

    python -m benchmarks.calibration [--quick] [--cases A,B] [--sigmas 0,0.001] [--no-extra | --extra TEXT]
        [--record FILE]
    python -m benchmarks --only calibration

Rows: every repository case (``cases/*``, each its own ``case.toml`` model and data; the three without committed
data made by their ``make_data.py`` in a temporary copy), clean and with Gaussian noise of ``1e-3`` of each field's
amplitude (training fields and tasks' initial data; ``noise = "auto"``, served from denoised starts; errors
against the clean reference), then the oscillators and fields of the calibration targets' table: the
double-well Duffing oscillator (test launches in one well and over both), a phi^4 string and a nonlinear
Klein-Gordon string (leapfrog data, polynomial (2, 4)), and bound Kepler launches (the radial MLP learned on
Venus, Earth, Mars). Per row: the model is chosen by ``select`` (``"auto"`` candidates; not for Kepler: minutes
per MLP candidate; nor for noisy space-time fields: each candidate would repeat the noise correction; the MLP
fits stop at their iteration limit, 500 L-BFGS iterations, and at no time limit: a row's models are the same
however busy the machine is), calibrated by :func:`latticedft._calibrate.calibrate` (the runner-up's disagreement
included), and served on every test field; without selection, a row with an ensemble takes its member 0 (learned
on all the data, as the single model is) as the single model instead of learning it twice. A single model's band
is ``psi_err_est`` (the larger of the held-out
law and the held-out trial model's disagreement on the task); an ensemble's (5 members, seed 0; not for Kepler)
is its members' standard deviation scaled by a factor measured on the held-out slices as the law's scale is,
and widened to at least the trial's disagreement (``psi_std``, :meth:`latticedft._calibrate.Calibration.band`);
"raw" is the
members' standard deviation alone (the band before calibration); "law only" the held-out law without the
trial's disagreement. Over the served slices of every test field
(the two given ones excluded), per slice the RMS error over the lattice: *coverage* is the share within 2 times
the band's RMS, *std/error* the mean band over the mean error. *silent misses* counts the test fields whose
single band covers less than half of their slices and that draw no calibration warning (the candidates' check
included: with a runner-up, its trial is served from each test's start beside the trial, and the test warns when
the two disagree more than ``CANDIDATES_RATIO`` times as much as on the training fields,
:meth:`latticedft._calibrate.Calibration.candidates_ratio`); *check cost* the runner-up trial's serves over the
model's, summed over the test fields (none without a runner-up). *cost* is the time of selection plus calibration
over selection alone. A failed calibration (no held-out slice served: :attr:`Calibration.failed`) gives no single
band and leaves the ensemble's raw spread, as a case serves it. ``--quick``: one small case
(cases/oscillator-sin, clean) for the structure.
"""

from __future__ import annotations

import copy
import json
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

import latticedft as ldft
from latticedft import systems
from latticedft._calibrate import (
    Calibration,
    calibrate,
    candidates_disagreement,
    runner_up,
    served_along,
    trial_keywords,
)
from latticedft._learn._noise import denoised_start
from latticedft._select import _build, select

from ._common import Check, Config, Table

NAME = "calibration"
TITLE = "Calibrated error bars: 2-sigma coverage and std/error of the served error, single model and ensemble"
ROOT = Path(__file__).resolve().parent.parent
CASES = ("oscillator-sin", "oscillator-wells", "wave", "klein-gordon-periodic", "sine-gordon", "wave-2d", "kepler")
NOISE = 1e-3
MEMBERS = 5
#: A test field the single band covers on less than this share of its served slices is missed (the table's
#: "silent misses": those without a calibration warning).
MISSED = 0.5


@dataclass
class Setup:
    """One row's data: training fields, test fields (initial data, clean reference, slices, boundary)."""

    label: str
    train: list[xr.DataArray]
    tests: list[tuple[xr.DataArray, xr.DataArray, int, Any]]
    model: Callable[[], ldft.AbstractLagrangian]
    boundary: Any = None
    learn: dict[str, Any] = field(default_factory=dict)
    select: bool = True
    ensemble: bool = True


def _case(name: str, tmp: Path) -> Setup:
    """A repository case from a temporary copy (its data made when not committed)."""
    from latticedft._case import load_case
    from latticedft._run import check_case

    folder = tmp / name
    shutil.copytree(ROOT / "cases" / name, folder, ignore=shutil.ignore_patterns("results*"))
    if not any((folder / "data").glob("*.nc")) or name in ("klein-gordon-periodic", "sine-gordon", "wave-2d"):
        subprocess.run([sys.executable, "make_data.py"], cwd=folder, check=True, capture_output=True)
    case = load_case(folder)
    data = check_case(case)
    tests = [(td.init, td.reference, td.slices, td.task.boundary) for td in data.tasks if td.reference is not None]
    kw = {k: v for k, v in case.train.learn.items() if k not in ("symmetries",)}
    mlp = case.model.kind == "mlp"
    return Setup(
        name,
        data.train,
        tests,
        lambda: case.model.build(len(data.dims)),
        case.train.boundary,
        kw,
        not mlp,
        not mlp,
    )


def _string(force: Callable[[np.ndarray], np.ndarray], nt: int) -> Callable[[list[tuple[int, float]]], xr.DataArray]:
    def make(modes: list[tuple[int, float]]) -> xr.DataArray:
        x = np.linspace(0.0, 1.0, 41)
        u0 = sum(a * np.sin(np.pi * m * x) for m, a in modes)
        u = systems.leapfrog(u0, u0.copy(), nt - 1, 0.0125, 0.025, force=force)
        return systems.make_field(u, ("t", "x"), spacing=(0.0125, 0.025))

    return make


def _extra() -> list[Setup]:
    """The oscillators and fields of the calibration targets' table."""
    from .noise import SYSTEMS

    out = []
    duff = SYSTEMS["duffing"]
    tests = [(f, f, 51, None) for f in duff.test()]
    out.append(Setup("double-well Duffing (4, 8), both wells", duff.train(), tests, duff.model))
    for label, force in (
        ("phi^4 string (2, 4)", lambda u: u - u**3),
        ("nonlinear Klein-Gordon string (2, 4)", lambda u: -u - u**3),
    ):
        train = [_string(force, 121)(m) for m in ([(1, 0.6)], [(2, 0.4), (3, 0.2)], [(1, 0.3), (3, 0.3)])]
        test = _string(force, 201)([(1, 0.45), (2, 0.25)])
        out.append(
            Setup(
                label, train, [(test, test, 201, "dirichlet")], lambda: ldft.PolynomialLagrangian((2, 4)), "dirichlet"
            )
        )
    kep = SYSTEMS["kepler"]
    out.append(
        Setup(
            "Kepler, bound launches (radial MLP)",
            kep.train(),
            [(f, f, f.sizes["t"], None) for f in kep.test()],
            kep.model,
            learn={},
            select=False,
            ensemble=False,
        )
    )
    return out


def _noisy(f: xr.DataArray, sigma: float, rng: np.random.Generator) -> xr.DataArray:
    return f + sigma * float(abs(f).max()) * rng.standard_normal(f.shape) if sigma else f


def _serve(model: ldft.AbstractLagrangian, init: xr.DataArray, slices: int, boundary: Any) -> Any:
    try:
        return ldft.serve(model, init, slices=slices, boundary=boundary, progress=False)
    except ldft.ServeError as err:
        return err.result


def _rms(a: np.ndarray, n: int) -> np.ndarray:
    return np.sqrt(np.mean(np.asarray(a[:n], dtype=np.float64).reshape(n, -1) ** 2, axis=1))


@dataclass
class _Pool:
    """Per-slice errors and bands pooled over a row's test fields."""

    err: list[np.ndarray] = field(default_factory=list)
    bands: dict[str, list[np.ndarray]] = field(default_factory=dict)
    #: Per test field: its served slices, value range, amplitude, the candidates' ratio, the calibration's warnings
    #: and the seconds of the model's serve and of the runner-up trial's (``--record``).
    facts: list[dict[str, Any]] = field(default_factory=list)

    def add(self, err: np.ndarray, **bands: np.ndarray) -> None:
        self.err.append(err[2:])
        for k, v in bands.items():
            self.bands.setdefault(k, []).append(v[2:])

    def score(self, name: str) -> tuple[float, float] | tuple[None, None]:
        if name not in self.bands:
            return None, None
        e, b = np.concatenate(self.err), np.concatenate(self.bands[name])
        ok = np.isfinite(e)
        b = np.where(np.isfinite(b), b, 0.0)
        return float(np.mean(e[ok] <= 2 * b[ok])), float(b[ok].mean() / max(e[ok].mean(), 1e-300))

    def silent(self) -> int:
        """The test fields the single band missed (2 std covers less than :data:`MISSED` of their served slices)
        without a calibration warning (:attr:`facts`' ``warnings``, the candidates' warning included)."""
        out = 0
        for i, e in enumerate(self.err):
            b = np.where(np.isfinite(self.bands["single"][i]), self.bands["single"][i], 0.0)
            ok = np.isfinite(e)
            covered = float(np.mean(e[ok] <= 2 * b[ok])) if ok.any() else 0.0
            out += covered < MISSED and not self.facts[i]["warnings"]
        return out

    def check_cost(self) -> float | None:
        """The runner-up trial's serves over the model's, summed over the test fields (None without a runner-up:
        the candidates' check costs nothing then)."""
        runner = [f["runner_s"] for f in self.facts if f.get("runner_s") is not None]
        served = sum(f["serve_s"] for f in self.facts if f.get("runner_s") is not None)
        return sum(runner) / served if runner and served > 0 else None


def _learned(s: Setup, train: list[xr.DataArray], kw: dict[str, Any]) -> tuple[Any, Any, float, float]:
    """(chosen model, (its fresh copy, its learn keywords, the runner-up, the two as selection learned them on
    the held-in slices and the fields they served when scored, None without selection, the chosen candidate's
    label), selection time, its wall time)."""
    if not s.select:
        model = s.model()
        t0 = time.perf_counter()
        ldft.learn(model, train, boundary=s.boundary, progress=False, **kw)
        own = trial_keywords(kw, model.report_.ridge if model.report_ is not None else None)
        return model, (s.model(), own, None, None, None, None), 0.0, time.perf_counter() - t0
    t0 = time.perf_counter()
    sel = select(s.model(), train, "auto", boundary=s.boundary, **kw)
    t_sel = time.perf_counter() - t0
    rows, chosen = sel.rows, sel.chosen
    hand = s.model()
    fresh = _build(hand, rows[chosen]["kind"], dict(rows[chosen]["options"]))
    own = {**kw, "ridge": rows[chosen]["ridge"]}
    runner, second, theirs = None, None, None
    i = runner_up(rows, chosen)
    if i is not None:
        r = rows[i]
        runner = (_build(hand, r["kind"], dict(r["options"])), {**kw, "ridge": r["ridge"]}, r["label"])
        second, theirs = sel.trials[i], sel.served[i]
    learned = (sel.trials[chosen], second) if sel.trials[chosen] is not None else None
    label = rows[chosen]["label"]
    return sel.model, (fresh, own, runner, learned, (sel.served[chosen], theirs), label), t_sel, t_sel


def measure(s: Setup, sigma: float) -> list[Any]:
    """One table row of setup ``s`` at noise ``sigma`` (noisy fields on a space-time lattice: no selection, each
    of its candidates would repeat the noise correction)."""
    rng = np.random.default_rng(0)
    train = [_noisy(f, sigma, rng) for f in s.train]
    kw = {**s.learn, **({"noise": "auto"} if sigma else {})}
    if sigma and s.train[0].ndim > 1:
        s = copy.copy(s)
        s.select = False
    if s.ensemble and not s.select:  # member 0 is the single model: learned once (a noisy fit corrects once)
        ens = ldft.EnsembleLagrangian(s.model(), members=MEMBERS, seed=0)
        ldft.learn(ens, train, boundary=s.boundary, progress=False, **kw)
        model, fresh, runner, learned, served, t_sel = ens.member(0), s.model(), None, None, None, 0.0
        own, label = trial_keywords(kw, model.report_.ridge if model.report_ is not None else None), None
    else:
        model, (fresh, own, runner, learned, served, label), t_sel, _ = _learned(s, train, kw)
        ens = None
        if s.ensemble:
            ens = ldft.EnsembleLagrangian(copy.deepcopy(fresh), members=MEMBERS, seed=0)
            ldft.learn(ens, train, boundary=s.boundary, progress=False, **own)
    t0 = time.perf_counter()
    held: list[dict[str, Any]] = []
    second: list[ldft.AbstractLagrangian] = []
    cal, _, trial = calibrate(
        fresh,
        train,
        boundary=s.boundary,
        runner_up=runner,
        ensemble_model=ens,
        record=held,
        learned=learned,
        served=served,
        chosen=label,
        runner_trial=second,
        **own,
    )
    t_cal = time.perf_counter() - t0
    pool = _Pool()
    pair = (trial, second[0] if second else None)
    for init, ref, slices, boundary in s.tests:
        _serve_test(pool, model, ens, pair, cal, _noisy(init, sigma, rng), ref, slices, boundary)
    single, ensemble, raw, law = (pool.score(k) for k in ("single", "ensemble", "raw", "law"))
    if cal.failed is not None:  # no law: served as a case is, without psi_err_est, the ensemble's spread as it is
        single, law, ensemble = (None, None), (None, None), raw
    cost = (t_sel + t_cal) / t_sel if t_sel else None
    if "record" in ONLY:
        _record(ONLY["record"], s.label, sigma, cal, pool, held)
    return [
        s.label,
        sigma,
        len(s.tests),
        int(sum(e.size for e in pool.err)),
        *single,
        *ensemble,
        *raw,
        *law,
        pool.silent() if cal.failed is None else None,
        pool.check_cost(),
        cal.coverage if cal.failed is None else None,
        t_sel if t_sel else None,
        t_cal,
        cost,
    ]


def _record(
    path: str, label: str, sigma: float, cal: Calibration, pool: _Pool, held: list[dict[str, Any]] | None = None
) -> None:
    """Append one row's per-slice record to the JSON file ``path`` (``--record``): the law, the trial's held-out
    samples (``held``, as :func:`latticedft._calibrate.calibrate` records them), and per test field (the two
    given slices excluded) the RMS error and every band (``trial``: the trial's disagreement), the served field's
    slices, value range (``low``, ``high``) and largest magnitude (``amplitude``), the calibration's
    ``warnings`` on it (:meth:`latticedft._calibrate.Calibration.warnings`, and the candidates' warning), the
    ``candidates_ratio`` (None without a runner-up) and the seconds of the model's serve and of the runner-up
    trial's (``serve_s``, ``runner_s``)."""
    file = Path(path)
    rows = json.loads(file.read_text()) if file.exists() else []
    tests = [
        {
            "error": e.tolist(),
            **{k: v[i].tolist() for k, v in pool.bands.items() if i < len(v)},
            **(pool.facts[i] if i < len(pool.facts) else {}),
        }
        for i, e in enumerate(pool.err)
    ]
    rows.append({"row": label, "noise": sigma, "law": cal.to_dict(), "held_out": held or [], "tests": tests})
    file.write_text(json.dumps(rows))


def _serve_test(
    pool: _Pool,
    model: Any,
    ens: Any,
    pair: tuple[Any, Any],
    cal: Calibration,
    init: xr.DataArray,
    ref: xr.DataArray,
    slices: int,
    boundary: Any,
) -> None:
    """Serve one test field with the single model (and the ensemble); pool its errors and bands. ``pair``: the
    trial and the runner-up's trial (None without one), served from the same start: their disagreement's
    :meth:`~latticedft._calibrate.Calibration.candidates_ratio` and warning."""
    noise = (model.report_.noise if model.report_ is not None else None) or {}
    start = denoised_start(model, init) if noise.get("method", "none") != "none" else init
    t0 = time.perf_counter()
    out = _serve(model, start, slices, boundary)
    serve_s = time.perf_counter() - t0
    pred = out.field
    n = min(pred.sizes[pred.dims[0]], ref.sizes[ref.dims[0]])
    err = _rms(np.asarray(pred.values) - np.asarray(ref.values[:n] if n else ref.values), n)
    values = np.asarray(pred.values, dtype=np.float64)
    amplitude = float(np.nanmax(np.abs(values)))
    mine = served_along(pair[0], start, pred, slices=slices, boundary=boundary)
    nt = pred.sizes[pred.dims[0]]
    other = candidates_disagreement(values, mine, nt)[:n]  # disagreement(): the trial's with the served field
    law = cal.estimate(np.arange(n), amplitude)
    est = np.fmax(law, other)
    bands = {"single": est, "law": law, "trial": other}
    finite = values[np.isfinite(values)]
    ratio, warnings, runner_s = None, cal.warnings(n, values) if cal.failed is None else [], None
    if pair[1] is not None and cal.failed is None:
        t0 = time.perf_counter()
        theirs = served_along(pair[1], start, pred, slices=slices, boundary=boundary)
        runner_s = time.perf_counter() - t0
        ratio = cal.candidates_ratio(candidates_disagreement(mine, theirs, nt) / amplitude, np.arange(nt))
        warning = cal.candidates_warning(ratio, min(nt, cal.slices) - 2)
        warnings += [warning] if warning else []
    pool.facts.append(
        {
            "slices": n,
            "low": float(finite.min()) if finite.size else None,
            "high": float(finite.max()) if finite.size else None,
            "amplitude": amplitude,
            "candidates_ratio": ratio,
            "warnings": warnings,
            "serve_s": serve_s,
            "runner_s": runner_s,
        }
    )
    if ens is not None:
        res = _serve(ens, start, slices, boundary)
        if res.std is not None and res.field.sizes[res.field.dims[0]] >= n:
            std = np.asarray(res.std.values, dtype=np.float64)
            bands["raw"] = _rms(std, n)
            bands["ensemble"] = _rms(np.asarray(cal.band(res.std[:n], est, other).values), n)
    pool.add(err, **bands)


def run(cfg: Config) -> Table:
    table = Table(
        NAME,
        TITLE,
        [
            "row",
            "noise",
            "tests",
            "slices",
            "coverage, single",
            "std/error, single",
            "coverage, ensemble",
            "std/error, ensemble",
            "coverage, raw ensemble",
            "std/error, raw ensemble",
            "coverage, law only",
            "std/error, law only",
            "silent misses",
            "check cost",
            "held-out coverage",
            "selection (s)",
            "calibration (s)",
            "cost",
        ],
    )
    with tempfile.TemporaryDirectory() as tmp:
        names = ("oscillator-sin",) if cfg.quick else tuple(c for c in ONLY.get("cases", CASES) if c)
        setups = [_case(c, Path(tmp)) for c in names]
        sigmas = (0.0,) if cfg.quick else ONLY.get("sigmas", (0.0, NOISE))
        keep = ONLY.get("extra", "")
        extra = [] if cfg.quick or keep is False else [(s, 0.0) for s in _extra() if keep in s.label]
        rows = [(s, sg) for s in setups for sg in sigmas] + extra
        for s, sigma in rows:
            try:
                table.rows.append(measure(s, sigma))
            except Exception as exc:  # noqa: BLE001 - a row that fails is reported, the others still run
                failed = f"failed: {type(exc).__name__}: {exc}"[:120]
                table.rows.append([s.label, sigma, len(s.tests), failed] + [None] * (len(table.columns) - 4))
            print(" | ".join(str(c) for c in table.rows[-1]), flush=True)
    _checks(table)
    table.notes.append(__doc__.split("\n\n", 2)[2].replace("\n", " ") if __doc__ else "")
    return table


def _checks(table: Table) -> None:
    """The targets, row by row: coverage in [80, 99] %, std/error in [0.5, 2] (single and ensemble); cost <= 1.5."""
    full = [r for r in table.rows if not str(r[3]).startswith("failed")]
    for kind, c, q in (("single", 4, 5), ("ensemble", 6, 7)):
        met = [r[0] + f" ({r[1]:g})" for r in full if r[c] is not None and 0.8 <= r[c] <= 0.99 and 0.5 <= r[q] <= 2]
        runs = [r for r in full if r[c] is not None]
        table.checks.append(
            Check(
                f"{kind}: 2-sigma coverage 80-99 % and std/error 0.5-2",
                f"{len(met)} of {len(runs)} rows" + (f": {', '.join(met)}" if met else ""),
                bool(runs) and len(met) == len(runs),
            )
        )
    costs = [r[-1] for r in full if r[-1] is not None]
    table.checks.append(
        Check(
            "cost of calibration <= 1.5x selection alone",
            f"{sum(c <= 1.5 for c in costs)} of {len(costs)} rows (max {max(costs, default=0):.2f}x)",
            bool(costs) and max(costs) <= 1.5,
        )
    )


#: A part of the table (``--cases``, ``--sigmas``, ``--no-extra`` when run alone): the full table is the union.
ONLY: dict[str, Any] = {}


def _part(argv: list[str]) -> list[str]:
    """Take ``--cases A,B``, ``--sigmas S,S``, ``--no-extra``, ``--extra TEXT`` (the extra rows whose label
    holds it) and ``--record FILE`` (per-slice errors and bands appended to a JSON file, :func:`_record`) out of
    ``argv`` into :data:`ONLY`."""
    rest = []
    it = iter(argv)
    for a in it:
        if a == "--cases":
            ONLY["cases"] = tuple(c for c in next(it).split(",") if c)
        elif a == "--sigmas":
            ONLY["sigmas"] = tuple(float(x) for x in next(it).split(","))
        elif a == "--no-extra":
            ONLY["extra"] = False
        elif a == "--extra":
            ONLY["extra"] = next(it)
        elif a == "--record":
            ONLY["record"] = next(it)
        else:
            rest.append(a)
    return rest


if __name__ == "__main__":
    from ._common import run_alone

    sys.exit(run_alone(run, __doc__, _part(sys.argv[1:])))
