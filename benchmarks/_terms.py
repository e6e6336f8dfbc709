"""Term recovery: a learned closed-form ``L_d`` against the true one, compared through the equations they imply.

Two discrete Lagrangians that differ by a factor, a constant or a total difference imply the same discrete
Euler-Lagrange (DEL) equation, so they are compared there. :func:`del_equations` writes the DEL at the site 0 of
a :class:`~latticedft._symbolic.SymbolicLd` in the values of the site's neighbours (``v{offset}_{component}``);
:func:`normalised_terms` expands it into terms and divides each component's equation by the coefficient of the
linear term in the next time slice's value of that component (the gauge normalisation: unit mass);
:func:`coefficient_error` compares the terms of two forms. The peers' continuous models are compared the same
way through their equations of motion: :func:`euler_lagrange_terms` (a Lagrangian ``L(q, v)``) and
:func:`acceleration_terms` (``q'' = f(q, q')``), each normalised so that the acceleration's coefficient is 1.
"""

from __future__ import annotations

import math
from typing import Any

import sympy

from latticedft._symbolic import SymbolicLd

__all__ = [
    "del_equations",
    "normalised_terms",
    "coefficient_error",
    "neighbour",
    "term_error",
    "euler_lagrange_terms",
    "acceleration_terms",
    "terms_cell",
]


#: Terms whose normalised coefficient is below this fraction of the largest are round-off, not terms.
ROUND_OFF = 1e-13


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
    return [_normalised(eq, neighbour(future, c)) for c, eq in enumerate(del_equations(form))]


def terms_cell(n_got: int, n_want: int) -> str:
    """The table cell of a comparison: ``got/wanted`` terms, or why the equation could not be normalised."""
    return f"{n_got}/{n_want}" if n_got else "no mass term"


def term_error(got: list[dict[Any, float]], want: list[dict[Any, float]]) -> tuple[float, int, int]:
    """``(max relative coefficient error, terms got, terms wanted)`` of normalised equations, component by
    component. Each wanted term's error is relative to its own coefficient; a term not wanted counts with its
    coefficient relative to the smallest wanted one. ``(inf, 0, terms wanted)`` when a component could not be
    normalised."""
    worst, n_got, n_want = 0.0, sum(len(x) for x in got), sum(len(x) for x in want)
    for g, w in zip(got, want, strict=True):
        if not g or not w:
            return math.inf, 0, n_want
        smallest = min(abs(v) for v in w.values())
        for term in set(g) | set(w):
            scale = abs(w[term]) if term in w else smallest
            worst = max(worst, abs(g.get(term, 0.0) - w.get(term, 0.0)) / scale)
    return worst, n_got, n_want


def coefficient_error(learned: SymbolicLd, true: SymbolicLd) -> tuple[float, int, int]:
    """:func:`term_error` of the normalised DEL equations of two closed-form ``L_d``."""
    return term_error(normalised_terms(learned), normalised_terms(true))


def _split_phases(expr: Any) -> Any:
    """``sin(a + c)``, ``cos(a + c)`` with a constant ``c`` written in ``sin a`` and ``cos a``, so that a potential
    such as ``cos(q^2 - 1)`` and a library's ``sin(q^2)``, ``cos(q^2)`` are compared on the same terms (other
    arguments, ``sin(2 q)`` or ``cos(q1 - q2)``, are kept as they are)."""

    def phased(e: Any) -> bool:
        return isinstance(e, (sympy.sin, sympy.cos)) and e.args[0].is_Add and e.args[0].as_coeff_Add()[0] != 0

    def split(e: Any) -> Any:
        c, a = e.args[0].as_coeff_Add()
        if isinstance(e, sympy.sin):
            return sympy.sin(a) * sympy.cos(c) + sympy.cos(a) * sympy.sin(c)
        return sympy.cos(a) * sympy.cos(c) - sympy.sin(a) * sympy.sin(c)

    return expr.replace(phased, split)


def expanded_terms(expr: Any) -> dict[Any, Any]:
    """``expr`` expanded into a sum of terms, ``{term: coefficient}``; powers with a non-integer exponent
    (``(x^2 + y^2)^(-3/2)``) are kept whole."""
    expr = _rational_powers(_split_phases(sympy.sympify(expr)).evalf())
    whole = {p: sympy.Dummy() for p in expr.atoms(sympy.Pow) if not p.exp.is_Integer}
    terms = sympy.expand(expr.xreplace(whole)).as_coefficients_dict()
    back = {d: p for p, d in whole.items()}
    return {t.xreplace(back): c for t, c in terms.items()}


def _normalised(eq: Any, lead: Any) -> dict[Any, float]:
    terms = expanded_terms(eq)
    scale = terms.get(lead, 0)
    if scale == 0:
        return {}
    out = {t: float(v / scale) for t, v in terms.items()}
    largest = max(abs(v) for v in out.values())
    return {t: v for t, v in out.items() if abs(v) > ROUND_OFF * largest}


def euler_lagrange_terms(L: Any, q: Any, v: Any, a: Any) -> list[dict[Any, float]]:
    """The terms of ``d/dt dL/dv_i - dL/dq_i`` (symbols ``q``, ``v``, ``a``), each scaled so that the
    coefficient of ``a_i`` is 1."""
    out = []
    for i in range(len(q)):
        p = sympy.diff(L, v[i])
        eq = sum(sympy.diff(p, q[j]) * v[j] + sympy.diff(p, v[j]) * a[j] for j in range(len(q))) - sympy.diff(L, q[i])
        out.append(_normalised(eq, a[i]))
    return out


def acceleration_terms(rhs: list[Any], a: Any) -> list[dict[Any, float]]:
    """The terms of ``a_i - rhs_i`` (``q'' = rhs``), the coefficient of ``a_i`` 1."""
    return [_normalised(a[i] - r, a[i]) for i, r in enumerate(rhs)]
