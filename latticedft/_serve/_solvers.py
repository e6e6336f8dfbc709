"""The linear solve of a slice-Newton step: site-wise, Krylov (GMRES) or sparse LU.

A Newton step on slice ``i`` solves ``J delta = -r`` with ``J`` the slice
Jacobian: rows are the DEL equations of slice ``i``, columns the unknowns of
slice ``i + 1``, and its ``m x m`` blocks are per-cell mixed Hessians summed
over the cells that couple an equation's site to an unknown site.

- ``"sitewise"``: only the diagonal blocks (an equation's own site on the next
  slice), inverted all at once. Exact when the off-diagonal blocks vanish,
  as for the first-order stencil with an ``L_d`` whose spatial differences do
  not mix with the time difference (wave, Klein-Gordon, sine-Gordon ...):
  then each unknown's equation is its own ``m x m`` system and the cost is
  linear in the sites with no factorisation at all.
- ``"krylov"``: restarted GMRES (``scipy.sparse.linalg.gmres``) on the
  assembled sparse Jacobian, preconditioned by those inverted diagonal blocks
  (block Jacobi): no fill-in, cost linear in the sites per iteration.
- ``"lu"``: the sparse (1+1D Dirichlet: banded) LU factorisation; in 1+1D a block-tridiagonal Jacobian (a
  stencil one site wide along space), periodic or not, is factorised by the compiled block LU of ``._band``
  where it needs no pivoting between blocks (the sparse LU serves it otherwise).
- ``"auto"``: site-wise when the off-diagonal blocks are below
  ``OFFDIAG_RTOL`` of the diagonal ones (measured on every fresh Jacobian);
  otherwise LU in 1+1D (a banded or nearly banded matrix: cheap to factorise)
  and Krylov in more dimensions.

Whatever solves the step, Newton's convergence test is the full DEL residual,
so the solvers differ only in how many iterations they take.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from .._kernel_krylov import krylov_kernels
from ._slices import Blocks, _SliceSystem, abs_max, member_blocks

__all__ = [
    "SOLVERS",
    "OFFDIAG_RTOL",
    "SolverRefused",
    "choose_solver",
    "factor_members",
    "factor_step",
    "members_solve",
]

#: The values of ``serve(..., solver=...)`` and ``[[serve]] solver``.
SOLVERS = ("auto", "sitewise", "krylov", "lu")

#: ``"auto"`` solves site-wise when the slice Jacobian's off-diagonal blocks are below this fraction of its
#: largest diagonal entry.
OFFDIAG_RTOL = 1e-12

#: GMRES stops when the step's linear residual is below this fraction of the Newton residual (or below a tenth of
#: Newton's own tolerance); Newton's convergence test is unaffected.
#: ``solver="sitewise"`` asked for explicitly still serves (as a quasi-Newton iteration, converging in a few more
#: steps) while the off-diagonal blocks are below this fraction of the diagonal; beyond it the slice stops with an
#: error that says so (the block-Jacobi iteration would crawl or diverge).
SITEWISE_MAX_OFFDIAG = 1e-6

GMRES_RTOL = 1e-8
GMRES_RESTART = 40
GMRES_MAXITER = 50  # restart cycles

#: Whether GMRES runs compiled (``latticedft._kernel_krylov``: scipy's algorithm, the steps the same to round-off)
#: where numba builds it (``False``: scipy's ``gmres``).
COMPILED_GMRES = True

#: The compiled GMRES keeps the first :data:`GMRES_KEPT_ROWS` rows of its Krylov basis (and two work vectors) with
#: the lattice's slice system where they take at most :data:`GMRES_KEPT_BYTES` (a larger lattice allocates them
#: per solve, as scipy does); a solve that needs more rows runs again with the whole basis (the same steps).
GMRES_KEPT_ROWS = 8
GMRES_KEPT_BYTES = 64 * 2**20

Solve = Callable[[np.ndarray], np.ndarray]


class SolverRefused(Exception):
    """The requested solver cannot serve this slice's Jacobian (the message says why and what to use)."""


def _diag_and_offdiag(sys: _SliceSystem, blocks: dict[tuple[int, int], torch.Tensor]) -> tuple[torch.Tensor, float]:
    """The diagonal ``m x m`` blocks ``(n, m, m)`` of the Jacobian (without the cell volume) and the largest
    off-diagonal entry (of one model: a stacked ensemble's members are each measured on their own system, by
    :func:`factor_members`)."""
    m = sys.m
    diag = sys.diagonal(blocks)
    off = 0.0
    for key, where in sys.offdiag_cells:
        held = blocks[key].reshape(-1, m, m)
        off = max(off, abs_max(held if where is None else held[where]))
    return diag, off


def choose_solver(sys: _SliceSystem, requested: str, diag: torch.Tensor, off: float) -> str:
    """The solver of a step: ``requested``, or for ``"auto"`` the one the Jacobian's structure calls for."""
    scale = abs_max(diag) if diag.numel() else 0.0
    if requested == "sitewise" and off > SITEWISE_MAX_OFFDIAG * scale:
        raise SolverRefused(
            f"solver 'sitewise' needs a block-diagonal slice Jacobian, but its off-diagonal blocks reach "
            f"{off / scale if scale else np.inf:.1e} of the diagonal (the stencil or L_d couples neighbouring "
            "unknowns): use solver 'auto', 'krylov' or 'lu'"
        )
    if requested != "auto":
        return requested
    if off <= OFFDIAG_RTOL * scale:
        return "sitewise"
    return "lu" if len(sys.spatial) == 1 else "krylov"


def _block_inverse(diag: torch.Tensor, vol: float) -> Solve:
    """``rhs -> D^-1 rhs`` for the block-diagonal ``D = vol * diag`` (``(n, m, m)``), vectorised over the sites."""
    return _inverse_of(diag, vol)[0]


def _inverse_of(diag: torch.Tensor, vol: float) -> tuple[Solve, np.ndarray]:
    """``(rhs -> D^-1 rhs, inv)``: :func:`_block_inverse`'s product and the inverted blocks ``inv`` ``(n, m, m)``
    it applies."""
    n, m = diag.shape[0], diag.shape[-1]
    if m == 1:
        mod = krylov_kernels() if COMPILED_GMRES else None
        if mod is not None and diag.dtype == torch.float64 and diag.is_contiguous():
            inv_d = np.empty(n)
            if not mod.invert_scaled(diag.reshape(-1).numpy(), vol, inv_d):  # the same values, one pass
                raise np.linalg.LinAlgError("zero on the diagonal")
        else:
            d = vol * diag.reshape(-1).numpy()
            if not np.all(d != 0):
                raise np.linalg.LinAlgError("zero on the diagonal")
            inv_d = 1.0 / d
        return (lambda rhs: inv_d * rhs), inv_d.reshape(n, 1, 1)
    inv, info = torch.linalg.inv_ex(vol * diag)
    if n and bool((info != 0).any()):
        raise np.linalg.LinAlgError("singular diagonal block")
    inv_np = inv.numpy()
    return (lambda rhs: np.einsum("nij,nj->ni", inv_np, rhs.reshape(n, m)).reshape(-1)), inv_np


def _krylov(sys: _SliceSystem, blocks: dict[tuple[int, int], torch.Tensor], vol: float, diag, target: float) -> Solve:
    """GMRES on the assembled Jacobian with the block-Jacobi preconditioner: compiled (``latticedft._kernel_krylov``,
    scipy's algorithm in one call, its basis a workspace kept per lattice) where numba builds it, else scipy's."""
    size = sys.n * sys.m
    data, indices, indptr = sys.csr_arrays(blocks, vol)
    prec, inv = _inverse_of(diag, vol)
    atol = 0.1 * target
    mod = krylov_kernels() if COMPILED_GMRES else None
    if mod is not None:
        inv = np.ascontiguousarray(inv)
        restart = min(GMRES_RESTART, size)
        rows = min(restart + 1, GMRES_KEPT_ROWS)  # most solves touch a few rows of the basis
        work = sys.kept.get("gmres_work")
        if (work is None or work[0].shape != (rows, size)) and (rows + 2) * size * 8 <= GMRES_KEPT_BYTES:
            work = sys.kept["gmres_work"] = (np.empty((rows, size)), np.empty(size), np.empty(size))

        def compiled(rhs: np.ndarray) -> np.ndarray:
            b = np.ascontiguousarray(rhs, dtype=np.float64)
            x = np.empty(size)
            held = sys.kept.get("gmres_work")
            if held is None or held[0].shape != (rows, size):  # a large lattice: allocated per solve, as scipy's
                held = (np.empty((rows, size)), np.empty(size), np.empty(size))
            for basis in (held[0], None):  # a solve that needs more of the basis runs again with all of it
                mod.psolve(inv, b, x)  # the site-wise step: exact where the off-diagonal blocks vanish
                v = basis if basis is not None else np.empty((restart + 1, size))
                info, _ = mod.gmres(
                    indptr, indices, data, inv, b, x, atol, GMRES_RTOL, GMRES_RESTART, GMRES_MAXITER, v, *held[1:]
                )
                if info != -1:
                    break
            return x  # an inexact step when GMRES stopped early: Newton's residual test decides

        return compiled
    mat = scipy.sparse.csr_matrix((data, indices, indptr), shape=(size, size), copy=False)
    pre = scipy.sparse.linalg.LinearOperator((size, size), matvec=prec, dtype=np.float64)

    def solve(rhs: np.ndarray) -> np.ndarray:
        x0 = prec(rhs)  # the site-wise step: exact where the off-diagonal blocks vanish
        x, _info = scipy.sparse.linalg.gmres(
            mat, rhs, x0=x0, rtol=GMRES_RTOL, atol=atol, restart=GMRES_RESTART, maxiter=GMRES_MAXITER, M=pre
        )
        return np.asarray(x)  # an inexact step when GMRES stopped early: Newton's residual test decides

    return solve


def factor_step(
    sys: _SliceSystem, blocks: dict[tuple[int, int], torch.Tensor], vol: float, requested: str, target: float
) -> tuple[Solve, str]:
    """``(solve, name)``: the Newton step's ``solve(rhs)`` for the current Jacobian and the solver chosen.

    ``target`` is Newton's absolute residual tolerance (GMRES aims a tenth below it). Raises
    ``np.linalg.LinAlgError`` for a singular Jacobian (or, site-wise, a singular diagonal block).
    """
    if sys.members > 1:  # a stacked ensemble: each member factorised on its own, as served alone
        solves: list[Solve | None] = [None] * sys.members
        names = factor_members(sys, blocks, vol, requested, np.full(sys.members, target), solves)
        return members_solve(solves, sys.members, sys.m // sys.members), "+".join(dict.fromkeys(names))
    diag, off = _diag_and_offdiag(sys, blocks)
    name = choose_solver(sys, requested, diag, off)
    if name == "lu":
        return sys.factor(blocks, vol), name
    if name == "sitewise":
        return _block_inverse(diag, vol), name
    return _krylov(sys, blocks, vol, diag, target), name


def factor_members(
    sys: _SliceSystem,
    blocks: dict[tuple[int, int], torch.Tensor],
    vol: float,
    requested: str,
    targets: np.ndarray,
    solves: list[Solve | None],
    which: np.ndarray | None = None,
) -> list[str]:
    """The members ``which`` (a mask; every one where None) of a stacked ensemble's slice Jacobian ``blocks``
    factorised each on its own (:func:`factor_step` on :attr:`._slices._SliceSystem.member_system` with its own
    blocks and its own Newton tolerance ``targets[k]``): the solver chosen, the band LU's pivots, GMRES's stop
    and a refusal are each member's, as when it is served alone. ``solves[k]`` is set for each; returns the
    names of the solvers chosen, member by member."""
    nm = sys.members
    one = sys.member_system
    held = getattr(blocks, "members", None)  # each member's own blocks (the folded kernels' of a stack)
    own = {} if held is not None else {p: member_blocks(b, nm) for p, b in blocks.items()}  # (members, cells, w, w)
    names = []
    for k in np.nonzero(np.ones(nm, dtype=bool) if which is None else which)[0]:
        mine = held[k] if held is not None else Blocks({p: b[k] for p, b in own.items()})
        solves[k], name = factor_step(one, mine, vol, requested, float(targets[k]))
        names.append(name)
    return names


def members_solve(solves: list[Solve | None], nm: int, w: int) -> Solve:
    """``solve(rhs)`` of a stacked ensemble's slice (``rhs``: ``nm`` members' ``w`` components side by side at
    each site) by each member's own ``solves[k]`` on its own part; a member whose part is zero (a converged one)
    is left at zero."""

    def solve(rhs: np.ndarray) -> np.ndarray:
        parts = rhs.reshape(-1, nm, w)
        out = np.zeros_like(parts)
        for k in np.nonzero((parts != 0).any(axis=(0, 2)))[0]:
            own = solves[k]
            assert own is not None, "a member's step asked before its Jacobian was factorised"
            out[:, k] = own(np.ascontiguousarray(parts[:, k]).reshape(-1)).reshape(-1, w)
        return out.reshape(-1)

    return solve
