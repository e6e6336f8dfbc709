"""The polynomial ``L_d``'s gradient and Hessian blocks in numpy, fused: no autograd, no per-call table lookups.

Serving a 1D trajectory evaluates a handful of cells per step, where the cost of a torch call (dispatch,
autograd bookkeeping, ``index_select`` of the basis tables) dwarfs the arithmetic. Here everything that
depends only on the model is precomputed once: per variable ``v`` a matrix ``M_v`` that maps the powers
``(1, z, z^2, ...)`` of the scaled variable straight to the basis factor of every term and its first two
derivatives (the coefficient matrix of the basis with its columns already picked by the term's exponent of
``v``). A call then takes the powers by cumulative products, one matrix product per variable, the products
of the other factors (prefix and suffix products, no division), and one product with ``coef``.

Where the monomials ``prod_v z_v^a_v`` (each variable up to its own largest exponent) are few, the
coefficients are folded once more, onto those monomials and through the chain rule: a call is then one
product of the monomials with a fixed matrix. n-D slice-Newton evaluates whole slices of cells at a time;
from ``_MANY_CELLS`` cells the cells run along the last axis and only the monomials some derivative needs
are formed (:func:`_many_cells`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .._options import option
from ._polybasis import _VANDERMONDE_MAX_DEGREE, _coefficient_matrix_f64, _pairs

if TYPE_CHECKING:
    from ._polynomial import PolynomialLagrangian

#: ``fn(cells) -> (grad, blocks)``: ``cells`` ``(B, K, m)``; ``grad`` ``(B, K, m)``; one ``(B, m, m)`` block per pair.
NumpyDerivatives = Callable[[np.ndarray], tuple[np.ndarray, list[np.ndarray]]]


def fused_factor_matrix(coefficients: np.ndarray, exponents: np.ndarray, order: int) -> np.ndarray:
    """``(V, D+1, (order+1) C)``: per variable, powers of ``z`` -> the basis factor of each term and its first
    ``order`` derivatives (``coefficients`` is the ``(D+1, 3 (D+1))`` matrix of the basis tables, ``exponents``
    the ``(C, V)`` exponent of each variable in each term)."""
    width = coefficients.shape[0]
    cols = np.arange(order + 1)[:, None, None] * width + exponents.T[None]  # (order+1, V, C)
    return np.stack([coefficients[:, cols[:, v].reshape(-1)] for v in range(exponents.shape[1])])


def _products(val: np.ndarray) -> tuple[list[np.ndarray | None], list[np.ndarray | None]]:
    """Prefix and suffix products of the factors ``val`` ``(V, B, C)`` (``None`` for an empty product)."""
    nvar = val.shape[0]
    pre: list[np.ndarray | None] = [None] * nvar
    suf: list[np.ndarray | None] = [None] * nvar
    for v in range(1, nvar):
        p = pre[v - 1]
        pre[v] = val[v - 1] if p is None else p * val[v - 1]
    for v in range(nvar - 2, -1, -1):
        s = suf[v + 1]
        suf[v] = val[v + 1] if s is None else s * val[v + 1]
    return pre, suf


def _times(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray | None:
    return b if a is None else a if b is None else a * b


def _product(out: np.ndarray, a: np.ndarray, b: np.ndarray | None) -> None:
    """``out = a * b`` (``b`` None: 1)."""
    if b is None:
        if out is not a:
            out[...] = a
    else:
        np.multiply(a, b, out=out)


def _combos(nvar: int) -> list[tuple[int, ...]]:
    """Derivative orders per variable: every first derivative, then the second ones in the order of ``_pairs``."""
    out = [tuple(int(u == v) for u in range(nvar)) for v in range(nvar)]
    for v in range(nvar):
        for w in range(v, nvar):
            j = [0] * nvar
            j[v] += 1
            j[w] += 1
            out.append(tuple(j))
    return out


def folded_tensor(
    basis_rows: np.ndarray, exponents: np.ndarray, coef: np.ndarray, second: bool, widths: Sequence[int] | None = None
) -> np.ndarray:
    """``(combos, *widths)``: per derivative order of :func:`_combos`, the coefficients of that derivative of
    ``L = sum_c coef_c prod_v P_{e_vc}(z_v)`` on the monomials ``prod_v z_v^a_v`` (``basis_rows[i, k]``: the
    coefficient of ``z^i`` in ``P_k``; ``widths[v]``: the powers ``a_v < widths[v]`` kept, at least one more than
    the largest exponent of ``v``; all of ``basis_rows``' rows by default)."""
    c, nvar = exponents.shape
    shape = tuple(int(x) for x in widths) if widths is not None else (basis_rows.shape[0],) * nvar
    full = np.zeros(shape)
    for t in range(c):  # the monomial coefficients of L: sum over terms of outer products
        outer = np.array(coef[t])
        for v in range(nvar):
            outer = np.multiply.outer(outer, basis_rows[: shape[v], exponents[t, v]])
        full += outer
    combos = _combos(nvar) if second else _combos(nvar)[:nvar]
    out = np.zeros((len(combos),) + shape)
    for q, js in enumerate(combos):
        if any(j >= w for j, w in zip(js, shape)):  # a derivative above the variable's degree: zero
            continue
        shifted = full[tuple(slice(j, None) for j in js)]  # A[a + j] ...
        for v, j in enumerate(js):  # ... times (a + j)! / a! per variable
            a = np.arange(shape[v] - j)
            fac = np.ones(shape[v] - j)
            for s in range(1, j + 1):
                fac = fac * (a + s)
            axes = [1] * nvar
            axes[v] = shape[v] - j
            shifted = shifted * fac.reshape(axes)
        out[q][tuple(slice(0, w - j) for j, w in zip(js, shape))] = shifted
    return out


#: Cells per call from which the derivatives are evaluated cells-last (:func:`_many_cells`), in chunks of
#: ``_MANY_CHUNK`` cells (the intermediates of a chunk stay in cache).
_MANY_CELLS = 256
_MANY_CHUNK = 2048


def _many_cells(
    g_chain: np.ndarray, widths: Sequence[int], w: np.ndarray, shift: np.ndarray
) -> Callable[[np.ndarray], np.ndarray]:
    """``flat (B, K m) -> (B, cols)``: ``monomials @ g_chain`` for many cells, cells along the last axis (every
    product runs over a long contiguous row).

    Only the monomials that some column needs count (a polynomial of low degree in the differences needs few
    of the ``prod(widths)``). Each is the power of the widest variable (the head) times a product of the
    others' powers (its tail); the columns are ``sum_tail tail * (C_tail @ powers of the head)``: one matrix
    product for all tails, then one weighted sum per chunk."""
    keep = np.nonzero(np.any(g_chain != 0, axis=1))[0]
    expo = np.stack(np.unravel_index(keep, tuple(widths)))  # (V, kept): the exponents of each kept monomial
    nvar = len(widths)
    head = int(np.argmax(widths))
    others = [v for v in range(nvar) if v != head]
    if others:
        tails, tail_of = np.unique(expo[others].T, axis=0, return_inverse=True)  # (ntail, V-1)
    else:
        tails, tail_of = np.zeros((1, 0), dtype=int), np.zeros(keep.size, dtype=int)
    cols = g_chain.shape[1]
    per_tail = np.zeros((len(tails), cols, widths[head]))  # C_tail: powers of the head -> columns
    per_tail[tail_of.reshape(-1), :, expo[head]] = g_chain[keep]
    stacked = per_tail.reshape(-1, widths[head])

    nt, wh = len(tails), widths[head]

    def evaluate(flat: np.ndarray) -> np.ndarray:
        b = flat.shape[0]
        out = np.empty((cols, b))
        zt = np.dot(w.T, flat.T) - shift[:, None]  # (V, cells): the scaled variables
        size = min(b, _MANY_CHUNK)
        hp = np.empty((wh, size))  # powers of the head, then of each other variable (buffers reused per chunk)
        op = [np.empty((widths[v], size)) for v in others]
        tail = np.empty((nt, size))
        buf = np.empty(nt * cols * size)  # the head's polynomials per tail and column
        hp[0] = 1.0
        for q in op:
            q[0] = 1.0
        for lo in range(0, b, _MANY_CHUNK):
            n = min(b, lo + _MANY_CHUNK) - lo
            if n < size:
                hp, op, tail = hp[:, :n], [q[:, :n] for q in op], tail[:, :n]
            for q, v in zip([hp, *op], [head, *others]):
                for i in range(1, q.shape[0]):
                    np.multiply(q[i - 1], zt[v, lo : lo + n], out=q[i])
            tail[...] = 1.0
            for j, q in enumerate(op):
                tail *= q[tails[:, j]]
            part = buf[: nt * cols * n].reshape(nt * cols, n)
            np.dot(stacked, hp, out=part)
            np.einsum("tcb,tb->cb", part.reshape(nt, cols, n), tail, out=out[:, lo : lo + n])
        return out.T

    return evaluate


@dataclass(frozen=True)
class _Folded:
    """What a folded evaluation needs: ``z = x.flat @ w - shift`` (``(K m, V)``, ``(V,)``), the powers of each
    variable that occur (``widths``), the matrix from the monomials to ``[dL/dx | blocks]`` and the shape; that
    matrix's two factors: ``g`` from the monomials to the derivatives in the scaled variables ``[dL/dz |
    d2L/dz_v dz_w]`` and ``chain`` from those to ``[dL/dx | blocks]`` (``g_chain = g @ chain``)."""

    w: np.ndarray
    shift: np.ndarray
    widths: tuple[int, ...]
    g_chain: np.ndarray
    k: int
    m: int
    g: np.ndarray | None = None
    chain: np.ndarray | None = None


def stacked_numpy_derivatives(
    members: Sequence[PolynomialLagrangian], pairs: Sequence[tuple[int, int]]
) -> NumpyDerivatives | None:
    """The numpy closed forms of polynomial ``members`` side by side (member ``n`` sees components
    ``n m .. (n + 1) m - 1`` of the cells; its blocks sit on the diagonal), evaluated together: one batched
    product for all members where each member's would be one (a few cells: 1D serving). ``None`` unless every
    member folds its coefficients with the same powers (same orders and stencil); from ``_MANY_CELLS`` cells
    each member is evaluated on its own (n-D slices)."""
    built = [_numpy_forms(mem, pairs) for mem in members]
    forms = [f for f, _ in built if f is not None]
    parts = [p for _, p in built if p is not None]  # a folded member has its forms too
    if len(parts) < len(built):
        return None
    first = parts[0]
    if any(p.widths != first.widths or p.k != first.k or p.m != first.m for p in parts):
        return None
    n, k, m, nvar, npairs = len(parts), first.k, first.m, len(first.widths), len(pairs)
    w = np.stack([p.w for p in parts])  # (N, K m, V)
    shift = np.stack([p.shift for p in parts])[:, None, :]  # (N, 1, V)
    g_chain = np.stack([p.g_chain for p in parts])  # (N, monomials, cols)
    widths, width = first.widths, max(first.widths)
    each = side_by_side(forms, m, npairs)

    def together(cells: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        b = cells.shape[0]
        if b >= _MANY_CELLS:
            return each(cells)
        flat = cells.reshape(b, k, n, m).transpose(2, 0, 1, 3).reshape(n, b, k * m)
        pw = np.empty((nvar, n, b, width))
        pw[..., 0] = 1.0
        pw[..., 1:] = (np.matmul(flat, w) - shift).transpose(2, 0, 1)[..., None]
        np.multiply.accumulate(pw, axis=-1, out=pw)
        prods = pw[0, :, :, : widths[0]]  # (N, B, monomials so far)
        for v in range(1, nvar):
            prods = (prods[..., :, None] * pw[v, :, :, None, : widths[v]]).reshape(n, b, -1)
        out = np.matmul(prods, g_chain)  # (N, B, cols)
        grad = out[..., : k * m].reshape(n, b, k, m).transpose(1, 2, 0, 3).reshape(b, k, n * m)
        blocks = [
            _diagonal(out[..., k * m + q * m * m : k * m + (q + 1) * m * m].reshape(n, b, m, m)) for q in range(npairs)
        ]
        return grad, blocks

    return together


def side_by_side(forms: Sequence[NumpyDerivatives], m: int, npairs: int) -> NumpyDerivatives:
    """The closed forms of members that never couple, one call each: member ``n`` sees components
    ``n m .. (n + 1) m - 1`` of the cells; gradients side by side, blocks on the diagonal."""

    def derivatives(cells: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        found = [f(cells[..., j * m : (j + 1) * m]) for j, f in enumerate(forms)]
        grad = np.concatenate([g for g, _ in found], axis=-1)
        return grad, [_diagonal(np.stack([b[q] for _, b in found])) for q in range(npairs)]

    return derivatives


def _diagonal(blocks: np.ndarray) -> np.ndarray:
    """``(N, B, m, m)`` -> ``(B, N m, N m)``, the ``N`` blocks on the diagonal."""
    n, b, m, _ = blocks.shape
    diagonal: np.ndarray = np.einsum("nbij,nl->bnilj", blocks, np.eye(n))
    return diagonal.reshape(b, n * m, n * m)


def numpy_derivatives(model: PolynomialLagrangian, pairs: Sequence[tuple[int, int]]) -> NumpyDerivatives | None:
    """``fn(cells) -> (dL/dx, [d^2 L / dx_a dx_b for (a, b) in pairs])`` for ``model`` as it is now (its
    coefficients and scaling are copied: call again after learning). ``None`` above degree 12, where the
    basis is evaluated by its recurrence (the torch closed forms serve then)."""
    return _numpy_forms(model, pairs)[0]


def _numpy_forms(
    model: PolynomialLagrangian, pairs: Sequence[tuple[int, int]]
) -> tuple[NumpyDerivatives | None, _Folded | None]:
    """:func:`numpy_derivatives` and, where the coefficients are folded onto the monomials, what the folded
    evaluation is made of (for :func:`stacked_numpy_derivatives`)."""
    deg = int(max(model.orders))
    if deg > _VANDERMONDE_MAX_DEGREE:
        return None, None
    m = model.m
    exps = model.exponents.detach().cpu().numpy()
    nvar, width, c = exps.shape[1], deg + 1, exps.shape[0]
    coef = model.coef.detach().cpu().numpy().astype(np.float64)
    center = model.center.detach().cpu().numpy()
    half = model.halfwidth.detach().cpu().numpy()
    proj = model.proj.detach().cpu().numpy().astype(np.float64)  # (n + 1, K): mean and differences
    k = proj.shape[1]
    p = np.einsum("pk,ij->kipj", proj, np.eye(m)).reshape(k * m, nvar)  # z = (x.flat @ p - center) / half
    w = p / half  # dz/dx
    pair_mats = _pair_matrices(w.reshape(k, m, nvar), pairs)
    ncombo = nvar + (nvar * (nvar + 1) // 2 if pairs else 0)
    widths = [int(x) + 1 for x in exps.max(axis=0)] if c else [1] * nvar  # powers of each variable that occur
    if int(np.prod(widths)) <= option("folded_max_powers"):
        basis_rows = _coefficient_matrix_f64(model.basis, deg).numpy()[:, :width]
        g = folded_tensor(basis_rows, exps, coef, bool(pairs), widths).reshape(ncombo, -1).T  # (monomials, combos)
        return _folded_forms(g, w, center / half, widths, width, pair_mats, k, m)
    fused = fused_factor_matrix(_coefficient_matrix_f64(model.basis, deg).numpy(), exps, 2)  # (V, width, 3C)
    return _term_forms(fused, coef, p, center, half, pair_mats, k, m, bool(pairs)), None


def _pair_matrices(rows: np.ndarray, pairs: Sequence[tuple[int, int]]) -> list[np.ndarray]:
    """Per pair ``(a, b)``: the ``(npairs, m m)`` matrix that takes the second derivatives ``d2L/dz_v dz_w``
    (``v <= w``) to the block ``d2L/dx_a dx_b`` (block = this row vector @ the matrix); ``rows`` is ``dz/dx``
    as ``(K, m, V)``."""
    m, nvar = rows.shape[1], rows.shape[2]
    vw = _pairs(nvar)
    pair_mats = []
    for a, b in pairs:
        full = np.einsum("iv,jw->vwij", rows[a], rows[b])
        pair_mats.append(
            np.stack([full[v, u] + full[u, v] if v != u else full[v, v] for v, u in vw]).reshape(-1, m * m)
        )
    return pair_mats


def _folded_forms(
    g: np.ndarray,
    w: np.ndarray,
    shift: np.ndarray,
    widths: list[int],
    width: int,
    pair_mats: list[np.ndarray],
    k: int,
    m: int,
) -> tuple[NumpyDerivatives, _Folded]:
    """The forms evaluated from the coefficients folded onto the monomials: ``g`` takes the monomials to
    ``[dL/dz | d2L/dz_v dz_w]``, ``z = x.flat @ w - shift``, a variable has at most ``width`` powers."""
    nvar, ncombo, npairs = len(widths), g.shape[1], len(pair_mats)
    nb = npairs * m * m
    chain = np.zeros((ncombo, k * m + nb))  # the chain rule: dL/dz -> dL/dx, d2L/dz2 -> the blocks
    chain[:nvar, : k * m] = w.T
    if pair_mats:
        chain[nvar:, k * m :] = np.concatenate(pair_mats, axis=1)
    g_chain = g @ chain  # monomials -> [dL/dx | blocks]: one product per call
    chunk = max(1, option("folded_chunk") // int(np.prod(widths)))
    accumulate = np.multiply.accumulate

    many = _many_cells(g_chain, widths, w, shift)

    def folded(cells: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        b = cells.shape[0]
        flat = cells.reshape(b, k * m)
        out = many(flat) if b >= _MANY_CELLS else np.empty((b, k * m + nb))
        for lo in range(0, b if b < _MANY_CELLS else 0, chunk):
            bc = min(b - lo, chunk)
            pw = np.empty((nvar, bc, width))  # powers (1, z, z^2, ...) of the scaled variables: cumulative products
            pw[..., 0] = 1.0
            pw[..., 1:] = (np.dot(flat[lo : lo + bc], w) - shift).T[..., None]
            accumulate(pw, axis=-1, out=pw)
            prods = pw[0, :, : widths[0]]  # every monomial prod_v z_v^a_v
            for v in range(1, nvar):
                prods = (prods[:, :, None] * pw[v, :, None, : widths[v]]).reshape(bc, -1)
            out[lo : lo + bc] = np.dot(prods, g_chain)
        grad = out[:, : k * m].reshape(b, k, m)
        return grad, [out[:, k * m + q * m * m : k * m + (q + 1) * m * m].reshape(b, m, m) for q in range(npairs)]

    return folded, _Folded(w, shift, tuple(widths), g_chain, k, m, g, chain)


def _term_forms(
    fused: np.ndarray,
    coef: np.ndarray,
    p: np.ndarray,
    center: np.ndarray,
    half: np.ndarray,
    pair_mats: list[np.ndarray],
    k: int,
    m: int,
    with_pairs: bool,
) -> NumpyDerivatives:
    """The forms evaluated term by term with the fused factor matrices ``fused`` (``(V, width, 3C)``);
    ``z = (x.flat @ p - center) / half``."""
    nvar, width, c = fused.shape[0], fused.shape[1], fused.shape[2] // 3
    w = p / half  # dz/dx
    nrows = nvar + (nvar * (nvar + 1) // 2 if with_pairs else 0)

    def derivatives(cells: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        b = cells.shape[0]
        pw = np.empty((nvar, b, width))  # powers (1, z, z^2, ...) of the scaled variables, by cumulative products
        pw[..., 0] = 1.0
        pw[..., 1:] = ((cells.reshape(b, k * m) @ p - center) / half).T[..., None]
        np.cumprod(pw, axis=-1, out=pw)
        f = pw @ fused  # (V, B, 3C): values, first and second derivatives of every term's factors
        val, d1, d2 = f[..., :c], f[..., c : 2 * c], f[..., 2 * c :]
        pre, suf = _products(val)
        excl = [_times(pre[v], suf[v]) for v in range(nvar)]
        t = np.empty((nrows, b, c))  # d phi / dz_v, then d^2 phi / dz_v dz_u (v <= u), per term
        for v in range(nvar):
            _product(t[v], d1[v], excl[v])
        j = nvar
        for v in range(nvar if with_pairs else 0):
            _product(t[j], d2[v], excl[v])
            j += 1
            between = pre[v]
            for u in range(v + 1, nvar):
                if u > v + 1:
                    between = _times(between, val[u - 1])
                np.multiply(d1[v], d1[u], out=t[j])
                _product(t[j], t[j], _times(between, suf[u]))
                j += 1
        s = t @ coef  # (V [+ npairs], B)
        grad = (w @ s[:nvar]).T.reshape(b, k, m)
        blocks = [(s[nvar:].T @ mat).reshape(b, m, m) for mat in pair_mats]
        return grad, blocks

    return derivatives
