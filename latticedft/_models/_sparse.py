"""A sparse ``L_d``: a few terms of a library (:mod:`latticedft._models._library`), found by sparse regression
inside the gauge-fixed exact solve, and printed as an equation."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
import torch

from .._contract import NumpyForms
from .._errors import InputError
from .._stencil import Stencil
from .._symbolic import SymbolicLd, cell_symbols, del_equations
from ._library import Library, cell_variables, readable_variables
from ._linear import LinearLagrangian
from ._termderiv import TermDerivatives, closed_derivatives, term_derivatives
from ._termnumpy import numpy_forms, numpy_term_derivatives
from ._terms import Term, axis_name, term_forms, term_values

__all__ = ["SparseLagrangian", "LazyEquation", "default_library", "exact_step_libraries", "THRESHOLDS"]

#: The thresholds tried by ``threshold = "auto"`` (a term is dropped when its share of the DEL residual's
#: largest column, ``|coef_c| |R e_c|``, is below the threshold), largest first.
THRESHOLDS = (0.1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 0.0)


def default_library(n: int, m: int, corrections: bool = False) -> str:
    """``library = "auto"``: the library tried on a lattice of ``n`` axes and ``m`` components; with
    ``corrections``, for a scalar field, also the products that carry the lattice's ``O(h^2)`` corrections
    to a continuum Lagrangian (a squared kinetic term, kinetic times on-site functions, the second harmonic).

    >>> default_library(2, 1)
    'kinetic + gradient + poly:4 + trig:1'
    >>> default_library(1, 1, corrections=True)
    'kinetic + poly:4 + trig:1 + trig:2 + kinetic*kinetic + kinetic*poly:2 + kinetic*trig:1'
    >>> default_library(1, 2)
    'kinetic + poly:2 + norm:-1 + log + cross'
    """
    if m == 1:
        base = "kinetic" + (" + gradient" if n > 1 else "") + " + poly:4 + trig:1"
        if corrections:
            base += " + trig:2 + kinetic*kinetic + kinetic*poly:2 + kinetic*trig:1"
            base += " + gradient*gradient + kinetic*gradient" if n > 1 else ""
        return base
    return "kinetic + poly:2 + norm:-1 + log" + (" + cross" if m == 2 else "")


def exact_step_libraries(n: int, m: int, order: int = 3) -> list[str]:
    """The exact-step corrections libraries of a time-only lattice (empty on a field lattice). For ``L = |q'|^2/2
    - V(q)`` one step of the exact flow has the discrete Lagrangian, in the trapezoid rule (``at = "average"``),
    ``h (|v|^2/2 - V) - h^3/24 |grad V|^2 + h^3/12 v.Hess(V).v + O(h^5)`` with ``v = (q1 - q0)/h``
    (docs/discovery.md). Each library holds a family of potentials ``V`` and the terms that its corrections
    span to ``O(h^order)``: at ``order = 3``, for ``V`` in ``trig:1``, ``V'^2`` in ``trig:2`` and ``V''`` in
    ``trig:1``; for ``V`` in ``poly:4``, ``V'^2`` to degree 6 and ``V''`` to degree 2; for ``V = c/|q|``,
    ``|q|^-4``, ``|Dq|^2 |q|^-3`` and ``(q . Dq)^2 |q|^-5``; for two components coupled through ``cos(q1 - q2)``
    (``velocities + trig:1 + cosdiff*velocities``, a mass that depends on the positions), ``coupledstep``. At
    ``order = 5`` (the trig potentials only) also ``V'^2 V''`` (in ``trig:3``), ``V''^2 v^2`` and ``V' V''' v^2`` (in
    ``kinetic*trig:2``) and ``V'''' v^4``.

    >>> exact_step_libraries(1, 1)
    ['kinetic + trig:2 + kinetic*trig:1', 'kinetic + poly:6 + kinetic*poly:2']
    >>> exact_step_libraries(1, 1, order=5)
    ['kinetic + trig:3 + kinetic*trig:2 + kinetic*kinetic*trig:1']
    >>> exact_step_libraries(1, 2)[1]
    'velocities + trig:1 + cosdiff*velocities + coupledstep'
    """
    if n != 1:
        return []
    if order == 5:
        return ["kinetic + trig:3 + kinetic*trig:2 + kinetic*kinetic*trig:1"] if m == 1 else []
    if m == 1:
        return ["kinetic + trig:2 + kinetic*trig:1", "kinetic + poly:6 + kinetic*poly:2"]
    return ["kinetic + norm:-1,-4 + kinetic*norm:-3 + radial*norm:-5"] + (
        ["velocities + trig:1 + cosdiff*velocities + coupledstep"] if m == 2 else []
    )


class SparseLagrangian(LinearLagrangian):
    """``L_d = sum_c coef_c T_c(q, D q)``: a few terms ``T_c`` of a library, the rest exactly zero.

    The terms are functions of the field ``q`` at the cell's anchor site (or the stencil mean) and of the
    discrete derivatives ``D_k q = (psi[x + e_k] -
    psi[x]) / h_k`` (see :mod:`latticedft._models._library` for the library's shorthands and objects).
    :func:`latticedft.learn` solves the gauge-fixed least-squares problem with sequential thresholding: fit,
    drop every term whose share of the residual is below ``threshold``, refit, until the support holds.
    ``threshold = "auto"`` tries :data:`THRESHOLDS` and the supports of backward elimination, each fitted on
    the first 70 % of every training field, and
    keeps the sparsest support that serves the held-out tail (from its first two slices) within a relative
    error of 5e-3, or else within 3x of the best.
    ``bags`` refits on resampled time blocks of the data give each term an inclusion probability.

    Parameters
    ----------
    library : str, Library or list, default "auto"
        The terms (a shorthand string such as ``"kinetic + gradient + poly:4 + trig:1"``, a
        :class:`Library`, or a list of either); ``"auto"``: :func:`default_library` of the lattice.
    threshold : float or "auto"
        Relative share below which a term is dropped (``0``: the dense fit), or ``"auto"``.
    bags : int
        Resampled fits for the inclusion probabilities (``0``: none).
    at : "anchor", "mean" or "average"
        Where the on-site functions of the field are evaluated: at the cell's anchor site (the default:
        ``L_d = |D_t q|^2 / 2 - V(q[x])`` is the leapfrog's own ``L_d``), at the stencil mean (a midpoint
        rule, as :class:`FeatureLagrangian`), or at every stencil point with the term averaged over them (on
        the first-order stencil of an ODE, the trapezoid rule ``h (L(q0, Dq) + L(q1, Dq)) / 2``, which a
        position-dependent mass such as ``cos(q1 - q2) Dtq1 Dtq2`` needs to be met exactly).
    stencil : Stencil, optional
        Default: the first-order stencil.
    """

    kind = "sparse"
    #: Buffers set by :meth:`_build`: each term's inclusion probability over the bagged fits (NaN before), and
    #: the threshold the fit used.
    inclusion: torch.Tensor
    threshold_used: torch.Tensor
    #: Set by the last fit (not saved): each term's coefficient's standard deviation over the bagged fits over
    #: the coefficient's magnitude (0 for a term not kept, NaN without bags); None before a fit.
    bag_spread: np.ndarray | None = None

    def __init__(
        self,
        library: Any = "auto",
        *,
        threshold: float | str = "auto",
        bags: int = 20,
        at: Literal["mean", "anchor", "average"] = "anchor",
        stencil: Stencil | None = None,
    ):
        super().__init__(stencil)
        self.library = None if isinstance(library, str) and library == "auto" else Library.parse(library)
        if not (threshold == "auto" or (isinstance(threshold, (int, float)) and not isinstance(threshold, bool))):
            raise InputError.at("threshold", f"expected a number in [0, 1) or 'auto', got {threshold!r}")
        if threshold != "auto" and not (0 <= float(threshold) < 1):
            raise InputError.at("threshold", f"expected a number in [0, 1) or 'auto', got {threshold!r}")
        if not isinstance(bags, int) or isinstance(bags, bool) or bags < 0:
            raise InputError.at("bags", f"expected an integer >= 0, got {bags!r}")
        if at not in _AT:
            raise InputError.at("at", f"expected 'anchor', 'mean' or 'average', got {at!r}")
        self.at = at
        self.threshold: float | str = threshold if threshold == "auto" else float(threshold)
        self.bags = bags
        self.terms: list[Term] = []

    @property
    def has_functions(self) -> bool:
        return self.library is not None and not self.library.saveable

    def options(self) -> dict[str, Any]:
        lib = "auto" if self.library is None else " + ".join(self.library.labels)
        return {"library": lib, "threshold": self.threshold, "bags": self.bags, "at": self.at}

    def auto_candidates(self, n: int, ridge: Any = 0.0) -> list[dict[str, Any]]:
        """The other thresholds (chosen by held-out serving)."""
        return [{"threshold": t} for t in THRESHOLDS if t != self.threshold]

    # -- structure ---------------------------------------------------------------------------------------
    def _build(self) -> None:
        library = self.library or Library.parse(default_library(self.n, self.m))
        self.terms = library.expand(self.n, self.m)
        self.register_buffer("inclusion", torch.full((len(self.terms),), math.nan, dtype=torch.float64))
        self.register_buffer("threshold_used", torch.tensor(math.nan, dtype=torch.float64))
        super()._build()

    @property
    def n_terms(self) -> int:
        return len(self.terms)

    @property
    def term_names(self) -> list[str]:
        """The library's terms on the bound lattice, in the order of ``coef``."""
        self._require_bound()
        return [t.name for t in self.terms]

    def n_parameters(self) -> int:
        """The terms kept (nonzero coefficients); every term before learning."""
        nonzero = int((self.coef != 0).sum()) if self.bound else 0
        return nonzero or (self.n_terms if self.bound else 0)

    def features(self, cells: torch.Tensor) -> torch.Tensor:
        z = self.mean_and_differences(cells)
        if self.at == "mean":
            return term_values(self.terms, z, self.spacing)
        points = [self.stencil.anchor] if self.at == "anchor" else range(self.stencil.size)
        # the on-site functions see one stencil point's value (the anchor's, or each in turn, averaged)
        values = [
            term_values(self.terms, torch.cat([cells[..., p : p + 1, :], z[..., 1:, :]], -2), self.spacing)
            for p in points
        ]
        return values[0] if len(values) == 1 else torch.stack(values).mean(0)

    def derivatives_of_features(
        self, cells: torch.Tensor, pairs: Sequence[tuple[int, int]], first: bool
    ) -> tuple[torch.Tensor | None, dict[tuple[int, int], torch.Tensor]]:
        """The terms' derivatives in closed form (their sympy forms differentiated,
        :mod:`latticedft._models._termderiv`); forward-mode differentiation where a user term has no form."""
        rule = self._closed_rule(self.terms)
        if rule is None:
            return super().derivatives_of_features(cells, pairs, first)
        return closed_derivatives(rule, self._input_maps(), cells, self.spacing, pairs, first, self.n_terms)

    def fast_derivatives(
        self, cells: torch.Tensor, pairs: list[tuple[int, int]]
    ) -> tuple[torch.Tensor, dict[tuple[int, int], torch.Tensor]] | None:
        """``dL/dx`` and Hessian blocks of the kept terms in closed form (what serving asks for; None, so autograd,
        where a user term has no sympy form)."""
        kept = self._kept()
        rule = self._closed_rule([self.terms[c] for c in kept])
        if rule is None:
            return None
        coef = self.coef.detach()[kept]
        with torch.no_grad():
            d, blocks = closed_derivatives(rule, self._input_maps(), cells, self.spacing, pairs, True, len(kept))
        assert d is not None
        return d @ coef, {p: b @ coef for p, b in blocks.items()}

    def numpy_derivatives(self, pairs: Sequence[tuple[int, int]]) -> NumpyForms | None:
        """:meth:`fast_derivatives` in numpy (:mod:`latticedft._models._termnumpy`), for the coefficients as they
        are now; None where a user term has no sympy form."""
        self._require_bound()
        if self.has_functions:
            return None
        kept = self._kept()
        rule = numpy_term_derivatives([self.terms[c] for c in kept], self.n, self.m)
        if rule is None:
            return None
        coef = self.coef.detach().cpu().numpy()[kept]
        maps = [a.detach().cpu().numpy() for a in self._input_maps()]
        return numpy_forms(rule, maps, self.spacing, pairs, coef)

    def _closed_rule(self, terms: list[Term]) -> TermDerivatives | None:
        """The closed-form derivatives of ``terms`` (None where the library holds a user function: no sympy
        form to differentiate)."""
        if self.library is not None and not self.library.saveable:
            return None
        return term_derivatives(terms, self.n, self.m)

    def _input_maps(self) -> list[torch.Tensor]:
        """The linear maps from a cell's values to the terms' inputs (the on-site value, then the differences),
        one per stencil point that :meth:`features` evaluates the on-site functions at."""
        if self.at == "mean":
            return [self.proj]
        points = [self.stencil.anchor] if self.at == "anchor" else range(self.stencil.size)
        maps = []
        for p in points:
            a_map = self.proj.clone()
            a_map[0] = 0.0
            a_map[0, p] = 1.0
            maps.append(a_map)
        return maps

    # -- the equation ------------------------------------------------------------------------------------
    def _kept(self, coef: list[float] | None = None) -> list[int]:
        coef = self.coef.detach().tolist() if coef is None else coef
        return [c for c, a in enumerate(coef) if a != 0.0]

    def kept_terms(self) -> list[str]:
        """The names of the terms the fit kept (nonzero coefficients), in the order of ``coef``."""
        return [self.terms[c].name for c in self._kept()]

    def symbolic(self) -> SymbolicLd | None:
        """``L_d`` in the cell symbols (None when a user term has no sympy form)."""
        return self._symbolic(self.coef.detach().tolist())

    def _symbolic(self, coef: list[float]) -> SymbolicLd | None:
        self._require_bound()
        q, d = cell_variables(self.proj, self.spacing, self.m)
        if self.at == "mean":
            return _sum_form(self, [q], d, coef)
        u = cell_symbols(self.stencil.size, self.m)
        points = [self.stencil.anchor] if self.at == "anchor" else range(self.stencil.size)
        return _sum_form(self, [list(u[p]) for p in points], d, coef)

    def equation(self) -> Any:
        """``L_d`` as a sympy expression in the readable symbols ``q`` (``q1``, ...) and ``Dtq``, ``Dxq`` ...
        (None when a user term has no sympy form)."""
        return self._equation(self.coef.detach().tolist())

    def _equation(self, coef: list[float]) -> Any:
        self._require_bound()
        q, d, _ = readable_variables(self.n, self.m)
        form = _sum_form(self, [q], d, coef)
        return None if form is None else form.expr

    def equation_text(self) -> dict[str, Any]:
        """``L_d`` and the DEL it implies in plain text and LaTeX (what describe, model.json and figures show)."""
        return self._equation_text(self.coef.detach().tolist())

    def equation_later(self) -> LazyEquation:
        """:meth:`equation_text` of the coefficients learned now, built when first called: sympy's printing costs
        more than a small fit, and selection fits many candidates to keep one (the learning report's equation)."""
        return LazyEquation(self, self.coef.detach().tolist())

    def _equation_text(self, coef: list[float]) -> dict[str, Any]:
        import sympy

        expr = self._equation(coef)
        if expr is None:
            return {}
        _, _, names = readable_variables(self.n, self.m)
        form = self._symbolic(coef)
        assert form is not None
        dels = del_equations(form, lambda shift, c: _site_name(shift, c, self.m))
        return {
            "L_d": str(expr),
            "latex": sympy.latex(expr, symbol_names=names),
            "del": [f"{sympy.sstr(e)} = 0" for e in dels],
            "where": f"q = {_AT[self.at]}, D<axis>q = (q[x + e_axis] - q[x]) / h_axis",
        }

    def describe(self, max_terms: int | None = 12) -> str:
        head = super().describe(max_terms)
        lib = "auto" if self.library is None else " + ".join(self.library.labels)
        lines = [
            head,
            f"  library: {lib} ({self.n_terms} terms on this lattice)" if self.bound else f"  library: {lib}",
        ]
        if not self.bound:
            return "\n".join(lines)
        coef = self.coef.detach().tolist()
        kept = self._kept()
        shown = kept if max_terms is None else kept[:max_terms]
        lines.append(f"  L_d = sum of {len(kept)} terms (threshold {float(self.threshold_used):.3g}):")
        for c in shown:
            p = float(self.inclusion[c])
            note = "" if math.isnan(p) else f"   (inclusion {p:.2f})"
            lines.append(f"      {coef[c]:+.10g} {self.terms[c].name}{note}")
        if len(kept) > len(shown):
            lines.append(f"      ... {len(kept) - len(shown)} more terms (model.describe(max_terms=None))")
        text = self.equation_text() if kept else {}
        if text:
            lines += [f"  L_d = {text['L_d']}", f"  LaTeX: {text['latex']}"]
            lines += [f"  DEL: {_clip(e)}" for e in text["del"]]
            lines.append(f"  where {text['where']}")
        return "\n".join(lines)

    def sparse_summary(self, equation: bool = True) -> dict[str, Any]:
        """The terms, their coefficients and inclusion probabilities, the threshold, and (with ``equation``) the
        equation with its DEL (:meth:`equation_text`): what the learning report (model.json, summary.json) holds."""
        coef = self.coef.detach().tolist()
        summary = {
            "threshold": float(self.threshold_used),
            "terms": [
                {"term": t.name, "coef": coef[c], "inclusion": _finite(float(self.inclusion[c]))}
                for c, t in enumerate(self.terms)
            ],
            "kept": self.kept_terms(),
        }
        return {**summary, "equation": self.equation_text() if self._kept() else {}} if equation else summary


class LazyEquation:
    """The equation of a sparse model's coefficients ``coef`` (:meth:`SparseLagrangian.equation_text`), built when
    called: the learning report holds one and builds its ``sparse["equation"]`` when first read."""

    def __init__(self, model: SparseLagrangian, coef: list[float]):
        self.model = model
        self.coef = coef

    def __call__(self) -> dict[str, Any]:
        return self.model._equation_text(self.coef) if self.model._kept(self.coef) else {}


_AT = {
    "anchor": "the value at the anchor site x",
    "mean": "the mean of the stencil values",
    "average": "each stencil value in turn, the L_d averaged over them",
}


def _clip(text: str, width: int = 400) -> str:
    """``text`` cut to ``width`` characters (a long DEL: ``equation_text()`` holds it whole)."""
    return text if len(text) <= width else text[: width - 40] + f" ... ({len(text)} characters in all)"


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def _sum_form(model: SparseLagrangian, qs: list[list[Any]], d: list[list[Any]], coef: list[float]) -> SymbolicLd | None:
    """The kept terms' sum (coefficients ``coef``) in the derivatives ``d``, its on-site functions at each of ``qs``
    in turn, averaged."""
    import sympy

    kept = model._kept(coef)
    expr = sympy.Integer(0)
    for q in qs:
        forms = term_forms([model.terms[c] for c in kept], q, d)
        if forms is None:
            return None
        expr += sum((sympy.Float(coef[c]) * f for c, f in zip(kept, forms)), sympy.Integer(0)) / len(qs)
    return SymbolicLd(expr, tuple(tuple(o) for o in model.stencil.to_list()), model.m, model.spacing)


def _site_name(shift: tuple[int, ...], c: int, m: int) -> str:
    """``q[t+1]``, ``q1[t,x-1]``: the field at a site shifted from the DEL's site."""
    parts = [axis_name(k) + (f"{s:+d}" if s else "") for k, s in enumerate(shift)]
    return f"{'q' if m == 1 else f'q{c + 1}'}[{','.join(parts)}]"
