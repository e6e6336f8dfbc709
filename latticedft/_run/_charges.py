"""Noether charges in a case run: ``[[serve]] charges`` checked against a task's lattice and measured along it.

* :func:`check_charges`: the names of a task's ``charges`` (at ``check``: one-line errors with the closest
  name);
* :func:`task_charges`: the charges and the discrete energy along a served field (``ldft.noether_charges``),
  as variables ``charge_<name>(t)`` and ``energy(t)`` of the task file and their drifts in the task's record;
* :func:`drift_text`: those drifts for the task's log line.

The names are those of :func:`latticedft.builtin_symmetries` that have a charge (continuous), ``"energy"``
(the discrete energy) and ``"auto"`` (every continuous built-in symmetry that :func:`latticedft.symmetries`
finds exact for the learned ``L_d`` on the served field). See docs/symmetries.md.
"""

from __future__ import annotations

import difflib
import logging
from typing import Any

import numpy as np
import xarray as xr

from .._case import ServeTask
from .._contract import AbstractLagrangian, GaugeName
from .._errors import ConfigError, LatticeDFTError
from .._lattice import LatticeField, as_lattice_field
from .._noether import noether_charges, symmetries
from .._noether._group import Symmetry, standard_symmetries
from ._record import TaskRecord

__all__ = ["AUTO", "ENERGY", "charge_names", "charge_variable", "check_charges", "drift_text", "task_charges"]

log = logging.getLogger("latticedft")

AUTO = "auto"
ENERGY = "energy"


def _continuous(f: LatticeField, periodic: tuple[bool, ...] | None = None) -> list[Symmetry]:
    per = f.periodic if periodic is None else periodic
    return [s for s in standard_symmetries(f.ndim, f.ncomp, per, f.dims, f.components) if s.continuous]


def charge_names(f: LatticeField) -> list[str]:
    """The names a task on the lattice of ``f`` may list: ``auto``, ``energy`` and its continuous symmetries."""
    return [AUTO, ENERGY] + [s.name for s in _continuous(f)]


def charge_variable(name: str) -> str:
    """The task file's variable of a charge: ``energy``, or ``charge_<name>`` with ``-`` as ``_`` (CF names)."""
    return ENERGY if name == ENERGY else "charge_" + name.replace("-", "_")


def check_charges(charges: tuple[str, ...], f: LatticeField, key: str) -> None:
    """Raise a one-line ConfigError (``case.toml: <key>: ...``) unless every name is a charge of ``f``'s lattice."""
    valid = charge_names(f)
    every = standard_symmetries(f.ndim, f.ncomp, f.periodic, f.dims, f.components)
    # the momenta the task would have if its spatial axes were periodic
    momenta = {
        s.name: s.axis
        for s in _continuous(f, (False,) + (True,) * (f.ndim - 1))
        if s.axis is not None and s.name not in valid
    }

    def bad(problem: str) -> ConfigError:
        return ConfigError(f"case.toml: {key}: {problem}", key=key, problem=problem)

    listing = f"(this task's charges: {', '.join(valid)})"
    for i, name in enumerate(charges):
        if name in charges[:i]:
            raise bad(f"{name!r} listed twice")
        if name in valid:
            continue
        discrete = next((s for s in every if s.name == name and not s.continuous), None)
        if discrete is not None:
            raise bad(f"{name!r} is a discrete symmetry and has no Noether charge {listing}")
        if name in momenta:
            axis = f.dims[int(momenta[name])]
            raise bad(
                f"{name!r} needs a periodic axis {axis!r}; this task's boundary along {axis!r} is "
                f'{f.boundary[int(momenta[name])]} (set boundary = {{{axis} = "periodic"}} or drop it) {listing}'
            )
        match = difflib.get_close_matches(name, valid, n=1, cutoff=0.5)
        hint = f"; did you mean {match[0]!r}?" if match else ""
        raise bad(f"unknown charge {name!r}{hint} {listing}")


# -- units ----------------------------------------------------------------------------------------------------
def _units(pred: xr.DataArray, sym: Symmetry | None, gauge: GaugeName | None) -> str | None:
    """Units of a charge (``sym``) or of the energy (``None``) when the field and its coordinates have units.

    In the unit-mass (and trace) gauge ``L_d`` is a Lagrangian per unit mass: ``[psi]^2 / [t]^2`` per unit
    spatial volume; the energy has the units of ``L_s`` and a charge those of ``P . xi``.
    """
    if gauge not in (GaugeName.UNIT_MASS, GaugeName.TRACE):
        return None
    tdim, space = pred.dims[0], [d for d in pred.dims[1:] if d != "component"]
    psi = pred.attrs.get("units")
    found = [pred[d].attrs.get("units") if d in pred.coords else None for d in (tdim, *space)]
    if not psi or not all(found):
        return None
    coords = [str(u) for u in found]
    exps: dict[str, int] = {}

    def add(unit: str, e: int) -> None:
        if unit != "1":  # dimensionless
            exps[unit] = exps.get(unit, 0) + e

    add(psi, 2)
    add(coords[0], -2 if sym is None else -1)
    for u in coords[1:]:
        add(u, 1)
    if sym is not None and sym.action == "affine" and not (sym.matrix is not None and np.any(sym.matrix)):
        add(psi, -1)  # a shift: xi is a pure number
    if sym is not None and sym.action == "momentum":
        add(coords[int(sym.axis)], -1)  # type: ignore[arg-type]

    def power(unit: str, e: int) -> str:
        u = f"({unit})" if " " in unit or "/" in unit else unit
        return u if e == 1 else f"{u}^{e}"

    num = " ".join(power(u, e) for u, e in exps.items() if e > 0) or "1"
    den = [power(u, -e) for u, e in exps.items() if e < 0]
    if not den:
        return num
    return f"{num}/{den[0]}" if len(den) == 1 else f"{num}/({' '.join(den)})"


def _long_name(sym: Symmetry | None, f: LatticeField) -> str:
    if sym is None:
        return "discrete energy (P^- + P^+)/2 . (Q1 - Q0)/h0 - L_s"
    what = sym.name
    if sym.action == "momentum":
        what = f"lattice pseudo-momentum along {f.dims[int(sym.axis)]}"  # type: ignore[arg-type]
    elif sym.name.startswith("rotation-") and f.components is not None and sym.matrix is not None:
        i, j = (int(k) for k in np.argwhere(sym.matrix < 0)[0])
        what = f"angular momentum in the ({f.components[i]}, {f.components[j]}) plane"
    elif sym.name.startswith("shift"):
        what = "total canonical momentum" + (f" of component {sym.name[6:]}" if sym.name != "shift" else "")
    return f"{what} (Noether charge of {sym.name})"


# -- measuring ------------------------------------------------------------------------------------------------
def _served(pred: xr.DataArray, slices: int) -> xr.DataArray:
    return pred.isel({pred.dims[0]: slice(0, slices)})


def _auto(
    model: AbstractLagrangian, served: xr.DataArray, f: LatticeField, boundary: Any, rec: TaskRecord
) -> list[str]:
    """The continuous built-in symmetries that ``ldft.symmetries`` finds exact on the served field."""
    reports = symmetries(model, served, [s.name for s in _continuous(f)], boundary=boundary)
    rec.charges_auto = [
        {"name": r.name, "residual": r.residual, "residual_equations": r.residual_equations, "verdict": r.verdict}
        for r in reports
    ]
    found = [r.name for r in reports if r.invariant]
    log.debug("auto charges: %s", "; ".join(r.summary_line() for r in reports))
    return found


def task_charges(model: AbstractLagrangian, t: ServeTask, pred: xr.DataArray, rec: TaskRecord) -> xr.Dataset | None:
    """The task's charges along the solved slices of ``pred``, on ``pred``'s time coordinate (NaN at ``t_0``:
    a charge belongs to a slab and is given at its later slice); their drifts go to ``rec.charges``.

    Nothing when the task lists no charges or fewer than two slices were solved; a failure is logged as a
    warning and recorded (``rec.charges_error``), not raised, so the served field is still written.
    """
    names = list(t.charges)
    slices = int(rec.slices or 0)
    if not names or slices < 2:
        return None
    served = _served(pred, slices)
    try:
        f = as_lattice_field(served, boundary=t.boundary, min_slices=2)
        if AUTO in names:
            found = _auto(model, served, f, t.boundary, rec)
            names = [n for n in names if n != AUTO]
            names += [n for n in found if n not in names]
        if not names:
            rec.charges = {}
            return None
        ds = noether_charges(model, served, names, boundary=t.boundary)
    except LatticeDFTError as exc:
        log.warning("task %s: charges not measured (%s)", t.name, exc)
        rec.charges_error = str(exc)
        return None
    syms = {s.name: s for s in _continuous(f)}
    gauge = model.gauge
    tdim = pred.dims[0]
    out: dict[str, xr.DataArray] = {}
    record: dict[str, Any] = {}
    for name in names:
        series = ds[ENERGY if name == ENERGY else f"J_{name}"]
        sym = None if name == ENERGY else syms.get(name)
        values = np.full(pred.sizes[tdim], np.nan)
        values[1:slices] = series.values
        var = charge_variable(name)
        attrs = {
            "long_name": _long_name(sym, f),
            "relative_drift": float(series.attrs["relative_drift"]),
            "scale": float(series.attrs["scale"]),
            "comment": "one value per slab (slices t_i, t_i+1), at its later slice; relative_drift = "
            "(max - min) / scale",
        }
        if sym is not None:
            attrs.update(symmetry=name, generator=sym.description)
        units = _units(pred, sym, gauge)
        if units:
            attrs["units"] = units
        out[var] = xr.DataArray(values, dims=[tdim], coords={tdim: pred[tdim]}, attrs=attrs)
        record[name] = {
            "variable": var,
            "relative_drift": attrs["relative_drift"],
            "scale": attrs["scale"],
            "first": float(series.values[0]),
        }
    rec.charges = record
    return xr.Dataset(out)


def drift_text(rec: TaskRecord) -> str:
    """``", drift rotation-xy 1.1e-12, energy 2.4e-02"``: the task line's part (empty without charges)."""
    charges = rec.charges or {}
    if not charges:
        return ", charges: none exact (auto)" if rec.charges_auto is not None and rec.charges is not None else ""
    return ", drift " + ", ".join(f"{n} {c['relative_drift']:.1e}" for n, c in charges.items())
