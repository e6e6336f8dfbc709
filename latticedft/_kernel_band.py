"""Compiled solve of a block-tridiagonal linear system, with or without the periodic wrap-around blocks.

A 1+1D slice Jacobian of a stencil one site wide along space is block tridiagonal: row ``x`` couples the
unknowns at ``x - 1``, ``x`` and ``x + 1`` through ``m x m`` blocks; a periodic axis adds the blocks that
wrap around (row 0 with unknown ``n - 1``, row ``n - 1`` with unknown 0). ``band_factor`` eliminates it
block by block without pivoting between blocks (block LU, the inverses of the pivot blocks kept), and for
the wrap borders the system with its last unknown: the first ``n - 1`` rows are solved for the border's
``m`` columns once, and each solve then corrects by them with the ``m x m`` Schur complement of the last
block. No sparse matrix is assembled and nothing is factorised by SuperLU.

The factorisation is refused (status ``1`` or ``2``: the caller keeps its sparse LU, which pivots) where a
pivot block's elimination meets a pivot below ``rtol`` times the largest entry of the system, or not
finite, or where a multiplier block ``A_x P_{x-1}^{-1}`` has an infinity norm above 1: within that bound the
pivot blocks grow at most by the largest off-diagonal block each step, so the elimination is as stable as
with pivoting (for ``m = 1`` it is the elimination partial pivoting would make). Built once per machine and
cached as the other kernels (``latticedft._kernel``).
"""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np

from ._kernel import _VERSION, cached_module, write_module

__all__ = ["band_kernels"]

_SOURCE = """
import numba
import numpy as np


@numba.njit(cache=True, error_model='numpy', nogil=True)
def invert(p, out, tol, work):
    # out = p^-1 (m x m) by Gauss-Jordan elimination with partial pivoting; False where a pivot is below tol
    # or not finite (out is then undefined)
    m = p.shape[0]
    if m == 1:
        d = p[0, 0]
        if not abs(d) >= tol:
            return False
        out[0, 0] = 1.0 / d
        return True
    for i in range(m):
        for j in range(m):
            work[i, j] = p[i, j]
            out[i, j] = 1.0 if i == j else 0.0
    for k in range(m):
        best = k
        for i in range(k + 1, m):
            if abs(work[i, k]) > abs(work[best, k]):
                best = i
        if not abs(work[best, k]) >= tol:
            return False
        if best != k:
            for j in range(m):
                work[k, j], work[best, j] = work[best, j], work[k, j]
                out[k, j], out[best, j] = out[best, j], out[k, j]
        d = 1.0 / work[k, k]
        for j in range(m):
            work[k, j] *= d
            out[k, j] *= d
        for i in range(m):
            if i != k:
                f = work[i, k]
                if f != 0.0:
                    for j in range(m):
                        work[i, j] -= f * work[k, j]
                        out[i, j] -= f * out[k, j]
    return True


@numba.njit(cache=True, error_model='numpy', nogil=True)
def band_add(band, dest, held, cells, vol):
    # band (blocks, m, m) += vol * held (cells, m, m): block q of a pair's entries (the cell cells[q], or q where
    # cells is empty) into block dest[q]
    m = band.shape[1]
    every = cells.shape[0] == 0
    for q in range(dest.shape[0]):
        c = q if every else cells[q]
        d = dest[q]
        for i in range(m):
            for j in range(m):
                band[d, i, j] += vol * held[c, i, j]


@numba.njit(cache=True, error_model='numpy', nogil=True)
def largest(band):
    # the largest entry of band in size, inf where one is not finite
    top = 0.0
    for v in band.reshape(-1):
        a = abs(v)
        if not a < np.inf:  # not finite
            return np.inf
        top = max(top, a)
    return top


@numba.njit(cache=True, error_model='numpy', nogil=True)
def band_factor(band, wrap, rtol):
    # band (3, n, m, m): per row x the blocks of unknowns x - 1, x, x + 1 (wrap: band[0, 0] couples row 0 with
    # unknown n - 1 and band[2, n - 1] row n - 1 with unknown 0). Returns (status, inv, low, z, sinv): status 0
    # factorised, 1 a pivot below rtol times the largest entry (or not finite), 2 a multiplier above 1
    n, m = band.shape[1], band.shape[2]
    top = largest(band)
    tol = rtol * top
    nb = n - 1 if wrap else n
    inv = np.zeros((n, m, m))
    low = np.zeros((n, m, m))
    z = np.zeros((n, m, m))
    sinv = np.zeros((m, m))
    work = np.empty((m, m))
    piv = np.empty((m, m))
    if not top > 0.0 or not top < np.inf:
        return 1, inv, low, z, sinv
    for x in range(nb):
        for i in range(m):
            for j in range(m):
                piv[i, j] = band[1, x, i, j]
        if x > 0:
            norm = 0.0
            for i in range(m):
                row = 0.0
                for j in range(m):
                    s = 0.0
                    for k in range(m):
                        s += band[0, x, i, k] * inv[x - 1, k, j]
                    low[x, i, j] = s
                    row += abs(s)
                norm = max(norm, row)
            if not norm <= 1.0:
                return 2, inv, low, z, sinv
            for i in range(m):
                for j in range(m):
                    s = 0.0
                    for k in range(m):
                        s += low[x, i, k] * band[2, x - 1, k, j]
                    piv[i, j] -= s
        if not invert(piv, inv[x], tol, work):
            return 1, inv, low, z, sinv
    if wrap:
        # the border's columns: z = T^-1 E, E's blocks A_0 (row 0) and C_{n-2} (row n - 2), then the Schur
        # complement of the last block, B_{n-1} - C_{n-1} z_0 - A_{n-1} z_{n-2}
        for i in range(m):
            for j in range(m):
                z[0, i, j] += band[0, 0, i, j]
                z[nb - 1, i, j] += band[2, nb - 1, i, j]
        solve_rows(band, inv, low, z, nb)
        for i in range(m):
            for j in range(m):
                s = band[1, n - 1, i, j]
                for k in range(m):
                    s -= band[2, n - 1, i, k] * z[0, k, j] + band[0, n - 1, i, k] * z[nb - 1, k, j]
                piv[i, j] = s
        if not invert(piv, sinv, tol, work):
            return 1, inv, low, z, sinv
    return 0, inv, low, z, sinv


@numba.njit(cache=True, error_model='numpy', nogil=True)
def solve_rows(band, inv, low, y, nb):
    # y[:nb] (nb, m, c) <- T^-1 y[:nb] for the first nb block rows (no wrap), from band_factor's inv and low
    m, c = y.shape[1], y.shape[2]
    t = np.empty((m, c))
    for x in range(1, nb):
        for i in range(m):
            for j in range(c):
                s = y[x, i, j]
                for k in range(m):
                    s -= low[x, i, k] * y[x - 1, k, j]
                y[x, i, j] = s
    for x in range(nb - 1, -1, -1):
        for i in range(m):
            for j in range(c):
                s = y[x, i, j]
                if x < nb - 1:
                    for k in range(m):
                        s -= band[2, x, i, k] * y[x + 1, k, j]
                t[i, j] = s
        for i in range(m):
            for j in range(c):
                s = 0.0
                for k in range(m):
                    s += inv[x, i, k] * t[k, j]
                y[x, i, j] = s


@numba.njit(cache=True, error_model='numpy', nogil=True)
def band_solve(band, wrap, inv, low, z, sinv, rhs):
    # the solution of the factorised system for rhs (n m,)
    n, m = band.shape[1], band.shape[2]
    nb = n - 1 if wrap else n
    y = rhs.copy().reshape(n, m, 1)
    solve_rows(band, inv, low, y, nb)
    if wrap:
        t = np.empty(m)
        for i in range(m):
            s = y[n - 1, i, 0]
            for k in range(m):
                s -= band[2, n - 1, i, k] * y[0, k, 0] + band[0, n - 1, i, k] * y[nb - 1, k, 0]
            t[i] = s
        for i in range(m):
            s = 0.0
            for k in range(m):
                s += sinv[i, k] * t[k]
            y[n - 1, i, 0] = s
        for x in range(nb):
            for i in range(m):
                s = y[x, i, 0]
                for k in range(m):
                    s -= z[x, i, k] * y[n - 1, k, 0]
                y[x, i, 0] = s
    return y.reshape(-1)


@numba.njit(cache=True, error_model='numpy', nogil=True)
def band_factor1(band, wrap, rtol):
    # band_factor for m = 1 on band (3, n): the same elimination in scalars (inv, low, z (n,), sinv (1,))
    n = band.shape[1]
    top = largest(band)
    tol = rtol * top
    nb = n - 1 if wrap else n
    inv = np.zeros(n)
    low = np.zeros(n)
    z = np.zeros(n)
    sinv = np.zeros(1)
    if not top > 0.0 or not top < np.inf:
        return 1, inv, low, z, sinv
    d = band[1, 0]
    for x in range(nb):
        if x > 0:
            lx = band[0, x] * inv[x - 1]
            if not abs(lx) <= 1.0:
                return 2, inv, low, z, sinv
            low[x] = lx
            d = band[1, x] - lx * band[2, x - 1]
        if not abs(d) >= tol:
            return 1, inv, low, z, sinv
        inv[x] = 1.0 / d
    if wrap:
        z[0] += band[0, 0]
        z[nb - 1] += band[2, nb - 1]
        solve_rows1(band, inv, low, z, nb)
        d = band[1, n - 1] - (band[2, n - 1] * z[0] + band[0, n - 1] * z[nb - 1])
        if not abs(d) >= tol:
            return 1, inv, low, z, sinv
        sinv[0] = 1.0 / d
    return 0, inv, low, z, sinv


@numba.njit(cache=True, error_model='numpy', nogil=True)
def solve_rows1(band, inv, low, y, nb):
    # solve_rows for m = 1 and one column: y[:nb] <- T^-1 y[:nb]
    for x in range(1, nb):
        y[x] -= low[x] * y[x - 1]
    y[nb - 1] = inv[nb - 1] * y[nb - 1]
    for x in range(nb - 2, -1, -1):
        y[x] = inv[x] * (y[x] - band[2, x] * y[x + 1])


@numba.njit(cache=True, error_model='numpy', nogil=True)
def band_solve1(band, wrap, inv, low, z, sinv, rhs):
    # band_solve for m = 1 on band_factor1's factors
    n = band.shape[1]
    nb = n - 1 if wrap else n
    y = rhs.copy()
    solve_rows1(band, inv, low, y, nb)
    if wrap:
        last = sinv[0] * (y[n - 1] - (band[2, n - 1] * y[0] + band[0, n - 1] * y[nb - 1]))
        y[n - 1] = last
        for x in range(nb):
            y[x] -= z[x] * last
    return y
"""


def band_kernels() -> Any:
    """The module of ``band_add(band, dest, held, cells, vol)``, ``band_factor(band, wrap, rtol)`` and
    ``band_solve(band, wrap, inv, low, z, sinv, rhs)`` (:data:`_SOURCE`; ``band_factor1`` and ``band_solve1`` the
    same for ``m = 1`` on ``band`` ``(3, n)``), built on first use and cached as the other kernels; ``None``, with
    one info line, where numba cannot build it."""
    key = hashlib.sha256(f"{_VERSION}|{_SOURCE}".encode()).hexdigest()[:24]
    return cached_module(
        key,
        lambda: _build(key),
        "block-tridiagonal solve",
        "compiled block-tridiagonal solve",
        "compiled block-tridiagonal solve unavailable",
        "1+1D slices use the sparse LU",
    )


def _build(key: str) -> tuple[Any, str]:
    """Write (once) and load the module, and run its kernels once on small systems (m = 1 and 2, with and
    without the wrap)."""
    mod, how = write_module(key, _SOURCE)
    for m in (1, 2):
        band = np.zeros((3, 3, m, m))
        mod.band_add(band.reshape(9, m, m), np.arange(3) + 3, np.ones((3, m, m)), np.zeros(0, dtype=np.int64), 1.0)
        band[1] = 2.0 * np.eye(m)
        for wrap in (False, True):
            status, *factors = mod.band_factor(band, wrap, 1e-8)
            mod.band_solve(band, wrap, *factors, np.ones(3 * m))
            if m == 1:
                status, *factors = mod.band_factor1(band.reshape(3, 3), wrap, 1e-8)
                mod.band_solve1(band.reshape(3, 3), wrap, *factors, np.ones(3))
    return mod, how
