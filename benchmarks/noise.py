"""Noisy data: served error against the noise level, latticedft plain and noise-aware, and PySINDy.

    python -m benchmarks.noise [SYSTEM ...] [--sigmas S,S,...] [--seeds N] [--ratios]

SYSTEM is any of ``duffing``, ``sin``, ``wells``, ``kepler``, ``kepler-coarse``, ``wave`` (default: all).
``kepler`` learns the radial MLP of ``cases/kepler`` from three of its planets' orbits (Venus, Earth, Mars) at the
case's sampling, dt = 0.05, and serves two of its Earth launches (``earth_0.98`` inside the training radii,
``earth_1.13`` reaching outside) for one period; ``kepler-coarse`` does the same sampled at dt = 0.2. Every
system's training fields and test fields get Gaussian noise of standard deviation ``sigma`` times each field's
amplitude (its largest ``|psi|``; seeded). Columns: the sigma estimated from the noisy training data; latticedft
plain (learned from the noisy data, served from the first two noisy slices); latticedft noise-aware
(``noise="auto"``, served from the first two slices of ``denoise`` of the first 20 noisy slices, as ``[[serve]]
start = "denoised"`` does); PySINDy (oscillators only; "inf" when its simulation diverges: the state ``(q, q')``
with ``q'`` by 4th-order differences of the noisy samples, a cubic polynomial library, STLSQ; simulated from the
first noisy sample and its 4th-order derivative estimate over the same 20 samples). The error is the largest ``|psi
- psi_ref|`` over the test field (50 steps for the oscillators, 80 for the string, one period for the orbits)
relative to the amplitude, the worst over the test fields and seeds. PySINDy is optional (``pip install
latticedft[bench]``); without it its column says so. One noise level of one system took 40 to 220 s on a shared
two-core machine.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import xarray as xr
from scipy.integrate import solve_ivp

import latticedft as ldft
from latticedft import systems
from latticedft._learn._noise import DENOISE_SLICES, denoised_start

from ._common import Table, markdown

NAME = "noise"
TITLE = "Served error against the noise level: latticedft plain, noise-aware, and PySINDy on the same samples"
SIGMAS = (0.0, 1e-4, 1e-3, 1e-2)
DUFFING_H = 0.25


def duffing(q0: float, n: int) -> xr.DataArray:
    """The double-well Duffing oscillator ``q'' = q - q^3`` from rest at ``q0``, every 0.25 (DOP853)."""
    t = np.arange(n) * DUFFING_H
    sol = solve_ivp(
        lambda _, y: [y[1], y[0] - y[0] ** 3], (0, t[-1]), [q0, 0.0], method="DOP853", rtol=1e-12, atol=1e-12, t_eval=t
    )
    return systems.make_field(sol.y[0], ("t",), spacing=DUFFING_H)


@dataclass
class System:
    """A benchmark system: training and test fields (clean) and the model to learn."""

    label: str
    train: Callable[[], list[xr.DataArray]]
    test: Callable[[], list[xr.DataArray]]
    model: Callable[[], ldft.AbstractLagrangian]
    ode: bool  # PySINDy's comparison is set up (a scalar oscillator)


SYSTEMS = {
    "duffing": System(
        "double-well Duffing, h = 0.25, (4, 8)",
        lambda: [duffing(q, 161) for q in (0.6, 1.0, 1.3, 1.45, 1.6, 1.75)],
        lambda: [duffing(q, 51) for q in (1.35, 1.55)],
        lambda: ldft.PolynomialLagrangian(orders=(4, 8)),
        True,
    ),
    "sin": System(
        "paper Example 1, h = 1, (2, 6)",
        lambda: [systems.oscillator_sin(a, n=101) for a in (1.2, 0.9, 0.6, 0.3)],  # type: ignore[misc]
        lambda: [systems.oscillator_sin(a, n=51) for a in (-0.6, 0.8)],  # type: ignore[misc]
        lambda: ldft.PolynomialLagrangian(orders=(2, 6)),
        True,
    ),
    "wells": System(
        "paper Example 2, h = 1, (4, 8)",
        lambda: [systems.oscillator_wells(a, n=101) for a in (1.7, 1.6, 1.5, 1.4, 1.3, 1.2)],  # type: ignore[misc]
        lambda: [systems.oscillator_wells(1.55, n=51)],  # type: ignore[list-item]
        lambda: ldft.PolynomialLagrangian(orders=(4, 8)),
        True,
    ),
    **{
        name: System(
            f"Kepler, dt = {dt:g} (cases/kepler's Venus, Earth, Mars; radial MLP)",
            lambda dt=dt: [systems.planet_orbit(p, dt=dt) for p in ("Venus", "Earth", "Mars")],
            lambda dt=dt: [systems.kepler_orbit(1.0167, v, dt=dt) for v in (0.98, 1.13)],
            lambda: ldft.MLPLagrangian(preset="radial"),
            False,
        )
        for name, dt in (("kepler", 0.05), ("kepler-coarse", 0.2))
    },
    "wave": System(
        "wave string (cases/wave), (2, 2)",
        lambda: [systems.wave_string([(1, 1.0), (2, 0.5, 0.3), (3, 0.25, 1.0)], nx=41, nt=81)],
        lambda: [systems.wave_string([(1, 0.6, 0.5), (2, -0.4), (4, 0.15, 0.7)], nx=41, nt=81)],
        lambda: ldft.PolynomialLagrangian(orders=(2, 2)),
        False,
    ),
}


def _noisy(f: xr.DataArray, sigma: float, rng: np.random.Generator) -> xr.DataArray:
    return f + sigma * float(abs(f).max()) * rng.standard_normal(f.shape)


def _error(pred: np.ndarray, ref: xr.DataArray) -> float:
    n = min(len(pred), ref.sizes[ref.dims[0]])
    return float(np.abs(pred[:n] - ref.values[:n]).max() / np.abs(ref.values).max())


def _served(model: ldft.AbstractLagrangian, start: xr.DataArray, ref: xr.DataArray) -> float:
    try:
        out = ldft.serve(model, start, slices=ref.sizes[ref.dims[0]], progress=False).field
    except ldft.ServeError as err:  # a theory that cannot step on: the part solved, the rest counts as lost
        out = err.result.field
        if out.sizes[out.dims[0]] < ref.sizes[ref.dims[0]]:
            return float("inf")
    return _error(out.values, ref)


def _start_plain(f: xr.DataArray) -> xr.DataArray:
    """The first two slices, and for Dirichlet axes the boundary strips (the whole noisy field)."""
    return f if f.ndim > 1 else f.isel({f.dims[0]: slice(0, 2)})


def _pysindy(train: list[xr.DataArray], tests: list[xr.DataArray], refs: list[xr.DataArray]) -> float | str:
    try:
        import pysindy as ps
    except ImportError:
        return "pysindy not installed"
    h = float(train[0][train[0].dims[0]][1] - train[0][train[0].dims[0]][0])
    fd = ps.FiniteDifference(order=4)
    states = [np.stack([f.values, fd._differentiate(f.values, h)], axis=1) for f in train]
    model = ps.SINDy(
        optimizer=ps.STLSQ(threshold=1e-4), feature_library=ps.PolynomialLibrary(degree=3), differentiation_method=fd
    )
    model.fit(states, t=h)
    worst = 0.0
    for f, ref in zip(tests, refs, strict=True):
        window = f.values[:DENOISE_SLICES]
        x0 = [window[0], fd._differentiate(window, h)[0]]
        t = np.arange(ref.sizes[ref.dims[0]]) * h
        try:
            sim = model.simulate(x0, t)[:, 0]
        except Exception:  # noqa: BLE001 - a diverging simulation is a lost prediction
            return float("inf")
        worst = max(worst, _error(sim, ref) if len(sim) == len(t) else float("inf"))
    return worst


def run_system(name: str, sigmas: tuple[float, ...], seeds: int, table: Table) -> None:
    sysm = SYSTEMS[name]
    clean, refs = sysm.train(), sysm.test()
    for sigma in sigmas:
        t0 = time.perf_counter()
        worst = {"plain": 0.0, "aware": 0.0, "sindy": 0.0}
        est, applied, sindy_note = [], [], ""
        for seed in range(seeds):
            rng = np.random.default_rng(seed)
            train = [_noisy(f, sigma, rng) for f in clean]
            tests = [_noisy(f, sigma, rng) for f in refs]
            plain = sysm.model()
            ldft.learn(plain, train, progress=False)
            aware = sysm.model()
            rep = ldft.learn(aware, train, progress=False, noise="auto")
            assert rep.noise is not None
            est.append(rep.noise["relative"] if rep.noise["resolved"] else float("nan"))
            applied.append(rep.noise["method"] != "none")
            for f, ref in zip(tests, refs, strict=True):
                worst["plain"] = max(worst["plain"], _served(plain, _start_plain(f), ref))
                start = denoised_start(aware, f) if applied[-1] else f
                worst["aware"] = max(worst["aware"], _served(aware, _start_plain(start), ref))
            if sysm.ode:
                got = _pysindy(train, tests, refs)
                if isinstance(got, str):
                    sindy_note = got
                else:
                    worst["sindy"] = max(worst["sindy"], got)
        sindy = sindy_note or (worst["sindy"] if sysm.ode else "n/a (scalar oscillators only)")
        table.rows.append(
            [
                sysm.label,
                sigma,
                float(np.nanmax(est)) if not all(np.isnan(est)) else "unresolved",
                "yes" if all(applied) else ("no" if not any(applied) else "some seeds"),
                worst["plain"],
                worst["aware"],
                sindy,
                time.perf_counter() - t0,
            ]
        )
        print(" | ".join(str(c) for c in table.rows[-1]), flush=True)


def figure(path: str, sigma: float = 1e-3) -> None:
    """Error against time on the Duffing test field ``q0 = 1.55`` at ``sigma`` (seed 0): the three predictions."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sysm = SYSTEMS["duffing"]
    rng = np.random.default_rng(0)
    train = [_noisy(f, sigma, rng) for f in sysm.train()]
    refs = sysm.test()
    tests = [_noisy(f, sigma, rng) for f in refs]
    ref, test = refs[1], tests[1]
    plain, aware = sysm.model(), sysm.model()
    ldft.learn(plain, train, progress=False)
    ldft.learn(aware, train, progress=False, noise="auto")
    n = ref.sizes["t"]
    t = ref.t.values
    curves = {
        "latticedft plain": ldft.serve(plain, test.isel(t=slice(0, 2)), slices=n, progress=False).field.values,
        "latticedft noise-aware": ldft.serve(
            aware, denoised_start(aware, test).isel(t=slice(0, 2)), slices=n, progress=False
        ).field.values,
    }
    try:
        import pysindy as ps

        h = DUFFING_H
        fd = ps.FiniteDifference(order=4)
        model = ps.SINDy(
            optimizer=ps.STLSQ(threshold=1e-4),
            feature_library=ps.PolynomialLibrary(degree=3),
            differentiation_method=fd,
        )
        model.fit([np.stack([f.values, fd._differentiate(f.values, h)], axis=1) for f in train], t=h)
        window = test.values[:DENOISE_SLICES]
        curves["PySINDy"] = model.simulate([window[0], fd._differentiate(window, h)[0]], t)[:, 0]
    except ImportError:
        pass
    fig, ax = plt.subplots(figsize=(6, 3.2))
    amp = float(np.abs(ref.values).max())
    for label, q in curves.items():
        ax.semilogy(t, np.abs(q - ref.values) / amp + 1e-12, label=label)
    ax.axhline(10 * sigma, color="gray", ls="--", lw=0.8, label="10 sigma")
    ax.set_xlabel("t")
    ax.set_ylabel("|q - q_ref| / amplitude")
    ax.set_title(f"double-well Duffing, h = {DUFFING_H}, noise sigma = {sigma:g}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def ratios(names: list[str], sigmas: tuple[float, ...]) -> Table:
    """Per system and noise level (seed 0), the noise's share of the training data's second time differences
    (``NoiseEstimate.second_difference_ratio``), beside the level above which ``learn`` warns."""
    from latticedft._learn._noise import SECOND_DIFFERENCE_WARN

    table = Table(NAME, "Noise share of the second time differences (seed 0)", ["system", *map(str, sigmas)])
    for name in names:
        clean = SYSTEMS[name].train()
        row: list = [SYSTEMS[name].label]
        for sigma in sigmas:
            rng = np.random.default_rng(0)
            est = ldft.estimate_noise([_noisy(f, sigma, rng) for f in clean])
            share = est.second_difference_ratio
            row.append("unresolved" if share is None else share)
        table.rows.append(row)
    table.notes.append(f"learn(..., noise='auto'|'correct') warns above {SECOND_DIFFERENCE_WARN:g}.")
    return table


def held_out(names: list[str], sigmas: tuple[float, ...]) -> Table:
    """Per system and noise level (seed 0): the noise's share of the second differences, the noise-aware fit's
    held-out check (the worst relative RMS error of the calibration's trial on its held-out slices, and whether
    it warns) and the noise-aware error on the test fields (as in the main table)."""
    from latticedft._calibrate import NOISE_FAILED, calibrate

    table = Table(
        NAME,
        "The noise-aware fit's held-out check (seed 0)",
        ["system", "sigma", "share", "held-out check warns", "noise-aware test error"],
    )
    for name in names:
        sysm = SYSTEMS[name]
        for sigma in sigmas:
            rng = np.random.default_rng(0)
            train = [_noisy(f, sigma, rng) for f in sysm.train()]
            tests = [_noisy(f, sigma, rng) for f in sysm.test()]
            aware = sysm.model()
            rep = ldft.learn(aware, train, progress=False, noise="auto")
            _, warnings, _ = calibrate(sysm.model(), train, noise="auto")
            worst = 0.0
            for f, ref in zip(tests, sysm.test(), strict=True):
                start = denoised_start(aware, f) if (rep.noise or {}).get("method") != "none" else f
                worst = max(worst, _served(aware, _start_plain(start), ref))
            share = (rep.noise or {}).get("second_difference_ratio")
            table.rows.append([sysm.label, sigma, share, "yes" if warnings else "no", worst])
            print(" | ".join(str(c) for c in table.rows[-1]), flush=True)
    table.notes.append(f"The check warns when the trial's held-out error exceeds {NOISE_FAILED:g} or a serve stops.")
    return table


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.noise", description=__doc__.split("\n\n")[0])
    p.add_argument("systems", nargs="*", help=f"systems: {', '.join(SYSTEMS)} (default: all)")
    p.add_argument("--sigmas", default=",".join(str(s) for s in SIGMAS), help="noise levels (comma-separated)")
    p.add_argument("--seeds", type=int, default=1, help="noise realisations per level (the worst is reported)")
    p.add_argument("--figure", metavar="PNG", help="only draw the error-against-time figure of docs/noise.md")
    p.add_argument("--ratios", action="store_true", help="only the noise's share of the second differences")
    p.add_argument("--held-out", action="store_true", help="only the noise-aware fit's held-out check (calibration)")
    args = p.parse_args(argv)
    if args.figure:
        figure(args.figure)
        return 0
    unknown = [s for s in args.systems if s not in SYSTEMS]
    if unknown:
        p.error(f"unknown system {unknown[0]!r}: expected one of {', '.join(SYSTEMS)}")
    sigmas = tuple(float(s) for s in args.sigmas.split(","))
    if args.held_out:
        print(markdown(held_out(args.systems or list(SYSTEMS), tuple(s for s in sigmas if s > 0))))
        return 0
    if args.ratios:
        print(markdown(ratios(args.systems or list(SYSTEMS), tuple(s for s in sigmas if s > 0))))
        return 0
    table = Table(
        NAME,
        TITLE,
        ["system", "sigma", "sigma est.", "corrected", "plain", "noise-aware", "PySINDy", "seconds"],
    )
    for name in args.systems or list(SYSTEMS):
        run_system(name, sigmas, args.seeds, table)
    print(markdown(table))
    return 0


if __name__ == "__main__":
    sys.exit(main())
