"""The DEL of a quadratic ``L_d`` as an affine recurrence: one factorised solve per slice, checked afterwards
against the model's own DEL."""

from __future__ import annotations

import logging
import weakref
from dataclasses import replace
from typing import Any

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from .._action import cell_derivatives, compiled_closed_forms, del_residual
from .._lattice import LatticeField
from .._models import AbstractLagrangian
from .._options import get_options, option
from ._folded import not_affine_by_forms, per_model_state
from ._potential import not_affine
from ._slices import _SliceSystem, first_singular, member_abs_max

log = logging.getLogger("latticedft")


class _AffineSlices:
    """The DEL of a quadratic ``L_d`` as an affine recurrence ``P psi_{i-1} + C psi_i + N psi_{i+1} + c = 0``.

    Built from the model's (constant) per-cell Hessian, without the cell
    volume (a common factor of every equation; leaving it out keeps sums such
    as a discrete Laplacian's rows exact); ``N`` restricted to the unknown
    sites is factorised once. ``probe`` decides whether the model's
    DEL is affine (equal Hessians and affine gradients at random states); the
    served field is checked against the model's own DEL afterwards anyway.
    """

    def __init__(self, sys: _SliceSystem, hess: np.ndarray, grad0: np.ndarray):
        m = sys.m
        now, nxt = sys.now, sys.nxt
        size = sys.nsite * m
        ii, jj = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")

        # indices as int32 where they fit, and no entries for zero blocks (the wave L_d couples no two spatial
        # neighbours of a cell): the same matrix, assembled in a fraction of the memory on large lattices
        itype = np.int32 if size < 2**31 - 1 else np.int64

        def assemble(pairs: list[tuple[int, int]]) -> scipy.sparse.csr_matrix:
            rows, cols, vals = [], [], []
            for a, b in pairs:
                if not np.any(hess[a, b]):
                    continue
                ra, cb = sys.site_of[a].astype(itype), sys.site_of[b].astype(itype)
                rows.append((ra[:, None, None] * m + ii.astype(itype)).reshape(-1))
                cols.append((cb[:, None, None] * m + jj.astype(itype)).reshape(-1))
                vals.append(np.broadcast_to(hess[a, b], (ra.size, m, m)).reshape(-1))
            if not rows:
                return scipy.sparse.csr_matrix((size, size))
            mat = scipy.sparse.coo_matrix(
                (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(size, size)
            ).tocsr()
            mat.sum_duplicates()
            mat.eliminate_zeros()  # e.g. the wave L_d has no coupling between a cell's spatial and time neighbours
            return mat

        rows_in = (np.nonzero(sys.interior)[0][:, None] * m + np.arange(m)).reshape(-1)
        unknown = np.zeros(size, dtype=bool)
        unknown[rows_in] = True
        self.kcols = np.nonzero(~unknown)[0]
        # a contiguous block of unknowns (e.g. a 1+1D Dirichlet string) is addressed by a slice, not fancy indexing
        contiguous = rows_in.size > 0 and rows_in[-1] - rows_in[0] + 1 == rows_in.size
        self.usel: slice | np.ndarray = slice(int(rows_in[0]), int(rows_in[-1]) + 1) if contiguous else rows_in
        self.all_unknown = self.kcols.size == 0
        p_mat = assemble([(a, b) for a in nxt for b in now])[rows_in]
        c_mat = assemble([(a, b) for a in nxt for b in nxt] + [(a, b) for a in now for b in now])[rows_in]
        n_mat = assemble([(a, b) for a in now for b in nxt])[rows_in]
        # Solved about the predictor 2 psi_i - psi_{i-1}: psi_{i+1} = 2 psi_i - psi_{i-1} + w, so that
        # (P - N) psi_{i-1} + (C + 2 N) psi_i + N_known dk + N_unknown w + c = 0. The large kinetic entries
        # (~ 1/h0^2) cancel in the matrices, not in the arithmetic on the field: w carries the rounding of a
        # small correction, as Newton's step does, and the wave L_d serves the leapfrog to ~1e-15, not 1e-13.
        self.pc = scipy.sparse.hstack([p_mat - n_mat, c_mat + 2 * n_mat]).tocsr()
        self.nk = n_mat[:, self.kcols].tocsr()
        nu = n_mat[:, rows_in].tocsc()
        cvec = np.zeros(size)
        for a in nxt + now:
            np.add.at(
                cvec,
                (sys.site_of[a][:, None] * m + np.arange(m)).reshape(-1),
                np.broadcast_to(grad0[a], (sys.site_of[a].size, m)).reshape(-1),
            )
        self.c = cvec[rows_in]
        self.dmax = max((float(np.abs(hess[a, b]).max()) for a, b in sys.diag_pairs), default=1.0)
        #: A stacked ensemble's: each member's own :attr:`dmax` (its own ``w x w`` blocks; None for one model).
        self.member_dmax: np.ndarray | None = None
        if sys.members > 1:
            nm, w = sys.members, m // sys.members
            own = np.arange(nm)
            sizes = [
                np.abs(hess[a, b].reshape(nm, w, nm, w)[own, :, own, :]).max(axis=(1, 2)) for a, b in sys.diag_pairs
            ]
            self.member_dmax = np.max(sizes, axis=0) if sizes else np.ones(nm)
        diag = nu.diagonal()
        if nu.nnz == np.count_nonzero(diag) and nu.nnz == nu.shape[0]:  # diagonal (first-order stencil)
            inv = 1.0 / diag
            self.solve = lambda rhs: inv * rhs
        else:
            try:
                self.solve = scipy.sparse.linalg.splu(nu).solve
            except RuntimeError as exc:
                raise np.linalg.LinAlgError(str(exc)) from None

    @staticmethod
    def probe(model: AbstractLagrangian, st, m: int, scale: float) -> tuple[np.ndarray, np.ndarray] | None:
        """``(H, g0)``: per-cell Hessian ``(K, K, m, m)`` and gradient at zero, if the DEL is affine; else None.

        Kept per model state (:func:`._folded.per_model_state`: the same parameters and buffers, unchanged in
        place) and probe (stencil, components, ``scale``, the model's lattice, the options in effect): serving
        the same model again asks once; the answer is returned as copies."""
        key = (
            tuple(map(tuple, st.offsets)),
            m,
            float(scale),
            getattr(model, "_spacing", None),
            tuple(get_options().items()),
        )
        found, _ = per_model_state(_PROBED, model, key, lambda: _AffineSlices._probe(model, st, m, scale))
        return None if found is None else (found[0].copy(), found[1].copy())

    @staticmethod
    def _probe(model: AbstractLagrangian, st, m: int, scale: float) -> tuple[np.ndarray, np.ndarray] | None:
        """:meth:`probe`'s answer, computed."""
        k = st.size
        gen = torch.Generator().manual_seed(12345)
        x = scale * (2 * torch.rand(3, 4, k, m, generator=gen, dtype=torch.float64) - 1)
        x[0, 0] = 0.0  # the constant term is the gradient at zero itself (g - H x there would carry round-off)
        if not_affine_by_forms(model, x.reshape(-1, k, m).numpy()):  # a polynomial's compiled forms decide
            return None
        pairs = [(a, b) for a in range(k) for b in range(k)]
        try:
            g, blocks = cell_derivatives(model, x, pairs)
        except (RuntimeError, ValueError):
            return None
        h = torch.stack([torch.stack([blocks[(a, b)] for b in range(k)], -3) for a in range(k)], -4)  # (3,4,K,K,m,m)
        if not (torch.isfinite(h).all() and torch.isfinite(g).all()):
            return None
        h0 = h[0, 0]
        big = float(h0.abs().max())
        if big == 0.0 or float((h - h0).abs().max()) > 1e-10 * big:
            return None
        # affine gradient: g(x) - H x is the same constant at every state
        hx = torch.einsum("abij,...bj->...ai", h0, x)
        g0 = g - hx
        gscale = float(g.abs().max()) + big * scale
        if float((g0 - g[0, 0]).abs().max()) > 1e-10 * gscale:
            return None
        return h0.numpy().copy(), g[0, 0].numpy().copy()

    def run(self, v: np.ndarray, start: int, stop: int) -> None:
        """Fill slices ``start + 1 .. stop`` of ``v`` (``(steps, nsite * m)``, known entries already set)."""
        pc, nk, c, solve, ucols, kcols = self.pc, self.nk, self.c, self.solve, self.usel, self.kcols
        with np.errstate(all="ignore"):
            for i in range(start, stop):
                two = v[i - 1 : i + 1]
                rhs = pc @ two.reshape(-1)
                rhs += c
                pred = 2 * two[1] - two[0]
                if self.all_unknown:
                    v[i + 1] = pred
                    v[i + 1] -= solve(rhs)
                else:
                    if nk.nnz:
                        rhs += nk @ (v[i + 1, kcols] - pred[kcols])
                    v[i + 1, ucols] = pred[ucols] - solve(rhs)


#: Per model, the affine probe's last answer with the parameters, buffers and probe it was found for.
_PROBED: weakref.WeakKeyDictionary[Any, tuple[list[tuple[torch.Tensor, int]], tuple[Any, ...], Any]] = (
    weakref.WeakKeyDictionary()
)


def _slice_residuals(
    model: AbstractLagrangian, f: LatticeField, psi: torch.Tensor, start: int, stop: int, members: int = 1
) -> np.ndarray:
    """Max |DEL residual| on slices ``start .. stop - 1`` of ``psi``: on every slice (one vectorised pass per
    chunk of slices), or with the ``affine_check_every`` option ``k > 1`` on slices ``start + k - 1``,
    ``start + 2 k - 1`` ... and the last one only (each from its three slices), NaN on the others. With
    ``members > 1`` (a stacked ensemble's), per member over its own components: ``(slices, members)``."""
    every = int(option("affine_check_every"))
    if members > 1:
        return _member_residuals(model, f, psi, start, stop, members)
    if every > 1:
        out = np.full(stop - start, np.nan)
        for s in sorted({*range(start + every - 1, stop, every), stop - 1} if stop > start else set()):
            el = del_residual(model, f.with_values(psi[s - 1 : s + 2]))
            out[s - start] = float(el.abs().max()) if el.numel() else 0.0
        return out
    nsite = max(int(np.prod(psi.shape[1:-1])), 1)
    width = max(3, min(stop - start + 2, 250_000 // nsite + 2))  # ~250k sites a pass: bounded memory
    out = np.empty(stop - start)
    j = start - 1
    while j + 2 <= stop:
        hi = min(j + width, stop + 1)
        chunk = f.with_values(psi[j:hi])
        el = del_residual(model, chunk)
        out[j + 1 - start : hi - 1 - start] = el.abs().reshape(el.shape[0], -1).amax(1).numpy()
        j = hi - 2
    return out


def _member_residuals(
    model: AbstractLagrangian, f: LatticeField, psi: torch.Tensor, start: int, stop: int, members: int
) -> np.ndarray:
    """:func:`_slice_residuals` of a stacked ensemble: ``(slices, members)``, each member's by its own model on its
    own components (the members never couple), as the member alone checks its recurrence: the same residuals to
    the bit (the stack's own evaluation rounded otherwise)."""
    w = psi.shape[-1] // members
    out = np.empty((stop - start, members))
    for k in range(members):
        own = psi[..., k * w : (k + 1) * w].contiguous()
        labels = f.components[k * w : (k + 1) * w] if f.components else f.components
        out[:, k] = _slice_residuals(model.member(k), replace(f, values=own, components=labels), own, start, stop)
    return out


def passing_prefix(res: np.ndarray, bound: np.ndarray) -> int:
    """How many leading slices the affine recurrence keeps: those up to the first checked slice (``res`` not
    NaN) whose residual is not finite or above ``bound``; with checks every ``k`` slices, up to the last
    checked slice before it (the unchecked slices between two passing checks are kept)."""
    checked = ~np.isnan(res)
    good = ~checked | (np.isfinite(res) & (res <= bound))
    if good.all():
        return int(res.size)
    passed = np.nonzero(checked[: int(np.argmin(good))])[0]
    return int(passed[-1]) + 1 if passed.size else 0


def affine_del(model: AbstractLagrangian, f: LatticeField, sys: _SliceSystem) -> bool:
    """Whether :func:`_affine_prefix` finds the DEL of ``model`` on ``f`` affine (the same tests, probed at the size
    of ``f``'s first two slices: the probe's answer is kept for the serve that follows)."""
    compiled = compiled_closed_forms(model, f.values[:0])
    if compiled is not None and not compiled.quadratic:
        return False
    scale = float(f.values[:2].abs().max()) or 1.0
    if not_affine(model, sys.st.size, sys.m, scale):
        return False
    return _AffineSlices.probe(model, sys.st, sys.m, scale) is not None


def _affine_prefix(
    model: AbstractLagrangian,
    f: LatticeField,
    sys: _SliceSystem,
    psi: torch.Tensor,
    flat: torch.Tensor,
    rtol: float,
    vol: float,
) -> tuple[int | np.ndarray, float | np.ndarray, float | np.ndarray, float | np.ndarray] | None:
    """Serve every slice of ``psi`` by the affine recurrence, if the model's DEL is affine, and check them.

    Returns ``(slices, worst, dmax, mscale)``: how many leading slices pass the residual test (Newton serves
    the rest), the largest residual among them, the Hessian scale of that test and the largest singular value
    of the mixed Hessian at a site (each per member of a stacked ensemble, each judged on its own); ``None``
    when the DEL is not affine or its mixed Hessian is singular (Newton then reports it with the slice and
    site).
    """
    steps, m = psi.shape[0], sys.m
    compiled = compiled_closed_forms(model, psi[:0])
    if compiled is not None and not compiled.quadratic:  # not affine by its form: no probe needed
        return None
    scale = float(f.values[:2].abs().max()) or 1.0
    if not_affine(model, sys.st.size, m, scale):  # a kinetic-potential MLP's closed forms answer the probe
        return None
    found = affine_recurrence(model, f, sys, scale)
    if found is None:
        return None
    op, mscale = found
    v = flat.reshape(steps, sys.nsite * m).numpy()
    op.run(v, 1, steps - 1)
    res = _slice_residuals(model, f, psi, 1, steps - 1, sys.members)
    if option("affine_check_every") > 1:
        log.info("affine recurrence checked against the model's DEL on every %d-th slice", option("affine_check_every"))
    if op.member_dmax is not None:  # a stacked ensemble: each member against its own scale, its own count
        counts, worsts = passing_members(v, res, rtol * vol * op.member_dmax, m)
        return counts, worsts, op.member_dmax, mscale
    affine_slices, worst = passing_slices(v, res, rtol * vol * op.dmax)
    return affine_slices, worst, op.dmax, mscale


def affine_recurrence(
    model: AbstractLagrangian, f: LatticeField, sys: _SliceSystem, scale: float | None = None
) -> tuple[_AffineSlices, float | np.ndarray] | None:
    """The affine recurrence of ``model``'s DEL on ``sys`` (probed at the size of ``f``'s first two slices) and
    the largest singular value of the mixed Hessian at a site (per member of a stacked ensemble, each judged on
    its own); ``None`` where the DEL is not affine, its mixed Hessian is singular or the slice matrix is (Newton
    then reports it with the slice and site). The whole field's (:func:`_affine_prefix`) and the window's
    (``_stream``); ``scale``: that size, where the caller has measured it."""
    m = sys.m
    if scale is None:
        scale = float(f.values[:2].abs().max()) or 1.0
    probe = _AffineSlices.probe(model, sys.st, m, scale)
    if probe is None:
        return None
    hess = torch.from_numpy(probe[0])
    ncell = int(sys.site_of[0].size)
    lows, highs, _ = sys.member_singular_values({(a, b): hess[a, b].expand(ncell, m, m) for a, b in sys.jac})
    if first_singular(lows, highs) is not None:  # a stacked ensemble's members each on their own scale
        return None
    mscale: float | np.ndarray = float(highs[0]) if sys.members == 1 else highs
    try:
        return _AffineSlices(sys, probe[0], probe[1]), mscale
    except np.linalg.LinAlgError:
        return None  # singular slice matrix: Newton reports it with the slice and site


def passing_slices(v: np.ndarray, res: np.ndarray, bound: float) -> tuple[int, float]:
    """``(slices, worst)``: how many leading slices of the recurrence's values ``v`` (``(slices, values)``, the
    two given ones first) pass the DEL test of their residuals ``res`` (one a slice's equations), each held to
    ``bound`` times the largest value of its three slices (:func:`passing_prefix`), and the largest residual
    among them (``0`` for none)."""
    absmax = np.array([np.abs(row).max() for row in v])  # per slice, without a copy of the field
    scl = np.maximum(np.maximum(absmax[:-2], absmax[1:-1]), absmax[2:]).clip(1e-300)
    k = passing_prefix(res, bound * scl)
    return k, float(np.nanmax(res[:k], initial=0.0)) if k else 0.0


def passing_members(v: np.ndarray, res: np.ndarray, bounds: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`passing_slices` of a stacked ensemble (``m`` components a site, ``bounds.size`` members side by side
    on them): each member's residuals ``res[:, k]`` held to its own ``bounds[k]`` times the largest of its own
    values on the three slices, as when served alone: ``(counts, worst)``, the leading slices each member passes
    (each keeps its own; Newton serves a member from its own first failing slice on) and each member's largest
    residual among the slices it kept (``0`` for none)."""
    nm = bounds.size
    absmax = np.stack([member_abs_max(row, nm, m // nm) for row in v])  # (slices, members)
    scl = np.maximum(np.maximum(absmax[:-2], absmax[1:-1]), absmax[2:]).clip(1e-300)
    counts = np.array([passing_prefix(res[:, j], bounds[j] * scl[:, j]) for j in range(nm)])
    worst = np.array([float(np.nanmax(res[:k, j], initial=0.0)) if k else 0.0 for j, k in enumerate(counts)])
    return counts, worst
