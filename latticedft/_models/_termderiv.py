"""Closed-form derivatives of a sparse library's terms, for the exact solve.

Each term is a function of its inputs ``w``: the field's value ``q_i`` (at a stencil point, or the stencil
mean) and its discrete derivatives ``D_k q_i``, all linear in the cell's values (``w = A x``). Its sympy form
(:func:`latticedft._models._terms.term_forms`) is differentiated once and twice in ``w`` by sympy, the
derivatives are evaluated by torch, and the chain rule through ``A`` gives the derivatives in the cell's
values that :meth:`LinearLagrangian.feature_derivatives` returns. This replaces forward-mode automatic
differentiation through the terms (one pass per stencil value and pair), which costs far more than the
terms themselves; the derivatives agree with it to round-off.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from ._terms import Term, term_forms

__all__ = ["TermDerivatives", "term_derivatives"]

#: The torch functions a lambdified term derivative may call.
_TORCH = {"sin": torch.sin, "cos": torch.cos, "exp": torch.exp, "log": torch.log, "sqrt": torch.sqrt}


@dataclass(frozen=True)
class TermDerivatives:
    """Every term's nonzero first and second derivatives in its ``V = (n + 1) m`` inputs (``v = r m + i``: row
    ``r`` of ``w``, 0 the field's value, ``1 + k`` its derivative along axis ``k``, component ``i``).

    ``fn(*w)`` returns the values of ``first`` then ``second``, in order: ``first[j] = (v, c)`` names
    ``d T_c / d w_v``, ``second[j] = (v, u, c)`` with ``v <= u`` names ``d^2 T_c / d w_v d w_u``."""

    n_vars: int
    first: list[tuple[int, int]]
    second: list[tuple[int, int, int]]
    fn: Callable[..., Sequence[Any]]


@dataclass(frozen=True)
class _Derived:
    """What sympy made of a list of terms: the inputs ``w``, the indices of :class:`TermDerivatives`, and the
    derivatives' expressions in that order."""

    w: list[Any]
    first: list[tuple[int, int]]
    second: list[tuple[int, int, int]]
    exprs: list[Any]
    hessians: list[Any]


_CACHE: dict[tuple[tuple[str, ...], int, int], TermDerivatives | None] = {}


def term_derivatives(terms: Sequence[Term], n: int, m: int) -> TermDerivatives | None:
    """The derivatives of ``terms`` on a lattice of ``n`` axes and ``m`` components (None when a term has no
    sympy form). Built once per list of term names: the named families' names fix their functions."""
    key = (tuple(t.name for t in terms), n, m)
    if key not in _CACHE:
        _CACHE[key] = _build(terms, n, m)
    return _CACHE[key]


def _derive(terms: Sequence[Term], n: int, m: int) -> _Derived | None:
    """The symbols ``w``, the nonzero first and second derivatives' indices and their sympy expressions."""
    import sympy

    q = [sympy.Symbol(f"q_{i}", real=True) for i in range(m)]
    d = [[sympy.Symbol(f"d_{k}_{i}", real=True) for i in range(m)] for k in range(n)]
    forms = term_forms(terms, q, d)
    if forms is None:
        return None
    w = q + [s for row in d for s in row]
    first: list[tuple[int, int]] = []
    second: list[tuple[int, int, int]] = []
    exprs: list[Any] = []
    hessians: list[Any] = []
    for c, form in enumerate(forms):
        grads = [sympy.diff(form, s) for s in w]
        for v, g in enumerate(grads):
            if g != 0:
                first.append((v, c))
                exprs.append(g)
        for v, u in itertools.combinations_with_replacement(range(len(w)), 2):
            h = sympy.diff(grads[v], w[u]) if grads[v] != 0 else 0
            if h != 0:
                second.append((v, u, c))
                hessians.append(h)
    return _Derived(w, first, second, exprs, hessians)


def _build(terms: Sequence[Term], n: int, m: int) -> TermDerivatives | None:
    import sympy

    got = _derive(terms, n, m)
    if got is None:
        return None
    fn = sympy.lambdify(got.w, got.exprs + got.hessians, modules=[_TORCH, "math"])
    return TermDerivatives(len(got.w), got.first, got.second, fn)


def closed_derivatives(
    rule: TermDerivatives,
    maps: Sequence[torch.Tensor],
    cells: torch.Tensor,
    spacing: Sequence[float],
    pairs: Sequence[tuple[int, int]],
    first: bool,
    n_terms: int,
) -> tuple[torch.Tensor | None, dict[tuple[int, int], torch.Tensor]]:
    """:meth:`LinearLagrangian.feature_derivatives` of ``mean over A in maps of T(A x)``: each map ``A``
    ``(n + 1, K)`` gives the terms' inputs on the cells ``x`` ``(..., K, m)`` (before dividing the derivative
    rows by the spacing)."""
    k, m = cells.shape[-2], cells.shape[-1]
    scale = [1.0] + [1.0 / h for h in spacing]
    d_out = cells.new_zeros(*cells.shape[:-2], k, m, n_terms) if first else None
    blocks = {p: cells.new_zeros(*cells.shape[:-2], m, m, n_terms) for p in pairs}
    for a_map in maps:
        w = torch.einsum("rk,...km->...rm", a_map, cells)
        args = [w[..., r, i] / spacing[r - 1] if r else w[..., r, i] for r in range(len(scale)) for i in range(m)]
        values = rule.fn(*args)
        nf = len(rule.first)
        if d_out is not None:
            grad = cells.new_zeros(*cells.shape[:-2], rule.n_vars, n_terms)
            for (v, c), val in zip(rule.first, values[:nf]):
                grad[..., v, c] = val * scale[v // m]
            grad = grad.unflatten(-2, (len(scale), m))
            d_out += torch.einsum("ra,...ric->...aic", a_map, grad)
        for (v, u, c), val in zip(rule.second, values[nf:]):
            (rv, iv), (ru, iu) = divmod(v, m), divmod(u, m)
            h = val * (scale[rv] * scale[ru])
            for a, b in pairs:
                blocks[(a, b)][..., iv, iu, c] += (a_map[rv, a] * a_map[ru, b]).item() * h
                if v != u:
                    blocks[(a, b)][..., iu, iv, c] += (a_map[ru, a] * a_map[rv, b]).item() * h
    count = len(maps)
    if count > 1:
        d_out = None if d_out is None else d_out / count
        blocks = {p: b / count for p, b in blocks.items()}
    return d_out, blocks
