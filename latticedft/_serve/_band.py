"""The slice Jacobian of a 1+1D lattice as a block-tridiagonal system, solved by compiled kernels.

On one spatial axis, a stencil one site wide along space couples an equation's site only to the unknowns at
the same site and its two neighbours (on a periodic axis, around the wrap). :func:`band_factor` gathers the
Hessian blocks into the ``m x m`` blocks of those three diagonals and factorises them with
``latticedft._kernel_band`` (block LU, the wrap bordered with the last unknown): no sparse matrix, no
SuperLU. Where the Jacobian is not block tridiagonal (a wider stencil, a periodic axis of fewer than three
sites), where numba cannot build the kernels, or where the elimination would need pivoting between blocks or
meets a pivot below :data:`PIVOT_RTOL` of the largest entry, it returns ``None`` and the caller keeps its
sparse LU, so a singular or badly conditioned slice is reported as before. The steps differ from the sparse
LU's by round-off only.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from .._kernel_band import band_kernels

if TYPE_CHECKING:
    from ._slices import _SliceSystem

__all__ = ["BAND_KERNEL", "PIVOT_RTOL", "band_factor", "band_places"]

#: Whether the slice Jacobian of a 1+1D lattice is solved by the compiled block-tridiagonal kernels where it
#: allows (``False``: by the sparse LU always).
BAND_KERNEL = True

#: The compiled elimination is refused (the sparse LU, which pivots, serves the slice) where a pivot is below
#: this fraction of the Jacobian's largest entry.
PIVOT_RTOL = 1e-8

#: Per pair of stencil points: the pair, its cells that hold entries (empty: every cell, in order), and each
#: entry's block among the three diagonals' ``(3 n)`` blocks (``k n + row``; ``k`` 0: the unknown before the
#: row's site, 1: its own, 2: the one after).
Places = list[tuple[tuple[int, int], np.ndarray, np.ndarray]]


def band_places(sys: _SliceSystem) -> Places | None:
    """Where each Hessian block of the slice Jacobian lies among its three block diagonals, kept per lattice;
    ``None`` where the Jacobian is not block tridiagonal on one spatial axis (or two entries of one pair share
    a place)."""
    if "band_places" not in sys.kept:
        sys.kept["band_places"] = _places(sys)
    places: Places | None = sys.kept["band_places"]
    return places


def _places(sys: _SliceSystem) -> Places | None:
    n = sys.n
    if len(sys.spatial) != 1 or n == 0 or (sys.wraps and n < 3):
        return None
    out: Places = []
    for key, (cells, r, c) in sys.jac.items():
        d = c - r
        if sys.wraps:
            d = np.where(d == n - 1, -1, np.where(d == 1 - n, 1, d))
        if d.size and (d.min() < -1 or d.max() > 1):
            return None
        k = (d + 1).astype(np.int64)
        if np.unique(k * n + r).size != r.size:
            return None
        every = cells.size == sys.site_of[0].size and bool(np.array_equal(cells, np.arange(cells.size)))
        out.append((key, np.zeros(0, np.int64) if every else cells.astype(np.int64), (k * n + r).astype(np.int64)))
    return out


def band_factor(
    sys: _SliceSystem, blocks: dict[tuple[int, int], torch.Tensor], vol: float
) -> Callable[[np.ndarray], np.ndarray] | None:
    """``solve(rhs)`` of the slice Jacobian of ``blocks`` (times ``vol``) by the compiled block-tridiagonal
    kernels, or ``None`` where they do not serve it (module docstring)."""
    places = band_places(sys) if BAND_KERNEL else None
    mod = band_kernels() if places is not None else None
    if mod is None or places is None:
        return None
    m = sys.m
    band = np.zeros((3 * sys.n, m, m))
    for key, cells, dest in places:  # each entry times vol, then summed, as the sparse matrix's
        held = np.ascontiguousarray(blocks[key].reshape(-1, m, m).numpy())
        mod.band_add(band, dest, held, cells, vol)
    # (3, n, m, m); for m = 1 the scalar kernels on (3, n): the same elimination
    shaped = band.reshape(3, sys.n) if m == 1 else band.reshape(3, sys.n, m, m)
    status, *factors = (mod.band_factor1 if m == 1 else mod.band_factor)(shaped, sys.wraps, PIVOT_RTOL)
    if status != 0:
        return None
    return _solver(mod.band_solve1 if m == 1 else mod.band_solve, shaped, sys.wraps, factors)


def _solver(kernel: Any, band: np.ndarray, wrap: bool, factors: list[np.ndarray]) -> Callable[[np.ndarray], np.ndarray]:
    def solve(rhs: np.ndarray) -> np.ndarray:
        out: np.ndarray = kernel(band, wrap, *factors, np.ascontiguousarray(rhs, dtype=np.float64))
        return out

    return solve
