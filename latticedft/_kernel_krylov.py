"""Compiled GMRES on a slice Jacobian held in CSR, with the block-Jacobi preconditioner (``._serve._solvers``).

The same algorithm as scipy's ``gmres`` (scipy 1.17: left preconditioning, restarted Arnoldi with modified
Gram-Schmidt, Givens rotations as LAPACK's ``lartg`` makes them, the inner test on the preconditioned residual
estimate against a tolerance that adapts between restarts, the outer test on the true residual), written out
in one compiled call: the products with the Jacobian (each row's products summed in order, as scipy's CSR
product) and with the inverted diagonal blocks are the same to the bit; the dot products and norms are
summed in another order than numpy's, so the steps differ from scipy's by round-off. At the slice sizes of
n-D serving scipy's loop spends more time in Python and in allocating its Krylov basis than in its products;
here the basis is a workspace the caller keeps. Built once per machine and cached as the other kernels
(``latticedft._kernel``).
"""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np

from ._kernel import _VERSION, cached_module, write_module
from ._kernel_folded import MAGNITUDE

__all__ = ["krylov_kernels"]

_SOURCE = (
    """
import math

import numba
import numpy as np

EPS = np.finfo(np.float64).eps
SAFMIN = np.finfo(np.float64).tiny
RTMIN = math.sqrt(SAFMIN)
RTMAX = math.sqrt(np.finfo(np.float64).max / 2)


@numba.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def row_product(indptr, indices, vals, x, row, k):
    # row `row` of A x: its products summed in the order of its entries from 0.0 (scipy's csr_matvec); k > 0:
    # every row holds k entries from indptr[0] = 0 on (a fixed-width loop)
    acc = 0.0
    if k > 0:
        base = row * k
        for j in range(k):
            acc += vals[base + j] * x[numba.uint64(indices[base + j])]
    else:
        for p in range(indptr[row], indptr[row + 1]):
            acc += vals[p] * x[numba.uint64(indices[p])]
    return acc


@numba.njit(cache=True, error_model='numpy', nogil=True)
def width(indptr):
    # k where every row of the CSR structure holds k entries from indptr[0] = 0 on, else 0
    n = indptr.shape[0] - 1
    if n == 0 or indptr[0] != 0:
        return 0
    k = indptr[1]
    for row in range(n):
        if indptr[row + 1] - indptr[row] != k:
            return 0
    return k


@numba.njit(cache=True, error_model='numpy', nogil=True)
def matvec(indptr, indices, vals, x, out, k):
    # out = A x (row_product per row)
    for row in range(out.shape[0]):
        out[row] = row_product(indptr, indices, vals, x, row, k)


@numba.njit(cache=True, error_model='numpy', nogil=True)
def residual(indptr, indices, vals, x, b, out, k):
    # out = b - A x; returns its 2-norm
    for row in range(out.shape[0]):
        out[row] = b[row] - row_product(indptr, indices, vals, x, row, k)
    return norm2(out)


@numba.njit(cache=True, error_model='numpy', nogil=True)
def psolve(inv, r, out):
    # out = D^-1 r, D^-1 the inverted diagonal blocks inv (n, m, m) (m = 1: one product a row); returns the
    # 2-norm of out
    m = inv.shape[1]
    if m == 1:
        flat = inv.reshape(-1)
        for q in range(flat.shape[0]):
            out[q] = flat[q] * r[q]
        return norm2(out)
    for q in range(inv.shape[0]):
        for i in range(m):
            acc = 0.0
            for j in range(m):
                acc += inv[q, i, j] * r[q * m + j]
            out[q * m + i] = acc
    return norm2(out)


@numba.njit(cache=True, error_model='numpy', nogil=True)
def precond_product(indptr, indices, vals, inv, x, av, out, k):
    # out = D^-1 (A x) (av: A x); returns the 2-norm of out
    m = inv.shape[1]
    if m == 1:
        for q in range(out.shape[0]):
            a = row_product(indptr, indices, vals, x, q, k)
            av[q] = a
            out[q] = inv[q, 0, 0] * a
        return norm2(out)
    matvec(indptr, indices, vals, x, av, k)
    return psolve(inv, av, out)


@numba.njit(cache=True, error_model='numpy', nogil=True)
def dot(a, b):
    # sum of a * b in eight running sums (independent chains), then added in order
    n = a.shape[0]
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
    t = 0
    while t + 8 <= n:
        s0 += a[t] * b[t]
        s1 += a[t + 1] * b[t + 1]
        s2 += a[t + 2] * b[t + 2]
        s3 += a[t + 3] * b[t + 3]
        s4 += a[t + 4] * b[t + 4]
        s5 += a[t + 5] * b[t + 5]
        s6 += a[t + 6] * b[t + 6]
        s7 += a[t + 7] * b[t + 7]
        t += 8
    while t < n:
        s0 += a[t] * b[t]
        t += 1
    return ((s0 + s1) + (s2 + s3)) + ((s4 + s5) + (s6 + s7))


@numba.njit(cache=True, error_model='numpy', nogil=True)
def norm2(a):
    return math.sqrt(dot(a, a))


@numba.njit(cache=True, error_model='numpy', nogil=True)
def lartg(f, g):
    # LAPACK's dlartg (3.10 on): c, s, r with [c s; -s c] [f; g] = [r; 0]
    if g == 0.0:
        return 1.0, 0.0, f
    if f == 0.0:
        return 0.0, math.copysign(1.0, g), abs(g)
    f1, g1 = abs(f), abs(g)
    if RTMIN < f1 < RTMAX and RTMIN < g1 < RTMAX:
        d = math.sqrt(f * f + g * g)
        c = f1 / d
        r = math.copysign(d, f)
        return c, g / r, r
    u = min(max(SAFMIN, max(f1, g1)), np.finfo(np.float64).max)
    fs, gs = f / u, g / u
    d = math.sqrt(fs * fs + gs * gs)
    c = abs(fs) / d
    r = math.copysign(d, f)
    s = gs / r
    return c, s, r * u


@numba.njit(cache=True, error_model='numpy', nogil=True)
def take_scaled(src, places, vol, out):
    # out[k] = src[places[k]] * vol: the slice Jacobian's CSR values read from the evaluated columns
    for k in range(places.shape[0]):
        out[k] = src[places[k]] * vol


@numba.njit(cache=True, error_model='numpy', nogil=True)
def diag_add(diag, rows, cells, held):
    # diag (n, m, m) += held[cells[q]] into diag[rows[q]], q in order (index_add_'s sums, in its order)
    m = diag.shape[1]
    if m == 1:
        d, h = diag.reshape(-1), held.reshape(-1)
        for q in range(rows.shape[0]):
            d[numba.uint64(rows[q])] += h[numba.uint64(cells[q])]
        return
    for q in range(rows.shape[0]):
        r, c = rows[q], cells[q]
        for i in range(m):
            for j in range(m):
                diag[r, i, j] += held[c, i, j]


@numba.njit(cache=True, error_model='numpy', nogil=True)
def invert_scaled(d, vol, out):
    # out = 1.0 / (vol * d) (numpy's two products, in one pass); False where some vol * d is zero
    ok = True
    for q in range(d.shape[0]):
        v = vol * d[q]
        ok = ok and v != 0.0
        out[q] = 1.0 / v
    return ok


"""
    + MAGNITUDE
    + """

@numba.njit(cache=True, error_model='numpy', nogil=True)
def abs_max(a):
    # the largest |value| of a (flat), a not-a-number wherever one is (torch's abs().max()), 0.0 when empty
    return magnitude(a)


@numba.njit(cache=True, error_model='numpy', nogil=True)
def finite_abs_max(a):
    # (every value finite, the largest |value|) of a (flat): numpy's isfinite().all() and abs().max()
    top = abs_max(a)
    if top - top == 0.0:  # finite, no not-a-number
        return True, top
    for t in range(a.shape[0]):
        if not (a[t] - a[t] == 0.0):
            return False, top
    return True, top


@numba.njit(cache=True, error_model='numpy', nogil=True)
def abs_extremes(d):
    # (smallest, its first index, largest) of |d| with a not-a-number taken as 0 (torch's nan_to_num, argmin, max)
    low = math.inf
    at = 0
    high = 0.0
    for q in range(d.shape[0]):
        a = abs(d[q])
        if a != a:
            a = 0.0
        if a < low:
            low = a
            at = q
        if a > high:
            high = a
    return low, at, high


@numba.njit(cache=True, error_model='numpy', nogil=True)
def gmres(indptr, indices, vals, inv, b, x, atol, rtol, restart, maxiter, v, w, r):
    # scipy.sparse.linalg.gmres(A, b, x0=x, rtol=rtol, atol=atol, restart=restart, maxiter=maxiter, M=D^-1) into x;
    # v: the Krylov basis (min(restart, n) + 1 rows for any solve), w and r: (n,) work; returns (info, residual
    # norm), info -1 where the solve needs more rows of v than given (x is then to be set again and the solve run
    # with a larger v)
    n = b.shape[0]
    k = width(indptr)
    bnrm2 = norm2(b)
    atol = max(atol, rtol * bnrm2)
    if bnrm2 == 0.0:
        for t in range(n):
            x[t] = b[t]
        return 0, 0.0
    restart = min(restart, n)
    mb_nrm2 = psolve(inv, b, w)
    ptol_max_factor = 1.0
    ptol = mb_nrm2 * min(ptol_max_factor, atol / bnrm2)
    presid = 0.0
    h = np.zeros((restart, restart + 1))
    givens = np.zeros((restart, 2))
    s_vec = np.zeros(restart + 1)
    rnorm = math.inf
    for iteration in range(maxiter):
        if iteration == 0:
            nonzero = False
            for t in range(n):
                if x[t] != 0.0:
                    nonzero = True
                    break
            if nonzero:
                r0 = residual(indptr, indices, vals, x, b, r, k)
            else:
                for t in range(n):
                    r[t] = b[t]
                r0 = bnrm2
            if r0 < atol:
                return 0, r0
        v0 = v[0]
        tmp = psolve(inv, r, v0)
        scale = 1.0 / tmp
        for t in range(n):
            v0[t] *= scale
        for j in range(restart + 1):
            s_vec[j] = 0.0
        s_vec[0] = tmp
        breakdown = False
        col = 0
        for col in range(restart):
            if col + 1 >= v.shape[0]:
                return -1, rnorm
            h0 = precond_product(indptr, indices, vals, inv, v[col], r, w, k)
            for j in range(col + 1):  # modified Gram-Schmidt
                vj = v[j]
                d = dot(vj, w)
                h[col, j] = d
                for t in range(n):
                    w[t] -= d * vj[t]
            h1 = norm2(w)
            h[col, col + 1] = h1
            vn = v[col + 1]
            if h1 <= EPS * h0:
                h[col, col + 1] = 0.0
                breakdown = True
                for t in range(n):
                    vn[t] = w[t]
            else:
                scale = 1.0 / h1
                for t in range(n):
                    vn[t] = w[t] * scale
            for j in range(col):
                c, s = givens[j, 0], givens[j, 1]
                n0, n1 = h[col, j], h[col, j + 1]
                h[col, j] = c * n0 + s * n1
                h[col, j + 1] = -s * n0 + c * n1
            c, s, mag = lartg(h[col, col], h[col, col + 1])
            givens[col, 0], givens[col, 1] = c, s
            h[col, col], h[col, col + 1] = mag, 0.0
            tmp = -s * s_vec[col]
            s_vec[col] = c * s_vec[col]
            s_vec[col + 1] = tmp
            presid = abs(tmp)
            if presid <= ptol or breakdown:
                break
        if h[col, col] == 0.0:
            s_vec[col] = 0.0
        y = s_vec[: col + 1].copy()
        for j in range(col, 0, -1):
            if y[j] != 0.0:
                y[j] /= h[j, j]
                tmp = y[j]
                for i in range(j):
                    y[i] -= tmp * h[j, i]
        if y[0] != 0.0:
            y[0] /= h[0, 0]
        for t in range(n):  # x += y @ v[: col + 1]
            acc = 0.0
            for j in range(col + 1):
                acc += y[j] * v[j, t]
            x[t] += acc
        rnorm = residual(indptr, indices, vals, x, b, r, k)
        if rnorm <= atol:
            break
        elif breakdown:
            break
        elif presid <= ptol:
            ptol_max_factor = max(EPS, 0.25 * ptol_max_factor)
        else:
            ptol_max_factor = min(1.0, 1.5 * ptol_max_factor)
        ptol = presid * min(ptol_max_factor, atol / rnorm)
    return (0 if rnorm <= atol else maxiter), rnorm
"""
)


#: The module's key in the kernel cache (hashed once: the kernels are asked for several times a slice).
_KEY = hashlib.sha256(f"{_VERSION}|{_SOURCE}".encode()).hexdigest()[:24]


def krylov_kernels() -> Any:
    """The module of ``gmres(indptr, indices, vals, inv, b, x, atol, rtol, restart, maxiter, v, w, r)`` and its
    parts (``psolve(inv, r, out)``: the preconditioner's product, returning its norm; :data:`_SOURCE`), built on
    first use and cached as the other kernels; ``None``, with one info line, where numba cannot build it."""
    return cached_module(
        _KEY,
        lambda: _build(_KEY),
        "GMRES",
        "compiled GMRES",
        "compiled GMRES unavailable",
        "Krylov steps use scipy's GMRES",
    )


def _build(key: str) -> tuple[Any, str]:
    """Write (once) and load the module, and run its kernel once on small systems (m = 1 and 2; the index arrays
    of scipy's constructor, 32-bit, and of the slice system's kept structure, 64-bit row pointers with 32-bit or
    64-bit columns)."""
    mod, how = write_module(key, _SOURCE)
    for m in (1, 2):
        size = 2 * m
        inv = np.tile(np.eye(m), (2, 1, 1))
        for ptr, kind in ((np.int32, np.int32), (np.int64, np.int32), (np.int64, np.int64)):
            indptr, idx = np.arange(size + 1, dtype=ptr), np.arange(size, dtype=kind)
            work = np.empty((3, size)), np.empty(size), np.empty(size)
            mod.gmres(indptr, idx, np.ones(size), inv, np.ones(size), np.zeros(size), 0.0, 1e-8, 2, 2, *work)
        one = np.zeros(1, dtype=np.int64)
        mod.diag_add(np.zeros((1, m, m)), one, one, np.ones((1, m, m)))
    mod.take_scaled(np.ones(2), np.zeros(1, dtype=np.int64), 1.0, np.empty(1))
    mod.abs_extremes(np.ones(2))
    mod.abs_max(np.ones(2))
    mod.finite_abs_max(np.ones(2))
    mod.invert_scaled(np.ones(2), 1.0, np.empty(2))
    return mod, how
