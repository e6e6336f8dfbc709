"""The double pendulum's exact-step corrections, for :mod:`benchmarks.discovery_gap` (``--corrections``).

One step of the exact flow of ``L = v.M(q).v/2 - V(q)`` has, in the trapezoid rule (``at = "average"``), the
discrete Lagrangian ``h L_avg - h^3/12 v.L_qq.v - h^3/24 E.M^-1.E + O(h^5)`` with ``v = (q1 - q0)/h`` and
``E = L_q - (d L_v/dq) v`` (the midpoint rule's ``h^3/24 (v.L_qq.v - E.M^-1.E)`` less the trapezoid rule's own
``h^3/8 v.L_qq.v``). :func:`exact_step_ld` writes it for an ODE system; :func:`correction_library` is the span of
these corrections over the family the coupled library holds for two pendulums, ``L = a v1^2 + b v2^2 + c v1 v2
cos(q1 - q2) - V1(q1) - V2(q2)`` with ``V_i`` in ``trig:1``, the factor ``1/det M`` of ``M^-1`` taken as a
constant: 28 terms, on top of :data:`latticedft._select.COUPLED_LIBRARY`. The library's shorthands cannot write
these terms without repeating products (``velocities*velocities`` holds ``Dtq1**2*Dtq1*Dtq2`` and
``Dtq1*Dtq2*Dtq1**2``), so the family is built here (a model file cannot record it).
"""

from __future__ import annotations

from typing import Any

import sympy

from latticedft._models._library import Library
from latticedft._models._terms import Family, Term
from latticedft._symbolic import SymbolicLd, cell_symbols

from ._discovery_systems import OdeSpec

__all__ = ["exact_step_ld", "correction_library", "CORRECTIONS"]


def exact_step_ld(spec: OdeSpec, h: float) -> SymbolicLd:
    """The trapezoid ``L_d`` of ``spec`` with the exact step's ``h^3`` corrections (``M^-1`` exact), on the
    stencil ``(0,), (1,)``."""
    q, v, lag = spec.q, spec.v, spec.lagrangian
    m = len(q)
    vv = sympy.Matrix(v)
    lq = sympy.Matrix([sympy.diff(lag, s) for s in q])
    lv = sympy.Matrix([sympy.diff(lag, s) for s in v])
    mass = sympy.Matrix(m, m, lambda i, j: sympy.diff(lag, v[i], v[j]))
    lqq = sympy.Matrix(m, m, lambda i, j: sympy.diff(lag, q[i], q[j]))
    e = lq - lv.jacobian(q) * vv
    corr = -(h**3) / 12 * (vv.T * lqq * vv)[0] - h**3 / 24 * (e.T * mass.inv() * e)[0]
    u0, u1 = cell_symbols(2, m)
    vel = [(u1[c] - u0[c]) / h for c in range(m)]

    def at(expr: Any, point: Any) -> Any:
        return expr.subs({**dict(zip(q, point)), **dict(zip(v, vel))}, simultaneous=True)

    total = sum((h * at(lag, u) + at(corr, u)) / 2 for u in (u0, u1))
    return SymbolicLd(total, ((0,), (1,)), m, (h,))


def _term(name: str, fn: Any) -> Term:
    return Term(name, lambda x: fn(x.q, x.d[0], x.xp))


def _terms() -> list[Term]:
    """The 28 correction terms (two components)."""

    def cd(q: Any, x: Any) -> Any:
        return x.cos(q[0] - q[1])

    def sd(q: Any, x: Any) -> Any:
        return x.sin(q[0] - q[1])

    trig = {"sin": lambda x, a: x.sin(a), "cos": lambda x, a: x.cos(a)}
    out = []
    # v.L_qq.v: the mass's cos(q1 - q2) v1 v2 (v1 - v2)^2 and the potentials' V_i'' v_i^2
    for p, r in ((3, 1), (2, 2), (1, 3)):
        name = "*".join(f"Dtq{i}" + (f"**{k}" if k > 1 else "") for i, k in ((1, p), (2, r)))
        out.append(_term(f"cos(q1-q2)*{name}", lambda q, d, x, p=p, r=r: cd(q, x) * d[0] ** p * d[1] ** r))
    for i in range(2):
        for f in trig:
            name = f"{f}(q{i + 1})*Dtq{i + 1}**2"
            out.append(_term(name, lambda q, d, x, i=i, f=f: trig[f](x, q[i]) * d[i] * d[i]))
    # E.M^-1.E: E_1 = -c v2^2 sin(q1 - q2) - V1'(q1), E_2 = c v1^2 sin(q1 - q2) - V2'(q2); the squares ...
    for i, j in ((0, 1), (1, 0)):
        out.append(_term(f"sin(q1-q2)**2*Dtq{j + 1}**4", lambda q, d, x, j=j: sd(q, x) ** 2 * d[j] ** 4))
        for f in trig:
            name = f"sin(q1-q2)*{f}(q{i + 1})*Dtq{j + 1}**2"
            out.append(_term(name, lambda q, d, x, i=i, j=j, f=f: sd(q, x) * trig[f](x, q[i]) * d[j] ** 2))
        for f, g in (("sin", "sin"), ("sin", "cos"), ("cos", "cos")):
            name = f"{f}(q{i + 1})*{g}(q{i + 1})"
            out.append(_term(name, lambda q, d, x, i=i, f=f, g=g: trig[f](x, q[i]) * trig[g](x, q[i])))
    # ... and the cross product E_1 E_2 cos(q1 - q2)
    out.append(
        _term("cos(q1-q2)*sin(q1-q2)**2*Dtq1**2*Dtq2**2", lambda q, d, x: cd(q, x) * sd(q, x) ** 2 * (d[0] * d[1]) ** 2)
    )
    for i in (1, 0):
        for f in trig:
            name = f"cos(q1-q2)*sin(q1-q2)*{f}(q{i + 1})*Dtq{i + 1}**2"
            out.append(_term(name, lambda q, d, x, i=i, f=f: cd(q, x) * sd(q, x) * trig[f](x, q[i]) * d[i] ** 2))
    for f in trig:
        for g in trig:
            name = f"cos(q1-q2)*{f}(q1)*{g}(q2)"
            out.append(_term(name, lambda q, d, x, f=f, g=g: cd(q, x) * trig[f](x, q[0]) * trig[g](x, q[1])))
    return out


#: The number of correction terms :func:`correction_library` adds.
CORRECTIONS = 28


def correction_library(base: str) -> Library:
    """``base`` (a shorthand string) and the 28 correction terms."""
    # Marked saveable (it is not: its label cannot be parsed back) so that the model takes the closed-form and numpy
    # derivatives of its terms' sympy forms, as a family of the package would; a library of user functions is
    # differentiated by autograd instead (about 100x slower to serve). The benchmark never saves it.
    return Library([*Library.parse(base).families, Family("corrections", lambda n, m: _terms(), saveable=True)])
