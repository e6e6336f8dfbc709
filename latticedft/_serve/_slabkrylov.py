"""Slice-Newton's Krylov step on a slab: GMRES over the processes of a split serve.

A DEL whose new slice couples neighbouring unknowns (its slice Jacobian is not block-diagonal) is solved by
restarted GMRES on the whole slice, each process holding its slab's rows: the product with the Jacobian
takes the slab's own unknowns and, through a halo exchange of the Krylov vector, its neighbours' unknowns on
the halo planes (the coupling blocks to them are assembled here: the slab's :class:`._slices._SliceSystem`
holds the halo planes as known sites); every dot product and norm is summed over the processes by one
all-reduce (classical Gram-Schmidt, twice: two all-reduces a GMRES step, and one for the norm). The
preconditioner is the block-Jacobi one of the one-process Krylov step, local by construction. Every decision
(the solver, the restart, the stop) reads global numbers only, so the processes iterate alike.

The solver is chosen from the whole slice's Jacobian, as one process chooses it (``_solvers.choose_solver``,
the off-diagonal blocks to the halo planes included), except that LU, which is not split, is never chosen:
``solver = "auto"`` takes the Krylov step where one process would take LU (1+1D), and ``solver = "lu"`` is
refused in one line naming the alternative.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np
import scipy.sparse
import torch
import torch.distributed as dist

from .._collective import group_device, world
from .._errors import InputError
from .._lattice import LatticeField, interior_slices
from ._solvers import (
    GMRES_MAXITER,
    GMRES_RESTART,
    GMRES_RTOL,
    OFFDIAG_RTOL,
    SITEWISE_MAX_OFFDIAG,
    SolverRefused,
    _block_inverse,
    _diag_and_offdiag,
)

__all__ = ["SlabSolver", "lu_refusal"]

Exchange = Callable[[np.ndarray], None]


def lu_refusal(key: str = "solver") -> InputError:
    """The one-line refusal of the LU slice solve under several processes, naming ``key`` and the
    alternative."""
    return InputError.at(
        key,
        "'lu' is not split across processes (a sparse LU of the whole slice); use solver = \"krylov\" "
        '(or "auto"), or serve in one process (without --workers)',
    )


class SlabSolver:
    """``factor(sys, blocks, vol, requested, target)`` of slice-Newton on a slab (``_newton``'s ``factor``
    hook): the site-wise or the Krylov step over the processes.

    ``f`` is the block's field (its split axes Dirichlet), ``block`` the process's :class:`._grid.Block` (the
    global plane of each local plane of each split axis, and its own planes among them), ``exchange`` the
    halo exchange of a slice-wide vector, ``maxima`` the flagged all-reduce (the gate before each solve)."""

    def __init__(
        self, sys: Any, f: LatticeField, block: Any, exchange: Exchange, maxima: Callable[..., tuple[float, ...]]
    ):
        self.sys, self.exchange, self.maxima = sys, exchange, maxima
        split = len(block.parts)
        whole = (f.shape[0], *(p.n for p in block.parts), *f.shape[1 + split :])
        inner = interior_slices(whole, sys.st, f.boundary)
        rest = np.zeros(f.shape[1 + split :], dtype=bool)
        rest[interior_slices(f.shape, sys.st, f.boundary)[1 + split :]] = True
        outer = np.ones(block.held, dtype=bool)  # the planes held that are unknown in the whole lattice
        for k, p in enumerate(block.parts):
            span = slice(0, p.n) if p.periodic else inner[1 + k]
            on = (p.local >= span.start) & (p.local < span.stop)
            outer &= on.reshape((1,) * k + (-1,) + (1,) * (split - k - 1))
        outer[block.own] = False  # the halo planes only
        held = (outer[..., None] & rest.reshape(1, -1)).reshape(-1)  # the neighbours' unknowns on the halo planes
        self.held = np.nonzero(held)[0]
        col = -np.ones(sys.nsite, dtype=np.int64)
        col[self.held] = np.arange(len(self.held))
        self.halo_jac = {}
        for a, b in sys.pairs:
            r, c = sys.index[sys.site_of[a]], col[sys.site_of[b]]
            keep = (r >= 0) & (c >= 0)
            self.halo_jac[(a, b)] = (np.nonzero(keep)[0], r[keep], c[keep])

    def factor(
        self, sys: Any, blocks: dict[tuple[int, int], torch.Tensor], vol: float, requested: str, target: float
    ) -> tuple[Callable[[np.ndarray], np.ndarray], str]:
        """``(solve, name)`` for the slice's Jacobian, the solver chosen from the whole slice's."""
        m = sys.m
        diag, off = _diag_and_offdiag(sys, blocks)
        for key, (cells, _, _) in self.halo_jac.items():
            if cells.size:
                off = max(off, float(blocks[key].reshape(-1, m, m)[cells].abs().max()))
        off, scale = self.maxima(off, float(diag.abs().max()) if diag.numel() else 0.0)
        if requested == "sitewise" and off > SITEWISE_MAX_OFFDIAG * scale:
            raise SolverRefused(
                f"solver 'sitewise' needs a block-diagonal slice Jacobian, but its off-diagonal blocks reach "
                f"{off / scale if scale else np.inf:.1e} of the diagonal (the stencil or L_d couples neighbouring "
                "unknowns): use solver 'auto' or 'krylov'"
            )
        if requested == "sitewise" or (requested == "auto" and off <= OFFDIAG_RTOL * scale):
            return _block_inverse(diag, vol), "sitewise"
        return self._krylov(blocks, vol, diag, target), "krylov"

    def _matrices(self, blocks: dict[tuple[int, int], torch.Tensor], vol: float) -> tuple[Any, Any]:
        """The slab's rows of the Jacobian: on its own unknowns, and on the halo planes' unknowns."""
        sys, m = self.sys, self.sys.m
        rows, cols, vals = sys.matrix_entries(blocks, vol)
        own = scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(sys.n * m, sys.n * m))
        ii, jj = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
        rs, cs, vs = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)], [np.zeros(0)]
        for key, (cells, r, c) in self.halo_jac.items():
            rs.append((r[:, None, None] * m + ii).reshape(-1))
            cs.append((c[:, None, None] * m + jj).reshape(-1))
            vs.append((blocks[key].reshape(-1, m, m).numpy()[cells] * vol).reshape(-1))
        shape = (sys.n * m, len(self.held) * m)
        halo = scipy.sparse.csr_matrix((np.concatenate(vs), (np.concatenate(rs), np.concatenate(cs))), shape=shape)
        return own, halo

    def _krylov(
        self, blocks: dict[tuple[int, int], torch.Tensor], vol: float, diag: torch.Tensor, target: float
    ) -> Callable[[np.ndarray], np.ndarray]:
        """GMRES over the processes, preconditioned by the inverted diagonal blocks."""
        own, halo = self._matrices(blocks, vol)
        prec = _block_inverse(diag, vol)
        sys, m = self.sys, self.sys.m
        unk = np.nonzero(sys.interior)[0]

        def scatter(v: np.ndarray) -> np.ndarray:
            full = np.zeros(sys.nsite * m)
            full.reshape(sys.nsite, m)[unk] = v.reshape(-1, m)
            return full

        def solve(rhs: np.ndarray) -> np.ndarray:
            self.maxima()  # the gate before the solve's exchanges and sums
            guard = Guard(self.maxima)

            def matvec(v: np.ndarray) -> np.ndarray:
                full = guard.local(scatter, v, np.zeros(sys.nsite * m))
                self.exchange(full)  # every process takes part, one that failed too (its planes are zeros)
                held = full.reshape(sys.nsite, m)[self.held].reshape(-1)
                return guard.local(lambda x: own @ x + halo @ held, v, v)

            pre = partial(guard.local, prec)
            return gmres(matvec, lambda v: pre(v, v), rhs, pre(rhs, rhs), 0.1 * target, sums=guard.sums)

        return solve


class Guard:
    """The local work of one GMRES solve over the processes, and its sums, flagged.

    A process whose local work (a product with its rows of the Jacobian, the preconditioner) raises does not
    leave the solve: it keeps its failure, goes on with zeros through the exchanges, and raises its flag in
    the solve's next sum (every sum carries one, and every exchange comes after a sum), where every process
    learns of it; then the failing process raises its own error and the others meet it in ``maxima``, the
    split serve's flagged all-reduce (``_flag.Flag``), which raises the same error in every process."""

    def __init__(self, maxima: Callable[..., tuple[float, ...]]):
        self.maxima = maxima
        self.error: Exception | None = None

    def local(self, fn: Callable[[np.ndarray], np.ndarray], v: np.ndarray, like: np.ndarray) -> np.ndarray:
        """``fn(v)``, or zeros like ``like`` once this process failed (now or before, in this solve)."""
        if self.error is None:
            try:
                return fn(v)
            except Exception as exc:  # told at the next sum
                self.error = exc
        return np.zeros_like(like)

    def sums(self, values: np.ndarray) -> np.ndarray:
        """``values`` summed over the processes, with the flag; a failure of any process raised in every one."""
        failed = float(self.error is not None)
        if world()[1] > 1:
            t = torch.from_numpy(np.append(np.asarray(values, dtype=np.float64), failed)).to(group_device())
            dist.all_reduce(t, op=dist.ReduceOp.SUM)
            got = t.cpu().numpy()
            values, failed = got[:-1], float(got[-1])
        if failed:
            if self.error is not None:
                raise self.error  # the serve reports it to the others, as any failure of its own
            self.maxima()  # meets the failing process's report: raises its error
        return values


def _sums(values: np.ndarray) -> np.ndarray:
    """``values`` summed over the processes (one all-reduce)."""
    if world()[1] == 1:
        return values
    t = torch.from_numpy(np.ascontiguousarray(values, dtype=np.float64)).to(group_device())
    dist.all_reduce(t, op=dist.ReduceOp.SUM)
    return t.cpu().numpy()


def gmres(
    matvec: Callable[[np.ndarray], np.ndarray],
    prec: Callable[[np.ndarray], np.ndarray],
    b: np.ndarray,
    x0: np.ndarray,
    atol: float,
    rtol: float = GMRES_RTOL,
    restart: int = GMRES_RESTART,
    maxiter: int = GMRES_MAXITER,
    sums: Callable[[np.ndarray], np.ndarray] = _sums,
) -> np.ndarray:
    """Restarted, right-preconditioned GMRES on vectors split over the processes (each its rows): the
    one-process Krylov step's tolerances; an inexact step when it stops early (Newton's test decides).
    ``sums`` sums over the processes (:meth:`Guard.sums`: flagged)."""

    def _norm(v: np.ndarray) -> float:
        return math.sqrt(float(sums(np.array([v @ v]))[0]))

    x = x0.copy()
    tol = max(rtol * _norm(b), atol)
    for _ in range(maxiter):
        r = b - matvec(x)
        beta = _norm(r)
        if not beta > tol:
            break
        basis, zs = [r / beta], []
        h = np.zeros((restart + 1, restart))
        g = np.zeros(restart + 1)
        g[0] = beta
        rot: list[tuple[float, float]] = []
        k = 0
        while k < restart:
            z = prec(basis[k])
            w = matvec(z)
            zs.append(z)
            v = np.stack(basis, axis=1)
            coef = sums(v.T @ w)
            w = w - v @ coef
            again = sums(v.T @ w)  # classical Gram-Schmidt, twice: as stable as the modified one
            w, coef = w - v @ again, coef + again
            hn = _norm(w)
            h[: k + 1, k], h[k + 1, k] = coef, hn
            for j, (c, s) in enumerate(rot):
                h[j, k], h[j + 1, k] = c * h[j, k] + s * h[j + 1, k], -s * h[j, k] + c * h[j + 1, k]
            d = math.hypot(h[k, k], h[k + 1, k])
            c, s = (h[k, k] / d, h[k + 1, k] / d) if d > 0 else (1.0, 0.0)
            rot.append((c, s))
            h[k, k], h[k + 1, k] = d, 0.0
            g[k], g[k + 1] = c * g[k], -s * g[k]
            k += 1
            if not (abs(g[k]) > tol and hn > 0):
                break
            basis.append(w / hn)
        y = np.linalg.solve(np.triu(h[:k, :k]), g[:k]) if k else np.zeros(0)
        x = x + np.stack(zs, axis=1) @ y if k else x
        if abs(g[k]) <= tol:
            break
    return x
