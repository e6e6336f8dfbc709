"""The double pendulum's exact-step corrections, for :mod:`benchmarks.discovery_gap` (``--corrections``).

One step of the exact flow of ``L = v.M(q).v/2 - V(q)`` has, in the trapezoid rule (``at = "average"``), the
discrete Lagrangian ``h L_avg - h^3/12 v.L_qq.v - h^3/24 E.M^-1.E + O(h^5)`` with ``v = (q1 - q0)/h`` and
``E = L_q - (d L_v/dq) v`` (the midpoint rule's ``h^3/24 (v.L_qq.v - E.M^-1.E)`` less the trapezoid rule's own
``h^3/8 v.L_qq.v``). :func:`exact_step_ld` writes it for an ODE system; :func:`correction_library` is the span of
these corrections over the family the coupled library holds for two pendulums, ``L = a v1^2 + b v2^2 + c v1 v2
cos(q1 - q2) - V1(q1) - V2(q2)`` with ``V_i`` in ``trig:1``, the factor ``1/det M`` of ``M^-1`` taken as a
constant: 28 terms, the library shorthand ``coupledstep``, on top of
:data:`latticedft._select.COUPLED_LIBRARY`.
"""

from __future__ import annotations

from typing import Any

import sympy

from latticedft._models._library import Library
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


#: The number of correction terms :func:`correction_library` adds.
CORRECTIONS = 28


def correction_library(base: str) -> Library:
    """``base`` (a shorthand string) and the 28 correction terms (the shorthand ``coupledstep``)."""
    return Library.parse(f"{base} + coupledstep")
