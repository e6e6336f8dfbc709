"""Term recovery: a learned closed-form ``L_d`` against the true one, compared through the equations they imply.

Two discrete Lagrangians that differ by a factor, a constant or a total difference imply the same discrete
Euler-Lagrange (DEL) equation, so they are compared there. :func:`del_equations` writes the DEL at the site 0 of
a :class:`~latticedft._symbolic.SymbolicLd` in the values of the site's neighbours (``v{offset}_{component}``);
:func:`normalised_terms` expands it into terms and divides each component's equation by the coefficient of the
linear term in the next time slice's value of that component (the gauge normalisation: unit mass);
:func:`coefficient_error` compares the terms of two forms.
"""

from __future__ import annotations

import math
from typing import Any

import sympy

from latticedft._symbolic import SymbolicLd

__all__ = ["del_equations", "normalised_terms", "coefficient_error", "neighbour"]


def neighbour(offset: tuple[int, ...], component: int) -> Any:
    """The symbol of the value at lattice offset ``offset`` from the site, component ``component``."""
    name = "_".join(str(o).replace("-", "m") for o in offset)
    return sympy.Symbol(f"v{name}_{component}", real=True)


def del_equations(form: SymbolicLd) -> list[Any]:
    """The DEL at the site 0, one expression per component: ``sum_p dL_d/du_p`` over the cells whose point
    ``p`` is the site (the cell based at ``-offsets[p]``)."""
    syms = form.symbols
    out = []
    for c in range(form.m):
        total = sympy.Integer(0)
        for p, op in enumerate(form.offsets):
            subs = {
                syms[q][k]: neighbour(tuple(a - b for a, b in zip(oq, op)), k)
                for q, oq in enumerate(form.offsets)
                for k in range(form.m)
            }
            total += sympy.diff(form.expr, syms[p][c]).xreplace(subs)
        out.append(total)
    return out


def _rational_powers(expr: Any) -> Any:
    """Float exponents that are simple fractions (``-1.5``) as exact ones, so equal terms compare equal."""
    return expr.replace(
        lambda e: e.is_Pow and e.exp.is_Float, lambda e: sympy.Pow(e.base, sympy.nsimplify(e.exp, rational=True))
    )


def normalised_terms(form: SymbolicLd) -> list[dict[Any, float]]:
    """Per component, the DEL's terms and their coefficients, the linear term in the next slice's value of
    that component scaled to 1. A component with no such term gives an empty dictionary."""
    n = len(form.offsets[0])
    future = tuple(1 if k == 0 else 0 for k in range(n))
    out: list[dict[Any, float]] = []
    for c, eq in enumerate(del_equations(form)):
        terms = sympy.expand(_rational_powers(eq), deep=False).as_coefficients_dict()
        lead = terms.get(neighbour(future, c), 0)
        if lead == 0:
            out.append({})
            continue
        out.append({t: float(v / lead) for t, v in terms.items() if v != 0})
    return out


def coefficient_error(learned: SymbolicLd, true: SymbolicLd) -> tuple[float, int, int]:
    """``(max relative coefficient error, terms of the learned DEL, terms of the true DEL)``.

    Each true term's error is relative to its own coefficient; a term the true DEL lacks counts with its
    coefficient relative to the smallest true one. ``inf`` when a component cannot be normalised.
    """
    got, want = normalised_terms(learned), normalised_terms(true)
    worst, n_got, n_want = 0.0, 0, 0
    for g, w in zip(got, want):
        if not g or not w:
            return math.inf, sum(len(x) for x in got), sum(len(x) for x in want)
        n_got, n_want = n_got + len(g), n_want + len(w)
        smallest = min(abs(v) for v in w.values())
        for term in set(g) | set(w):
            scale = abs(w[term]) if term in w else smallest
            worst = max(worst, abs(g.get(term, 0.0) - w.get(term, 0.0)) / scale)
    return worst, n_got, n_want
