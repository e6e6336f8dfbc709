"""Compiled kernels of a dense polynomial ``L_d`` folded into data (``latticedft._serve._folded``).

One numba module serves every polynomial, whatever its orders, stencil, dimension and components: the
coefficients, exponents and scalings are arrays it reads. ``folded_cells_kernel`` adds, per class of
polynomial (variables and columns), the cell pass with its monomial loop unrolled (and
``latticedft._kernel_zchain``, per pattern, the pass in the scaled variables). Modules are written into
and loaded from the kernel cache of ``latticedft._kernel``, and a module that cannot be built leaves the
polynomial on its numpy forms with one info line.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from typing import Any

import numpy as np

from ._kernel import _VERSION, cached_module, write_module

__all__ = ["folded_cells_kernel", "folded_kernels", "horner_cells_kernel"]


#: The folded polynomial's kernels (:func:`folded_kernels`): one module for every polynomial, whatever its
#: orders, stencil, dimension and components, which it reads as data (the scaled variables ``z = x.flat @ w -
#: shift``, the exponents of the monomials some derivative needs, the matrix from those monomials to the
#: derivatives). Cells run along the innermost loops in chunks of ``_CHUNK``, as the numpy forms' cells-last
#: evaluation, so that each product runs over a contiguous row that the compiler vectorises.
_FOLDED_CELLS = """
@numba.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def chunk_variables(lo, hi, site_of, upper, w, shift, start, n, x, z, pw):
    # the stencil of cells start .. start + n from the flat slices into x, the scaled variables
    # z = x.flat @ w - shift, and their powers pw[v, e] = z[v]**e (e < pw.shape[1]); inlined, so that the
    # caller's floating-point flags hold for its sums
    m = lo.shape[1]
    for a in range(site_of.shape[0]):
        src = hi if upper[a] else lo
        for j in range(n):
            s = site_of[a, start + j]
            for c in range(m):
                x[a * m + c, j] = src[s, c]
    for v in range(w.shape[1]):
        for j in range(n):
            z[v, j] = 0.0
        for r in range(w.shape[0]):
            wr = w[r, v]
            if wr != 0.0:
                for j in range(n):
                    z[v, j] += x[r, j] * wr
        for j in range(n):
            z[v, j] -= shift[v]
            pw[v, 0, j] = 1.0
            pw[v, 1, j] = z[v, j]
        for e in range(2, pw.shape[1]):
            for j in range(n):
                pw[v, e, j] = pw[v, e - 1, j] * z[v, j]


@numba.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def chunk_buffers(lo, site_of, w, expo):
    # the buffers chunk_variables fills for one chunk of cells: the stencil's values x, the variables z and
    # their powers pw, up to the largest exponent in the rows of expo (at least the first)
    nvar = w.shape[1]
    wmax = 2
    for t in range(expo.shape[0]):
        for v in range(nvar):
            wmax = max(wmax, expo[t, v] + 1)
    x = np.empty((site_of.shape[0] * lo.shape[1], _CHUNK))
    return x, np.empty((nvar, _CHUNK)), np.empty((nvar, wmax, _CHUNK))


@numba.njit(cache=True, error_model='numpy', nogil=True)
def folded_cells(lo, hi, site_of, upper, w, shift, expo, gc, out):
    nvar = w.shape[1]
    ncell = site_of.shape[1]
    nmono = gc.shape[0]
    cols = gc.shape[1]
    ch = _CHUNK
    x, z, pw = chunk_buffers(lo, site_of, w, expo[:nmono])
    acc = np.empty((cols, ch))
    p = np.empty(ch)
    for start in range(0, ncell, ch):
        n = min(ch, ncell - start)
        chunk_variables(lo, hi, site_of, upper, w, shift, start, n, x, z, pw)
        for c in range(cols):
            for j in range(n):
                acc[c, j] = 0.0
{monomials}
        for j in range(n):
            for c in range(cols):
                out[start + j, c] = acc[c, j]


"""

#: The largest |value| of a flat array as torch's ``abs().max()`` takes it (a not-a-number wherever one is), in
#: eight lanes: a numba function of the folded kernel module, printed into the Krylov module too
#: (:mod:`latticedft._kernel_krylov`).
MAGNITUDE = """\
@numba.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def magnitude(a):
    # the largest |value| of a (flat), a not-a-number wherever one is (as torch's abs().max()), 0.0 when empty: in
    # eight running maxima and eight running sums held in scalars (registers: the loop vectorises); a NaN never
    # enters a maximum (x > top is false) but makes its sum NaN, as an infinity makes it infinite (or an overflow
    # of finite sizes: then the scalar pass finds no NaN), and such a sum is settled by a scalar pass
    n = a.shape[0]
    l0 = l1 = l2 = l3 = l4 = l5 = l6 = l7 = 0.0
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
    s = 0
    while s + 8 <= n:
        x0, x1, x2, x3 = abs(a[s]), abs(a[s + 1]), abs(a[s + 2]), abs(a[s + 3])
        x4, x5, x6, x7 = abs(a[s + 4]), abs(a[s + 5]), abs(a[s + 6]), abs(a[s + 7])
        l0 = x0 if x0 > l0 else l0
        l1 = x1 if x1 > l1 else l1
        l2 = x2 if x2 > l2 else l2
        l3 = x3 if x3 > l3 else l3
        l4 = x4 if x4 > l4 else l4
        l5 = x5 if x5 > l5 else l5
        l6 = x6 if x6 > l6 else l6
        l7 = x7 if x7 > l7 else l7
        s0 += x0
        s1 += x1
        s2 += x2
        s3 += x3
        s4 += x4
        s5 += x5
        s6 += x6
        s7 += x7
        s += 8
    top = 0.0
    for v in (l0, l1, l2, l3, l4, l5, l6, l7):
        top = v if v > top else top
    total = ((s0 + s1) + (s2 + s3)) + ((s4 + s5) + (s6 + s7))
    odd = total - total != 0.0
    for t in range(s, n):
        x = abs(a[t])
        top = x if x > top else top
        odd = odd or x - x != 0.0
    if odd:
        for t in range(n):
            if a[t] != a[t]:
                return math.nan
    return top
"""

_FOLDED = (
    """
import math

import numba
import numpy as np

_CHUNK = 256


{cells}
@numba.njit(cache=True, error_model='numpy', nogil=True)
def scatter(gprev, gcur, site_of, upper, rows, vol, el, r):
    m = el.shape[1]
    el[:] = 0.0
    for a in range(site_of.shape[0]):
        g = gprev if upper[a] else gcur
        for n in range(site_of.shape[1]):
            s = site_of[a, n]
            for c in range(m):
                el[s, c] += g[n, a * m + c]
    for q in range(rows.shape[0]):
        for c in range(m):
            r[q * m + c] = vol * el[rows[q], c]


@numba.njit(cache=True, error_model='numpy', nogil=True)
def gather_residual(gprev, gcur, cell_at, upper, rows, vol, r):
    # scatter's residual read per equation row (cell_at[a, site]: the cell whose point a the site is, -1: none),
    # each row's terms added in the order of the points, as scatter adds them: the same sums
    m = gcur.shape[1] // cell_at.shape[0]
    for q in range(rows.shape[0]):
        y = rows[q]
        for c in range(m):
            acc = 0.0
            for a in range(cell_at.shape[0]):
                n = cell_at[a, y]
                if n >= 0:
                    if upper[a]:
                        acc += gprev[n, a * m + c]
                    else:
                        acc += gcur[n, a * m + c]
            r[q * m + c] = vol * acc


"""
    + MAGNITUDE
    + """

@numba.njit(cache=True, error_model='numpy', nogil=True)
def predict(prev, cur, nxt, older, rows):
    # the predictor on the unknown sites rows of nxt; returns the magnitudes of prev, cur and the predicted sites
    # (_slices._scale's three); a slice whose every site is unknown runs over contiguous rows
    m = prev.shape[1]
    pf, cf, nf = prev.reshape(-1), cur.reshape(-1), nxt.reshape(-1)
    if rows.shape[0] == prev.shape[0]:  # rows are every site in order
        if older.shape[0]:
            of = older.reshape(-1)
            for t in range(nf.shape[0]):
                nf[t] = (2.0 * cf[t] - pf[t]) + (cf[t] - 2.0 * pf[t] + of[t])
        else:
            for t in range(nf.shape[0]):
                nf[t] = 2.0 * cf[t] - pf[t]
        return magnitude(pf), magnitude(cf), magnitude(nf)
    new = np.empty(rows.shape[0] * m)
    for q in range(rows.shape[0]):
        y = rows[q]
        for c in range(m):
            v = 2.0 * cur[y, c] - prev[y, c]
            if older.shape[0]:
                v = v + (cur[y, c] - 2.0 * prev[y, c] + older[y, c])
            nxt[y, c] = v
            new[q * m + c] = v
    return magnitude(pf), magnitude(cf), magnitude(new)


@numba.njit(cache=True, error_model='numpy', nogil=True, fastmath={'contract'})
def horner_cells(lo, hi, site_of, upper, w, shift, head, texp, coef, top, out):
    nvar = w.shape[1]
    ncell = site_of.shape[1]
    ntail, cols, _ = coef.shape
    ch = _CHUNK
    x, z, pw = chunk_buffers(lo, site_of, w, texp[:ntail])
    tv = np.empty(ch)
    p = np.empty(ch)
    zh = np.empty(ch)
    acc = np.empty((cols, ch))
    for start in range(0, ncell, ch):
        n = min(ch, ncell - start)
        chunk_variables(lo, hi, site_of, upper, w, shift, start, n, x, z, pw)
        for j in range(n):
            zh[j] = z[head, j]
        for c in range(cols):
            for j in range(n):
                acc[c, j] = 0.0
        for t in range(ntail):
            for j in range(n):
                tv[j] = 1.0
            for v in range(nvar):
                e = texp[t, v]
                if e:
                    for j in range(n):
                        tv[j] *= pw[v, e, j]
            for c in range(cols):
                d = top[t, c]
                if d < 0:
                    continue
                ct = coef[t, c, d]
                for j in range(n):
                    p[j] = ct
                e = d - 1
                while e >= 3:  # four steps of Horner per pass over the cells: a quarter of the stores
                    c0, c1, c2, c3 = coef[t, c, e], coef[t, c, e - 1], coef[t, c, e - 2], coef[t, c, e - 3]
                    for j in range(n):
                        y = zh[j]
                        p[j] = (((p[j] * y + c0) * y + c1) * y + c2) * y + c3
                    e -= 4
                while e >= 0:
                    ce = coef[t, c, e]
                    for j in range(n):
                        p[j] = p[j] * zh[j] + ce
                    e -= 1
                for j in range(n):
                    acc[c, j] += tv[j] * p[j]
        for j in range(n):
            for c in range(cols):
                out[start + j, c] = acc[c, j]


@numba.njit(cache=True, error_model='numpy', nogil=True)
def quadratic_residual(gprev, lo, hi, site_of, upper, hess, vlo, rows, vol, el, r):
    m = el.shape[1]
    km = site_of.shape[0] * m
    el[:] = 0.0
    x = np.empty(km)
    for a in range(site_of.shape[0]):
        if upper[a]:
            for n in range(site_of.shape[1]):
                s = site_of[a, n]
                for c in range(m):
                    el[s, c] += gprev[n, a * m + c]
    for n in range(site_of.shape[1]):
        for a in range(site_of.shape[0]):
            src = hi if upper[a] else lo
            s = site_of[a, n]
            for c in range(m):
                x[a * m + c] = src[s, c]
        for a in range(site_of.shape[0]):
            if not upper[a]:
                s = site_of[a, n]
                for c in range(m):
                    q = a * m + c
                    g = vlo[s, c]
                    for b in range(km):
                        g += x[b] * hess[b, q]
                    el[s, c] += g
    for q in range(rows.shape[0]):
        for c in range(m):
            r[q * m + c] = vol * el[rows[q], c]


@numba.njit(cache=True, error_model='numpy', nogil=True)
def quadratic_grad(lo, hi, site_of, upper, hess, vlo, vhi, out):
    m = lo.shape[1]
    km = site_of.shape[0] * m
    x = np.empty(km)
    for n in range(site_of.shape[1]):
        for a in range(site_of.shape[0]):
            src = hi if upper[a] else lo
            s = site_of[a, n]
            for c in range(m):
                x[a * m + c] = src[s, c]
        for a in range(site_of.shape[0]):
            v = vhi if upper[a] else vlo
            s = site_of[a, n]
            for c in range(m):
                q = a * m + c
                g = v[s, c]
                for b in range(km):
                    g += x[b] * hess[b, q]
                out[n, q] = g


@numba.njit(cache=True, error_model='numpy', nogil=True)
def layer_in(x, center, scale, w, b, out):
    m = x.shape[1]
    for s in range(x.shape[0]):
        for j in range(w.shape[1]):
            out[s, j] = b[j]
        for c in range(m):
            y = (x[s, c] - center[c]) / scale[c]
            for j in range(w.shape[1]):
                out[s, j] += y * w[c, j]


@numba.njit(cache=True, error_model='numpy', nogil=True)
def act_slope(a, d, kind):
    x = a.reshape(-1)
    y = d.reshape(-1)
    if kind == 0:
        for s in range(x.shape[0]):
            x[s] = y[s] * (1.0 - x[s] * x[s])
    else:
        for s in range(x.shape[0]):
            x[s] = y[s] * (x[s] * (1.0 - x[s]))


@numba.njit(cache=True, error_model='numpy', nogil=True)
def act_slope_row(a, d, kind):
    h = d.shape[0]
    if kind == 0:
        for s in range(a.shape[0]):
            for j in range(h):
                a[s, j] = d[j] * (1.0 - a[s, j] * a[s, j])
    else:
        for s in range(a.shape[0]):
            for j in range(h):
                a[s, j] = d[j] * (a[s, j] * (1.0 - a[s, j]))


@numba.njit(cache=True, error_model='numpy', nogil=True)
def feature_extremes(values, site_of, upper, proj, fmin, fmax):
    # per anchor slice i and feature, the least and largest value over the cells (a not-a-number wherever one
    # is): each cell's feature summed over the points in their order from 0.0, a chunk of cells at a time into
    # per-lane extremes (each lane's select vectorises), which are reduced once per slice
    nf, k = proj.shape
    m = values.shape[2]
    ncell = site_of.shape[1]
    ch = _CHUNK
    x = np.empty((k, ch))
    row = np.empty(ch)
    lo = np.empty((nf, ch))
    hi = np.empty((nf, ch))
    for i in range(fmin.shape[0]):
        for c in range(m):
            lo[:] = np.inf
            hi[:] = -np.inf
            for start in range(0, ncell, ch):
                n = min(ch, ncell - start)
                for a in range(k):
                    src = values[i + upper[a]]
                    for j in range(n):
                        x[a, j] = src[site_of[a, start + j], c]
                for p in range(nf):
                    for j in range(n):
                        row[j] = 0.0
                    for a in range(k):
                        w = proj[p, a]
                        for j in range(n):
                            row[j] += w * x[a, j]
                    lp, hp = lo[p], hi[p]
                    for j in range(n):
                        v = row[j]
                        lp[j] = lp[j] if (lp[j] <= v or lp[j] != lp[j]) else v
                        hp[j] = hp[j] if (hp[j] >= v or hp[j] != hp[j]) else v
            for p in range(nf):
                a_lo, a_hi = lo[p, 0], hi[p, 0]
                for j in range(1, ch):
                    a_lo = a_lo if (a_lo <= lo[p, j] or a_lo != a_lo) else lo[p, j]
                    a_hi = a_hi if (a_hi >= hi[p, j] or a_hi != a_hi) else hi[p, j]
                fmin[i, p * m + c] = a_lo
                fmax[i, p * m + c] = a_hi


@numba.njit(cache=True, error_model='numpy', nogil=True)
def update(nxt, rows, delta):
    m = nxt.shape[1]
    top = 0.0
    for q in range(rows.shape[0]):
        for c in range(m):
            nxt[rows[q], c] += delta[q * m + c]
            top = max(top, abs(nxt[rows[q], c]))
    return top
"""
)

#: The generic monomial loop of ``folded_cells``: any number of variables and columns.
_GENERIC_MONOMIALS = """
        for t in range(nmono):
            e0 = expo[t, 0]
            for j in range(n):
                p[j] = pw[0, e0, j]
            for v in range(1, nvar):
                e = expo[t, v]
                if e:
                    for j in range(n):
                        p[j] *= pw[v, e, j]
            for c in range(cols):
                g = gc[t, c]
                if g != 0.0:
                    for j in range(n):
                        acc[c, j] += g * p[j]
"""

_FOLDED = _FOLDED.replace("{cells}", _FOLDED_CELLS.replace("{monomials}", _GENERIC_MONOMIALS.strip("\n")))


def folded_kernels() -> Any:
    """The folded polynomial's kernel module (:data:`_FOLDED`: ``folded_cells``, ``horner_cells``,
    ``scatter``, ``gather_residual``, ``predict``, ``update``, ``feature_extremes``; ``quadratic_residual``,
    ``quadratic_grad``, ``layer_in``, ``act_slope`` and ``act_slope_row`` for an ``L_d`` quadratic but for a
    network's one-site terms,
    ``._serve._potential``), built on first use and cached as the others (one build per machine, for every
    polynomial); ``None``, with one info line, where numba cannot build it."""
    return _folded_module(_FOLDED, "folded polynomial")


def folded_cells_kernel(nvar: int, cols: int) -> Callable[..., None] | None:
    """``folded_cells`` with its monomial loop unrolled for ``nvar`` variables and ``cols`` columns (the class of
    a polynomial: its orders, stencil, dimension and components; its coefficients stay data), four monomials
    per pass over the cells; built once per class and cached; ``None`` where numba cannot build it."""
    source = "\nimport numba\nimport numpy as np\n\n_CHUNK = 256\n\n" + _FOLDED_CELLS.replace(
        "{monomials}", _unrolled_monomials(nvar, cols)
    )
    mod = _folded_module(source, f"folded polynomial ({nvar} variables, {cols} columns)", (nvar, cols))
    return None if mod is None else mod.folded_cells


#: ``horner_cells`` for one class of columns and degree (:func:`horner_cells_kernel`): per tail, every column's
#: Horner chain of the head variable written out over the cells of a chunk, its coefficients read once into
#: scalars, so that the chains run in registers (``horner_cells`` stores each column's partial value every four
#: steps). A (tail, column) of lower degree starts with zero coefficients, which leave its chain as
#: ``horner_cells`` computes it: the same multiply-adds in the same order, the same columns to the bit.
_HORNER_CLASS = """
@numba.njit(cache=True, error_model='numpy', nogil=True, fastmath={'contract'})
def horner_class(lo, hi, site_of, upper, w, shift, head, texp, coef, top, out):
    nvar = w.shape[1]
    ncell = site_of.shape[1]
    ntail = coef.shape[0]
    ch = _CHUNK
    x, z, pw = chunk_buffers(lo, site_of, w, texp[:ntail])
    tv = np.empty(ch)
    acc = np.empty((COLS, ch))
    for start in range(0, ncell, ch):
        n = min(ch, ncell - start)
        chunk_variables(lo, hi, site_of, upper, w, shift, start, n, x, z, pw)
        zh = z[head]
        for c in range(COLS):
            for j in range(n):
                acc[c, j] = 0.0
        for t in range(ntail):
            for j in range(n):
                tv[j] = 1.0
            for v in range(nvar):
                e = texp[t, v]
                if e:
                    for j in range(n):
                        tv[j] *= pw[v, e, j]
{chains}
        for j in range(n):
            for c in range(COLS):
                out[start + j, c] = acc[c, j]
"""


def _horner_chains(cols: int, deg: int) -> str:
    """The per-tail body of ``horner_class``: the coefficients of ``cols`` columns of degree ``deg`` read into
    scalars, then one pass over the chunk's cells with every column's chain."""
    lines = []
    for c in range(cols):
        names = ", ".join(f"k{c}_{e}" for e in range(deg + 1))
        lines.append(f"{names} = " + ", ".join(f"coef[t, {c}, {e}]" for e in range(deg + 1)))
    lines += ["for j in range(n):", "    y = zh[j]", "    s = tv[j]"]
    for c in range(cols):
        chain = f"k{c}_{deg}"
        for e in range(deg - 1, -1, -1):
            chain = f"({chain} * y + k{c}_{e})"
        lines.append(f"    acc[{c}, j] += s * {chain}")
    return "\n".join("            " + x for x in lines)


def horner_cells_kernel(cols: int, deg: int) -> Callable[..., None] | None:
    """``horner_cells`` written out for ``cols`` columns of degree ``deg`` in the head variable (the class of a
    polynomial's folded forms; its coefficients stay data): the same columns to the bit, about a quarter
    faster where every (tail, column) has that degree; built once per class and cached; ``None`` where numba
    cannot build it."""
    body = _HORNER_CLASS.replace("{chains}", _horner_chains(cols, deg)).replace("COLS", str(cols))
    cells = _FOLDED_CELLS.replace("{monomials}", _GENERIC_MONOMIALS.strip("\n"))
    source = "\nimport numba\nimport numpy as np\n\n_CHUNK = 256\n\n" + cells + body
    mod = _folded_module(source, f"folded polynomial (Horner, {cols} columns of degree {deg})", (1, cols), deg)
    return None if mod is None else mod.horner_class


def _unrolled_monomials(nvar: int, cols: int, unroll: int = 4) -> str:
    """The monomial loop of ``folded_cells`` for ``nvar`` variables and ``cols`` columns: ``unroll`` monomials
    per pass, each column's sum kept in one expression (fewer loads and stores per cell)."""

    def take(u: int, at: str) -> list[str]:
        e = ", ".join(f"e{u}_{v}" for v in range(nvar)) + ("," if nvar == 1 else "")
        g = ", ".join(f"g{u}_{c}" for c in range(cols)) + ("," if cols == 1 else "")
        exps = ", ".join(f"expo[{at}, {v}]" for v in range(nvar))
        return [f"{e} = {exps}", f"{g} = " + ", ".join(f"gc[{at}, {c}]" for c in range(cols))]

    def body(us: range) -> list[str]:
        lines = ["for j in range(n):"]
        lines += [f"    p{u} = " + " * ".join(f"pw[{v}, e{u}_{v}, j]" for v in range(nvar)) for u in us]
        lines += [f"    acc[{c}, j] += " + " + ".join(f"g{u}_{c} * p{u}" for u in us) for c in range(cols)]
        return lines

    out = ["t = 0", f"while t + {unroll} <= nmono:"]
    out += ["    " + x for u in range(unroll) for x in take(u, f"t + {u}")]
    out += ["    " + x for x in body(range(unroll))] + [f"    t += {unroll}", "while t < nmono:"]
    out += ["    " + x for x in take(0, "t")] + ["    " + x for x in body(range(1))] + ["    t += 1"]
    return "\n".join("        " + x for x in out)


def _folded_module(source: str, what: str, shape: tuple[int, int] = (1, 1), deg: int = -1) -> Any:
    """Build (once per machine) or load the folded kernel module of ``source``; ``None``, with one info line,
    where numba cannot build it (``deg >= 0``: a ``horner_class`` module of that degree)."""
    key = hashlib.sha256(f"{_VERSION}|{source}".encode()).hexdigest()[:24]
    return cached_module(
        key,
        lambda: _build_folded(key, source, shape, deg),
        what,
        f"compiled {what} kernel",
        f"compiled {what} kernel unavailable",
        "serving uses its numpy forms",
    )


def _build_folded(key: str, source: str, shape: tuple[int, int], deg: int = -1) -> tuple[Any, str]:
    """Write (once) and load a folded kernel module, and run each of its kernels once on one cell (``shape``:
    the variables and columns ``folded_cells`` is run with; ``deg``: the degree of a ``horner_class``)."""
    mod, how = write_module(key, source)
    one, idx = np.zeros((1, 1)), np.zeros((1, 1), dtype=np.int64)
    rows, up = np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64)
    nvar, cols = shape
    if deg >= 0:
        texp, top = np.zeros((1, 1), dtype=np.int64), np.zeros((1, cols), dtype=np.int64)
        coef = np.zeros((1, cols, deg + 1))
        mod.horner_class(one, one, idx, up, one, np.zeros(1), 0, texp, coef, top, np.empty((1, cols)))
        return mod, how
    expo = np.zeros((1, nvar), dtype=np.int64)
    mod.folded_cells(
        one, one, idx, up, np.zeros((1, nvar)), np.zeros(nvar), expo, np.zeros((1, cols)), np.empty((1, cols))
    )
    if not hasattr(mod, "scatter"):  # a class's own folded_cells alone
        return mod, how
    mod.scatter(one, one, idx, up, rows, 1.0, np.empty((1, 1)), np.empty(1))
    mod.gather_residual(one, one, idx, up, rows, 1.0, np.empty(1))
    mod.predict(one, one, one, one, rows)
    mod.predict(one, one, one, np.zeros((0, 1)), rows)
    mod.update(one, rows, np.zeros(1))
    mod.feature_extremes(np.zeros((2, 1, 1)), idx, up, one, np.empty((1, 1)), np.empty((1, 1)))
    mod.quadratic_residual(one, one, one, idx, up, one, one, rows, 1.0, np.empty((1, 1)), np.empty(1))
    texp, coef, top = np.zeros((1, 1), dtype=np.int64), np.zeros((1, 1, 1)), np.zeros((1, 1), dtype=np.int64)
    mod.horner_cells(one, one, idx, up, one, np.zeros(1), 0, texp, coef, top, np.empty((1, 1)))
    mod.quadratic_grad(one, one, idx, up, one, one, one, np.empty((1, 1)))
    mod.layer_in(one, np.zeros(1), np.ones(1), one, np.zeros(1), np.empty((1, 1)))
    mod.act_slope(np.zeros((1, 1)), one, 0)
    mod.act_slope_row(np.zeros((1, 1)), np.zeros(1), 0)
    return mod, how
