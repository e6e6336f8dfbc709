"""Closed-form ``L_d`` as a sympy expression: what printing, the compiled DEL kernels and ``to_sympy`` share.

A model known in closed form (sparse term libraries, polynomials, features, analytic ``L_d``) describes one
cell's ``L_d`` as a :class:`SymbolicLd`: a sympy expression in the values of the field at the stencil's
points, one symbol per (stencil point, component). The symbols are those of :func:`cell_symbols`, so every
producer and consumer agrees on them without passing them around. sympy is imported only when a symbolic
form is built or read.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

__all__ = ["SymbolicLd", "cell_symbols", "symbol_name"]


def symbol_name(point: int, component: int) -> str:
    """The name of the symbol of stencil point ``point`` (its index in the stencil's offsets), component
    ``component``: ``u{point}_{component}``.

    >>> symbol_name(2, 0)
    'u2_0'
    """
    return f"u{point}_{component}"


def cell_symbols(k: int, m: int) -> tuple[tuple[Any, ...], ...]:
    """``K x m`` real sympy symbols, ``[point][component]``, named by :func:`symbol_name`.

    >>> cell_symbols(2, 1)
    ((u0_0,), (u1_0,))
    """
    import sympy

    return tuple(tuple(sympy.Symbol(symbol_name(p, c), real=True) for c in range(m)) for p in range(k))


@dataclass(frozen=True)
class SymbolicLd:
    """One cell's ``L_d`` in closed form.

    ``expr`` is a sympy expression in the symbols ``cell_symbols(len(offsets), m)``: the value of component
    ``c`` at stencil point ``offsets[p]`` is ``u{p}_{c}``. It is the model's own ``L_d`` (its scaling folded
    in), so that ``expr`` evaluated on a cell equals ``model(cell)`` to round-off. ``spacing`` is the lattice
    spacing the model was bound to (time first).
    """

    expr: Any
    offsets: tuple[tuple[int, ...], ...]
    m: int
    spacing: tuple[float, ...]

    @property
    def symbols(self) -> tuple[tuple[Any, ...], ...]:
        """The symbols of ``expr``, ``[point][component]``."""
        return cell_symbols(len(self.offsets), self.m)

    def flat_symbols(self) -> list[Any]:
        """The symbols point by point, component by component (the order of a cell ``(K, m)`` flattened)."""
        return [s for row in self.symbols for s in row]

    def latex(self) -> str:
        """``expr`` as LaTeX."""
        import sympy

        return str(sympy.latex(self.expr))

    def evaluate(self, cells: Sequence[Sequence[float]]) -> float:
        """``L_d`` on one cell ``(K, m)`` (a check of the expression against the model, not a serving path)."""
        import sympy

        subs = {s: float(cells[p][c]) for p, row in enumerate(self.symbols) for c, s in enumerate(row)}
        return float(sympy.N(self.expr.subs(subs)))


def del_equations(form: SymbolicLd, site_name: Any = None) -> list[Any]:
    """The discrete Euler-Lagrange equations ``L_d`` implies at a site ``x``, one expression per component
    (each ``= 0``): the sum over stencil points ``p`` of ``d L_d / d u_p`` on the cell anchored at
    ``x - offsets[p]``. The field at site ``x + s`` is the symbol ``site_name(s, component)`` (default
    ``"v[s]_c"``).

    >>> import sympy
    >>> u = cell_symbols(2, 1)
    >>> form = SymbolicLd((u[1][0] - u[0][0]) ** 2 / 2, ((0,), (1,)), 1, (1.0,))
    >>> del_equations(form)
    [-v[-1]_0 + 2*v[0]_0 - v[1]_0]
    """
    import sympy

    def name(shift: tuple[int, ...], c: int) -> str:
        return site_name(shift, c) if site_name is not None else f"v[{','.join(str(s) for s in shift)}]_{c}"

    syms = form.symbols
    offsets = [tuple(o) for o in form.offsets]
    out = []
    for c in range(form.m):
        total = sympy.Integer(0)
        for p, op in enumerate(offsets):
            subs = {
                syms[q][j]: sympy.Symbol(name(tuple(a - b for a, b in zip(oq, op)), j), real=True)
                for q, oq in enumerate(offsets)
                for j in range(form.m)
            }
            total += sympy.diff(form.expr, syms[p][c]).xreplace(subs)
        out.append(total)
    return out
