"""Invariance tests of a learned ``L_d``: which symmetries does the theory have, on the data it was learned from?"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from .._contract import AbstractLagrangian
from .._errors import InputError
from .._lattice import as_lattice_field
from ._core import FieldEval, _listify, prepare, ratio
from ._group import Symmetry, resolve_symmetries, standard_symmetries

__all__ = ["DEFAULT_TOL", "SymmetryReport", "builtin_symmetries", "symmetries"]

#: Residual at or below which a symmetry counts as exact (round-off is ~1e-15; see docs/symmetries.md).
DEFAULT_TOL = 1e-9


@dataclass
class SymmetryReport:
    """The invariance of one ``L_d`` under one symmetry, measured over data.

    ``residual`` (dimensionless) — continuous symmetries: rms over slabs of
    ``delta_i = H sum_cells sum_a dL_d/dpsi_a . xi(psi_a)`` over rms of ``H sum_cells sum_a |dL_d/dpsi_a| |xi(psi_a)|``
    (the per-step change of the Noether charge relative to the size of its terms); discrete symmetries:
    rms over slabs of ``L_s(g . slab) - L_s(slab)`` over rms of ``H sum_cells |L_d - mean L_d|``.
    ``residual_equations``: the same test up to null Lagrangians — the DEL residual of ``L_d o g - L_d``
    (or of ``delta L_d``) on the interior sites relative to the inertial term ``H Mbar D_tt psi``; it
    vanishes when ``L_d`` has the symmetry up to a discrete divergence, and it probes the derivatives of
    ``L_d`` around the data, not only its values on them.

    ``invariant``: both are at most ``tol`` — ``L_d`` has the symmetry, and the Noether charge of a
    continuous one is conserved along fields served by it. ``verdict`` says which part fails:
    ``"exact"``, ``"up to a null Lagrangian"`` (only the equations are symmetric: the DEL equations and
    served fields have the symmetry, but the charge computed from this ``L_d`` is not conserved),
    ``"on the data only"`` (``L_d`` is invariant on these fields but not around them) or ``"broken"``.
    """

    name: str
    kind: str
    generator: Any
    residual: float
    invariant: bool
    residual_equations: float
    equations_invariant: bool
    tol: float
    symmetry: Symmetry

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible (``symmetry`` is left out; ``generator`` describes it)."""
        return {
            "name": self.name,
            "kind": self.kind,
            "generator": self.generator,
            "residual": _num(self.residual),
            "invariant": self.invariant,
            "residual_equations": _num(self.residual_equations),
            "equations_invariant": self.equations_invariant,
            "tol": self.tol,
        }

    @property
    def verdict(self) -> str:
        """``"exact"``, ``"up to a null Lagrangian"``, ``"on the data only"`` or ``"broken"``."""
        if self.invariant:
            return "exact"
        if self.equations_invariant:
            return "up to a null Lagrangian"
        return "on the data only" if self.residual <= self.tol else "broken"

    def summary_line(self) -> str:
        return (
            f"{self.name:<16} {self.kind:<10} residual {self.residual:8.1e}   "
            f"equations {self.residual_equations:8.1e}   {self.verdict}"
        )

    def __str__(self) -> str:
        return self.summary_line()


def _num(x: float) -> float | str:
    return x if math.isfinite(x) else str(x)


def _check_tol(tol: Any) -> float:
    if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not (math.isfinite(tol) and tol >= 0):
        raise InputError(f"tol: expected a finite number >= 0, got {tol!r}")
    return float(tol)


def measure(model: AbstractLagrangian, evals: list[FieldEval], sym: Symmetry, tol: float) -> SymmetryReport:
    """One report from prepared field evaluations."""
    num = den = 0.0
    for ev in evals:
        a, b = ev.variation(sym) if sym.continuous else ev.discrete_change(sym)
        num += float((a**2).sum())
        den += float((b**2).sum())
    res = ratio(num, den)
    eq_num = eq_den = 0.0
    for ev in evals:
        a2, b2 = ev.equation_change(sym)
        eq_num += a2
        eq_den += b2
    res_eq = ratio(eq_num, eq_den)
    return SymmetryReport(
        name=sym.name,
        kind=sym.kind,
        generator=sym.generator(),
        residual=res,
        invariant=bool(res <= tol and res_eq <= tol),
        residual_equations=res_eq,
        equations_invariant=bool(res_eq <= tol),
        tol=tol,
        symmetry=sym,
    )


def builtin_symmetries(data: Any, *, boundary: Any = None) -> list[Symmetry]:
    """The built-in symmetry candidates of a field's lattice (the first field of a list), named after its labels.

    ``shift`` (scalar) or ``shift-<component>``; ``reflection`` (``psi -> -psi``); ``rotation-<a><b>`` for
    every pair of components; ``time-reversal``; for every periodic spatial axis ``translation-<dim>``
    (one site) and ``momentum-<dim>`` (the pseudo-momentum generator). The names are what
    :func:`symmetries` and :func:`noether_charge` accept.

    >>> from latticedft import systems
    >>> [s.name for s in builtin_symmetries(systems.kepler_orbit(1.0, 1.0, n=3))]
    ['shift-x', 'shift-y', 'reflection', 'rotation-xy', 'time-reversal']
    """
    f = as_lattice_field(_listify(data)[0], boundary=boundary, min_slices=2)
    return standard_symmetries(f.ndim, f.ncomp, f.periodic, f.dims, f.components)


def symmetries(
    model: AbstractLagrangian, data: Any, candidates: Any = None, *, tol: float = DEFAULT_TOL, boundary: Any = None
) -> list[SymmetryReport]:
    """Test a (learned) ``L_d`` for symmetries over data — usually the training fields.

    Parameters
    ----------
    model
        A bound model (learned), or an ``AnalyticLagrangian`` (bound to the data's lattice here).
    data
        A field (DataArray or LatticeField) or a list of them, on the model's lattice.
    candidates
        Symmetries to test: :class:`Symmetry` objects or names of :func:`builtin_symmetries` (default: all
        the built-in ones that apply to the data: shifts, reflection, rotations of the components, time
        reversal, translations and pseudo-momenta along periodic axes).
    tol
        A symmetry is ``invariant`` when its residual is at most ``tol`` (default 1e-9; round-off is
        about 1e-15).
    boundary
        Boundary kinds of the spatial axes (default: the coordinates' ``periodic`` attributes).

    Returns
    -------
    list of SymmetryReport
        One per candidate, in order.
    """
    tol = _check_tol(tol)
    fields = prepare(model, data, boundary)
    f0 = fields[0]
    syms = resolve_symmetries(candidates, f0.ndim, f0.ncomp, f0.periodic, f0.dims, f0.components)
    for f in fields[1:]:
        for s in syms:
            s.check(f.ndim, f.ncomp, f.periodic)
    evals = [FieldEval(model, f) for f in fields]
    return [measure(model, evals, s, tol) for s in syms]
