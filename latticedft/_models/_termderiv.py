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
    rows by the spacing).

    The derivatives are scattered into place by a few indexed operations over all of them (:class:`_Plan`), each
    entry of a Hessian block summed in the order of the maps and of ``rule.second``, as one addition per term
    would sum them."""
    k, m = cells.shape[-2], cells.shape[-1]
    lead = cells.shape[:-2]
    scale = [1.0] + [1.0 / h for h in spacing]
    plan = _plan(rule, maps, scale, pairs, m, n_terms, cells)
    d_out = cells.new_zeros(*lead, k, m, n_terms) if first else None
    hessians = []
    nf = len(rule.first)
    for a_map in maps:
        w = torch.einsum("rk,...km->...rm", a_map, cells)
        args = [w[..., r, i] / spacing[r - 1] if r else w[..., r, i] for r in range(len(scale)) for i in range(m)]
        values = rule.fn(*args)
        if d_out is not None:
            grad = cells.new_zeros(*lead, rule.n_vars * n_terms)
            if nf:
                grad[..., plan.first_at] = _stacked(values[:nf], lead, cells) * plan.first_scale
            d_out += torch.einsum("ra,...ric->...aic", a_map, grad.unflatten(-1, (len(scale), m, n_terms)))
        if pairs and len(values) > nf:
            hessians.append(_stacked(values[nf:], lead, cells) * plan.second_scale)
    blocks = {}
    for p in pairs:
        flat = cells.new_zeros(*lead, m * m * n_terms)
        if hessians:
            h = hessians[0] if len(hessians) == 1 else torch.cat(hessians, -1)
            for src, coef, at in plan.scatter[p]:  # each round adds to distinct entries
                flat.index_add_(-1, at, h[..., src] * coef)
        blocks[p] = flat.unflatten(-1, (m, m, n_terms))
    count = len(maps)
    if count > 1:
        d_out = None if d_out is None else d_out / count
        blocks = {p: b / count for p, b in blocks.items()}
    return d_out, blocks


def _stacked(values: Sequence[Any], lead: torch.Size, like: torch.Tensor) -> torch.Tensor:
    """The derivative values (tensors over the cells, or numbers where a derivative is constant) stacked along a
    last axis."""
    full = [
        like.new_full(lead, v) if not isinstance(v, torch.Tensor) else v if v.shape == lead else v.expand(lead)
        for v in values
    ]
    return torch.stack(full, -1)


@dataclass(frozen=True)
class _Plan:
    """Where :func:`closed_derivatives` puts each derivative: ``first_at`` the flat index ``v C + c`` of each of
    ``rule.first`` (scaled by ``first_scale``, the spacing's factor of its row), ``second_scale`` the factor of
    each of ``rule.second``; per pair, ``scatter``: rounds of ``(source, coefficient, entry)``, the sources
    indexing the second derivatives of every map in turn and the entries the flat ``(m, m, C)`` block, each
    round's entries distinct and the rounds in the order in which a term-by-term sum adds them."""

    first_at: torch.Tensor
    first_scale: torch.Tensor
    second_scale: torch.Tensor
    scatter: dict[tuple[int, int], list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]]


_PLANS: dict[tuple[Any, ...], tuple[TermDerivatives, _Plan]] = {}


def _plan(
    rule: TermDerivatives,
    maps: Sequence[torch.Tensor],
    scale: list[float],
    pairs: Sequence[tuple[int, int]],
    m: int,
    n_terms: int,
    like: torch.Tensor,
) -> _Plan:
    """The :class:`_Plan` of ``rule`` on ``maps`` (kept: a few per library)."""
    values = [a.detach().cpu().tolist() for a in maps]
    key = (id(rule), str(values), tuple(scale), tuple(pairs), m, n_terms, like.dtype, str(like.device))
    if key not in _PLANS:  # the rule is held with its plan, so its id stays its own
        _PLANS[key] = (rule, _make_plan(rule, values, scale, pairs, m, n_terms, like))
    return _PLANS[key][1]


def _make_plan(
    rule: TermDerivatives,
    maps: list[list[list[float]]],
    scale: list[float],
    pairs: Sequence[tuple[int, int]],
    m: int,
    n_terms: int,
    like: torch.Tensor,
) -> _Plan:
    def index(x: list[int]) -> torch.Tensor:
        return torch.tensor(x, dtype=torch.long, device=like.device)

    def real(x: list[float]) -> torch.Tensor:
        return torch.tensor(x, dtype=like.dtype, device=like.device)

    ns = len(rule.second)
    scatter = {}
    for a, b in pairs:
        rounds: list[tuple[list[int], list[float], list[int]]] = []
        seen: dict[int, int] = {}
        for j, a_map in enumerate(maps):
            for s, (v, u, c) in enumerate(rule.second):
                (rv, iv), (ru, iu) = divmod(v, m), divmod(u, m)
                adds = [(a_map[rv][a] * a_map[ru][b], (iv * m + iu) * n_terms + c)]
                if v != u:
                    adds.append((a_map[ru][a] * a_map[rv][b], (iu * m + iv) * n_terms + c))
                for coef, at in adds:
                    r = seen.get(at, 0)
                    seen[at] = r + 1
                    if r == len(rounds):
                        rounds.append(([], [], []))
                    rounds[r][0].append(j * ns + s)
                    rounds[r][1].append(coef)
                    rounds[r][2].append(at)
        scatter[(a, b)] = [(index(src), real(coef), index(at)) for src, coef, at in rounds]
    return _Plan(
        index([v * n_terms + c for v, c in rule.first]),
        real([scale[v // m] for v, _ in rule.first]),
        real([scale[v // m] * scale[u // m] for v, u, _ in rule.second]),
        scatter,
    )
