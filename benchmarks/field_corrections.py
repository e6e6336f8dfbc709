"""Exact-step corrections on a field lattice: what the first-order stencil can hold, and what a fit finds.

    python -m benchmarks.field_corrections

On the nonlinear Klein-Gordon string of :mod:`benchmarks.discovery` (``psi_tt = psi_xx - psi - 0.3 psi^3``, fixed
ends, dx = 0.1, dt = 0.05, trained at ``|psi| <= 1.13``, served at amplitude 5.5), the data are the lattice
equation (three-point Laplacian) solved finely in time: the ODE system ``L = sum_x (psi_t^2/2 - (D_x psi)^2/2 -
V(psi))``. One step of its flow has the discrete Lagrangian (per ``h dx``, ``v = D_t psi``, ``g = D_x psi``)

    v^2/2 - g^2/2 - V - h^2/24 V'^2 + h^2/12 V'' (v^2 - g^2) - h^2/24 (Lap psi)^2 + h^2/12 (D_x v)^2 + O(h^4)

(the cross term ``-2 V' Lap psi`` summed by parts into ``2 V'' g^2``). The first-order cell ``(0, 0), (1, 0),
(0, 1)`` holds the first line, not the last two terms. Printed:

- the share of the unheld term in the leapfrog's truncation, field by field: the rms of ``Lap^2 psi`` over that of
  ``psi_tttt`` (fourth differences of the samples; ``dt^2/12`` times each is the DEL's part);
- the true terms and the representable corrections with their exact-step coefficients, set by hand (the
  ceiling on this stencil), and the corrections computed from the true terms as fitted on the samples;
- on the string, sine-Gordon 1+1D and phi^4 1+1D, correction libraries fitted on the training samples (threshold 1e-5,
  as the exact-step candidates of a time-only lattice): the served error and its ratio to the leapfrog, the
  held-out score of selection, the coefficients, and the terms kept on the variational data (where the
  corrections must drop out).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np
import torch
import xarray as xr

import latticedft as ldft
from latticedft._learn._heldout import HOLD_OUT, held_in, held_out_score
from latticedft._models._library import Library
from latticedft._models._terms import Family, Term, Vars
from latticedft._stencil import Stencil

from . import _discovery_systems as systems_mod
from .discovery import served

#: The libraries fitted (the corrections of a quartic potential, then with the gradient's, then with the quartic
#: products of the derivatives, then the corrections' Lorentz-invariant combination ``(v^2 - g^2) q^k``).
LIBRARIES: tuple[str, ...] = (
    "kinetic + gradient + poly:4",
    "kinetic + gradient + poly:4 + kinetic*poly:2",
    "kinetic + gradient + poly:4 + kinetic*poly:2 + gradient*poly:2",
    "kinetic + gradient + poly:6 + kinetic*poly:2 + gradient*poly:2",
    "kinetic + gradient + poly:4 + kinetic*poly:2 + gradient*poly:2 + kinetic*kinetic + gradient*gradient"
    " + kinetic*gradient",
    "kinetic + gradient + poly:4 + wave*poly:2",
)
#: On sine-Gordon 1+1D and phi^4 1+1D: the true terms, then with the held corrections of their potentials (for
#: ``V = 1 - cos q``: ``V'^2`` in ``trig:2``, ``V'' (v^2 - g^2)`` in ``kinetic*trig:1`` and ``gradient*trig:1``).
PERIODIC: dict[str, tuple[str, ...]] = {
    "sine-gordon-1d": ("kinetic + gradient + trig:1", "kinetic + gradient + trig:2 + kinetic*trig:1 + gradient*trig:1"),
    "phi4-1d": ("kinetic + gradient + poly:4", "kinetic + gradient + poly:6 + kinetic*poly:2 + gradient*poly:2"),
}
THRESHOLD = 1e-5


def _wave_value(v: Vars) -> Any:
    return v.d[0][0] ** 2 - v.d[1][0] ** 2


#: ``(D_t q)^2 - (D_x q)^2`` on a 1+1D scalar lattice (this benchmark's own term).
WAVE = Family("wave", lambda n, m: [Term("(Dtq**2-Dxq**2)", _wave_value)], saveable=False)


def _library(spec: str) -> Library:
    parts = [p.strip() for p in spec.split("+")]
    out = Library.parse([p for p in parts if "wave" not in p])
    if any(p == "wave*poly:2" for p in parts):
        out = out + Library([WAVE]) * "poly:2"
    return out


def unheld_share(field: xr.DataArray, periodic: bool) -> float:
    """rms of ``Lap^2 psi`` over rms of ``psi_tttt`` (interior sites and slices)."""
    p = np.asarray(field.values, dtype=float)
    dt, dx = float(field.t[1] - field.t[0]), float(field.x[1] - field.x[0])

    def lap(a: np.ndarray) -> np.ndarray:
        if periodic:
            return (np.roll(a, 1, -1) - 2 * a + np.roll(a, -1, -1)) / dx**2
        out = np.zeros_like(a)
        out[..., 1:-1] = (a[..., 2:] - 2 * a[..., 1:-1] + a[..., :-2]) / dx**2
        return out

    space = slice(None) if periodic else slice(2, -2)
    l2 = lap(lap(p))[2:-2, space]
    d4 = ((p[4:] - 4 * p[3:-1] + 6 * p[2:-2] - 4 * p[1:-3] + p[:-4]) / dt**4)[:, space]
    return float(np.sqrt(np.mean(l2**2) / np.mean(d4**2)))


def exact_step(
    h: float, c2: float = -0.5, c4: float = -0.075, cx: float = -0.5, gradient: bool = True
) -> dict[str, float]:
    """The exact-step coefficients of the held terms for ``L = v^2/2 + cx g^2 + c2 q^2 + c4 q^4`` (per ``h dx``;
    the string: ``c2 = -1/2``, ``c4 = -0.075``): ``V' = -(2 c2 q + 4 c4 q^3)``, ``V'' = -(2 c2 + 12 c4 q^2)``."""
    a, b = h * h / 24, h * h / 12
    out = {"Dtq**2": 0.5 - 2 * c2 * b, "Dxq**2": cx + 2 * c2 * b, "q**2": c2 - 4 * a * c2**2}
    out |= {"q**4": c4 - 16 * a * c2 * c4, "q**6": -16 * a * c4**2, "Dtq**2*q**2": -12 * c4 * b}
    if gradient:
        out["Dxq**2*q**2"] = 12 * c4 * b
    return out


def _error(model: ldft.SparseLagrangian, system: systems_mod.System, ref: np.ndarray) -> float:
    return systems_mod.max_errors(served(model, system), ref, system.slices)[0]


def _fit(
    spec: str, fields: list[xr.DataArray], system: systems_mod.System, threshold: float, at: str = "anchor"
) -> ldft.SparseLagrangian:
    model = ldft.SparseLagrangian(_library(spec), threshold=threshold, bags=0, at=at, stencil=Stencil.first_order(2))
    ldft.learn(model, fields, boundary=system.boundary, progress=False)
    return model


def rows() -> list[str]:
    """The lines of the benchmark."""
    system = systems_mod.build("nlkg-string")
    ref = np.asarray(system.test.values, dtype=float)
    leap = systems_mod.max_errors(system.leapfrog(system.test, system.slices), ref, system.slices)[0]
    shares = [f"train {i}: {unheld_share(f, False):.2f}" for i, f in enumerate(system.train)]
    out = [f"{system.name}: leapfrog of the true equation {leap:.3e}"]
    out.append(f"  rms(Lap^2 psi) / rms(psi_tttt): {'; '.join(shares)}; test: {unheld_share(system.test, False):.2f}")
    h = float(system.test.t[1] - system.test.t[0])
    full = LIBRARIES[3]
    true = _fit(LIBRARIES[0], system.train, system, THRESHOLD)
    own = {k: c / (2 * true.coef[0].item()) for k, c in zip(true.term_names, true.coef.tolist())}
    hand = {"true terms": {"Dtq**2": 0.5, "Dxq**2": -0.5, "q**2": -0.5, "q**4": -0.075}}
    hand |= {"exact-step held terms": exact_step(h), "the same without Dxq**2*q**2": exact_step(h, gradient=False)}
    hand |= {"fitted true terms + their held": exact_step(h, own["q**2"], own["q**4"], own["Dxq**2"])}
    step = {k: float(f"{c:.4g}") for k, c in hand["exact-step held terms"].items()}
    out.append(f"  exact-step coefficients of the held terms: {step}")
    for label, coef in hand.items():
        model = _fit(full, system.train, system, 0.0)
        model.coef.data.copy_(torch.tensor([coef.get(t, 0.0) for t in model.term_names], dtype=model.coef.dtype))
        e = _error(model, system, ref)
        out.append(f"  set by hand, {label:30s} served {e:.3e} ({e / leap:.3f}x)")
    return out + fitted(system, LIBRARIES, ("anchor",))


def fitted(system: systems_mod.System, libraries: tuple[str, ...], ats: tuple[str, ...]) -> list[str]:
    """Each library fitted on the training samples at :data:`THRESHOLD`: served error and ratio, held-out score,
    coefficients, and the terms kept on the variational data."""
    ref = np.asarray(system.test.values, dtype=float)
    leap = systems_mod.max_errors(system.leapfrog(system.test, system.slices), ref, system.slices)[0]
    variational = systems_mod.variational_data(system)
    out = []
    for spec in libraries:
        for at in ats:
            model = _fit(spec, system.train, system, THRESHOLD, at)
            e = _error(model, system, ref)
            trial = _fit(spec, held_in(system.train, HOLD_OUT), system, THRESHOLD, at)
            score = held_out_score(trial, system.train, system.boundary)
            kept = {k: float(f"{c:.4g}") for k, c in zip(model.term_names, model.coef.tolist()) if c}
            on_var = _fit(spec, variational, system, THRESHOLD, at).kept_terms()
            out.append(f"  fitted {spec} (at = {at!r})")
            out.append(f"      served {e:.3e} ({e / leap:.3f}x), held-out score {score:.3e}; {kept}")
            out.append(f"      on the variational data: {on_var}")
    return out


def periodic_rows(name: str, libraries: tuple[str, ...]) -> list[str]:
    """A periodic system of :mod:`benchmarks.discovery` (``sine-gordon-1d``, ``phi4-1d``): the share of the unheld
    term, then ``libraries`` fitted at the anchor and in the trapezoid rule (``at = "average"``)."""
    system = systems_mod.build(name)
    ref = np.asarray(system.test.values, dtype=float)
    leap = systems_mod.max_errors(system.leapfrog(system.test, system.slices), ref, system.slices)[0]
    shares = [f"train {i}: {unheld_share(f, True):.2f}" for i, f in enumerate(system.train)]
    out = [f"{system.name}: leapfrog of the true equation {leap:.3e}"]
    out.append(f"  rms(Lap^2 psi) / rms(psi_tttt): {'; '.join(shares)}; test: {unheld_share(system.test, True):.2f}")
    return out + fitted(system, libraries, ("anchor", "average"))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.field_corrections", description=__doc__.split("\n\n")[0])
    p.parse_args(argv)
    print("\n".join(rows()), flush=True)
    for name, libraries in PERIODIC.items():
        print("\n".join(periodic_rows(name, libraries)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
