"""Serving a learned theory: fill a lattice slice by slice by solving the DEL (DESIGN.md §1).

On slice ``i`` every interior site ``y`` gives one equation ``EL_y = 0`` for
the values on slice ``i + 1``. ``mode="newton"`` solves a whole slice by
Newton's method with the sparse (block lower-triangular for the first-order
stencil) Jacobian assembled from per-cell Hessian blocks; ``mode="sweep"`` is
the paper's site-by-site sweep (Qin 2020, Sec. 2, Steps 1-5), kept as a
reference. In 1D a slice is one site and a batch of trajectories is stepped
together.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg
import torch
import xarray as xr
from tqdm.auto import tqdm

from ._action import CellDerivatives, cell_derivatives, del_residual
from ._errors import InputError, ServeError
from ._lattice import BoundaryKinds, LatticeField, as_lattice_field, gather_cells, interior_slices
from ._learn import _check_model_lattice
from ._models import AbstractLagrangian, AnalyticLagrangian

__all__ = ["serve", "ServeResult", "compare"]

MODES = ("newton", "sweep")


@dataclass
class ServeResult:
    """A served field and how serving went."""

    field: xr.DataArray
    complete: bool
    reason: str
    slices: int
    newton_iterations: int
    max_newton_iterations: int
    wall_time: float
    sites_per_second: float
    max_residual: float
    mode: str
    #: how the slices were solved: "newton", "sweep", "affine" (a quadratic L_d: the DEL's affine recurrence,
    #: one factorised solve per slice, checked afterwards) or "affine+newton" (Newton from the first slice
    #: that failed that check)
    solver: str = "newton"

    def to_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in ("complete", "reason", "slices", "newton_iterations",
                                              "max_newton_iterations", "wall_time", "sites_per_second",
                                              "max_residual", "mode", "solver")}


def compare(pred: xr.DataArray, ref: xr.DataArray) -> dict[str, float]:
    """Max and RMS error of ``pred`` against ``ref`` over the time slices both hold.

    >>> import numpy as np, xarray as xr
    >>> a = xr.DataArray(np.zeros(4), dims="t", coords={"t": np.arange(4.0)})
    >>> compare(a, a + 0.5)
    {'max_error': 0.5, 'rms_error': 0.5, 'slices': 4}
    """
    tdim = pred.dims[0]
    n = min(pred.sizes[tdim], ref.sizes[tdim])
    if pred.shape[1:] != ref.shape[1:]:
        raise InputError(f"compare: shapes {pred.shape} and {ref.shape} differ beyond the time axis")
    d = pred.values[:n] - ref.values[:n]
    return {"max_error": float(np.abs(d).max()), "rms_error": float(np.sqrt(np.mean(d ** 2))), "slices": int(n)}


# -- helpers ------------------------------------------------------------------------------------------------
def _bar(total: int, desc: str, progress: bool | None):
    return tqdm(total=total, desc=desc, disable=None if progress is None else not progress, leave=False)


def _prepare_model(model: AbstractLagrangian, f: LatticeField) -> None:
    if not isinstance(model, AbstractLagrangian):
        raise InputError(f"model: expected a latticedft model, got {type(model).__name__}")
    if isinstance(model, AnalyticLagrangian):
        model.bind(f.ndim, f.ncomp, f.spacing, f.components)  # a formula in h: valid on any lattice
    if not model.bound:
        raise InputError(f"model: {type(model).__name__} has not been learned yet (latticedft.learn)")
    _check_model_lattice(model, f, "init")


def _steps(steps: int | None, f: LatticeField) -> int:
    if steps is None:
        return f.shape[0]
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 3:
        raise InputError(f"steps: expected an integer >= 3 (time slices of the served field), got {steps!r}")
    return steps


class _SliceSystem:
    """Index maps of one slice's equations and unknowns, built once per lattice."""

    def __init__(self, model: AbstractLagrangian, f: LatticeField):
        st = model.stencil
        self.st = st
        self.m = f.ncomp
        spatial = f.shape[1:]
        self.spatial = spatial
        self.periodic = f.periodic
        self.nsite = int(np.prod(spatial))
        inner = interior_slices(f.shape, st, f.periodic)[1:]
        mask = np.zeros(spatial, dtype=bool)
        mask[inner] = True
        self.interior = mask.reshape(-1)
        self.index = -np.ones(self.nsite, dtype=np.int64)  # site -> equation row / unknown column
        self.index[self.interior] = np.arange(int(self.interior.sum()))
        self.n = int(self.interior.sum())
        # cells anchored on one slice: shape of the cell grid along the spatial axes
        lo, width = st.lo, st.width
        cshape = [nk if f.periodic[k + 1] else nk - int(width[k + 1]) for k, nk in enumerate(spatial)]
        self.cshape = tuple(cshape)
        grids = np.meshgrid(*[np.arange(c) for c in cshape], indexing="ij")
        self.site_of: list[np.ndarray] = []  # per stencil point: flat site index of that point for every cell
        for off in st.offsets:
            idx = []
            for k, gk in enumerate(grids):
                v = gk + off[k + 1] - lo[k + 1]
                if f.periodic[k + 1]:
                    v = v % spatial[k]
                idx.append(v.reshape(-1))
            self.site_of.append(np.ravel_multi_index(idx, spatial) if idx else np.zeros(1, dtype=np.int64))
        self.now = [a for a, o in enumerate(st.offsets) if o[0] == 0]
        self.nxt = [a for a, o in enumerate(st.offsets) if o[0] == 1]
        self.pairs = [(a, b) for a in self.now for b in self.nxt]
        # Jacobian structure: rows (equation sites on slice i) x cols (unknowns on slice i+1)
        self.jac: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        for a, b in self.pairs:
            r = self.index[self.site_of[a]]
            c = self.index[self.site_of[b]]
            keep = (r >= 0) & (c >= 0)
            self.jac[(a, b)] = (np.nonzero(keep)[0], r[keep], c[keep])
        m = self.m
        rows = np.concatenate([r for _, r, _ in self.jac.values()]) if self.jac else np.zeros(0, np.int64)
        cols = np.concatenate([c for _, _, c in self.jac.values()]) if self.jac else np.zeros(0, np.int64)
        self.lower = int(max(0, (rows - cols).max() if rows.size else 0)) * m + m - 1
        self.upper = int(max(0, (cols - rows).max() if rows.size else 0)) * m + m - 1
        self.banded = len(spatial) == 1 and not any(f.periodic[1:])
        self.triangular = bool(rows.size == 0 or (cols <= rows).all()) and not any(f.periodic[1:])
        self.diag_pairs = [(a, b) for (a, b), (_, r, c) in self.jac.items() if np.any(r == c)]

    # EL on slice i (equation rows) from the per-cell gradients of the cells anchored at i-1 and i
    def residual(self, g_prev: torch.Tensor, g_cur: torch.Tensor, vol: float) -> np.ndarray:
        m = self.m
        el = torch.zeros(self.nsite, m, dtype=torch.float64)
        gp = g_prev.reshape(-1, self.st.size, m)
        gc = g_cur.reshape(-1, self.st.size, m)
        for a in self.nxt:
            el.index_add_(0, torch.from_numpy(self.site_of[a]), gp[:, a])
        for a in self.now:
            el.index_add_(0, torch.from_numpy(self.site_of[a]), gc[:, a])
        return (vol * el).numpy()[self.interior].reshape(-1)

    def matrix_entries(self, blocks: dict[tuple[int, int], torch.Tensor], vol: float):
        m = self.m
        rs, cs, vs = [], [], []
        ii, jj = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
        for key, (cells, r, c) in self.jac.items():
            v = blocks[key].reshape(-1, m, m).numpy()[cells] * vol  # (nnz, m, m)
            rs.append((r[:, None, None] * m + ii).reshape(-1))
            cs.append((c[:, None, None] * m + jj).reshape(-1))
            vs.append(v.reshape(-1))
        return np.concatenate(rs), np.concatenate(cs), np.concatenate(vs)

    def factor(self, blocks, vol: float):
        """Assemble and factorise the slice Jacobian; returns ``solve(rhs)``."""
        rows, cols, vals = self.matrix_entries(blocks, vol)
        size = self.n * self.m
        if self.banded:
            lo, up = self.lower, self.upper
            ab = np.zeros((lo + up + 1, size))
            np.add.at(ab, (up + rows - cols, cols), vals)
            if not np.all(ab[up] != 0):
                raise np.linalg.LinAlgError("zero on the diagonal")
            return lambda rhs: scipy.linalg.solve_banded((lo, up), ab, rhs, check_finite=False)
        mat = scipy.sparse.csc_matrix((vals, (rows, cols)), shape=(size, size))
        try:
            return scipy.sparse.linalg.splu(mat).solve
        except RuntimeError as exc:  # "Factor is exactly singular"
            raise np.linalg.LinAlgError(str(exc)) from None


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

        def assemble(pairs: list[tuple[int, int]]) -> scipy.sparse.csr_matrix:
            rows, cols, vals = [], [], []
            for a, b in pairs:
                ra, cb = sys.site_of[a], sys.site_of[b]
                rows.append((ra[:, None, None] * m + ii).reshape(-1))
                cols.append((cb[:, None, None] * m + jj).reshape(-1))
                vals.append(np.broadcast_to(hess[a, b], (ra.size, m, m)).reshape(-1))
            if not rows:
                return scipy.sparse.csr_matrix((size, size))
            mat = scipy.sparse.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                                          shape=(size, size)).tocsr()
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
            np.add.at(cvec, (sys.site_of[a][:, None] * m + np.arange(m)).reshape(-1),
                      np.broadcast_to(grad0[a], (sys.site_of[a].size, m)).reshape(-1))
        self.c = cvec[rows_in]
        self.dmax = max((float(np.abs(hess[a, b]).max()) for a, b in sys.diag_pairs), default=1.0)
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
        """``(H, g0)``: per-cell Hessian ``(K, K, m, m)`` and gradient at zero, if the DEL is affine; else None."""
        k = st.size
        gen = torch.Generator().manual_seed(12345)
        x = scale * (2 * torch.rand(3, 4, k, m, generator=gen, dtype=torch.float64) - 1)
        x[0, 0] = 0.0  # the constant term is the gradient at zero itself (g - H x there would carry round-off)
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
                two = v[i - 1:i + 1]
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


def _slice_residuals(model: AbstractLagrangian, f: LatticeField, psi: torch.Tensor, start: int, stop: int) -> np.ndarray:
    """Max |DEL residual| on slices ``start .. stop - 1`` of ``psi`` (one vectorised pass per chunk of slices)."""
    nsite = max(int(np.prod(psi.shape[1:-1])), 1)
    width = max(3, min(stop - start + 2, 250_000 // nsite + 2))  # ~250k sites a pass: bounded memory
    out = np.empty(stop - start)
    j = start - 1
    while j + 2 <= stop:
        hi = min(j + width, stop + 1)
        chunk = f.with_values(psi[j:hi])
        el = del_residual(model, chunk)
        out[j + 1 - start: hi - 1 - start] = el.abs().reshape(el.shape[0], -1).amax(1).numpy()
        j = hi - 2
    return out


def _site_label(f: LatticeField, sys: _SliceSystem, tslice: int, row: int) -> tuple[int, ...]:
    site = int(np.nonzero(sys.interior)[0][row // sys.m])
    return (tslice, *[int(v) for v in np.unravel_index(site, sys.spatial)])


# -- n-D serving (n >= 2) --------------------------------------------------------------------------------------
def _serve_field(model: AbstractLagrangian, f: LatticeField, steps: int, mode: str, rtol: float, max_newton: int,
                 progress: bool | None, affine: bool = True) -> ServeResult:
    st = model.stencil
    sys = _SliceSystem(model, f)
    nt_given = f.shape[0]
    m = f.ncomp
    dirichlet_axes = [f.dims[k] for k in range(1, f.ndim) if not f.periodic[k]]
    if dirichlet_axes and nt_given < steps:
        raise InputError(f"init: holds {nt_given} time slices but the Dirichlet boundary along "
                         f"{dirichlet_axes[0]!r} needs its strips on all {steps} slices; give the whole field, "
                         "fewer steps, or a periodic boundary")
    psi = torch.full((steps, *f.shape[1:], m), math.nan, dtype=torch.float64)
    psi[:2] = f.values[:2]
    known = np.ones(sys.nsite, dtype=bool)
    known[sys.interior] = False
    flat = psi.reshape(steps, sys.nsite, m)
    if known.any():
        kidx = torch.from_numpy(np.nonzero(known)[0])
        flat[:, kidx] = f.values[:steps].reshape(-1, sys.nsite, m)[:, kidx]
    unk = torch.from_numpy(np.nonzero(sys.interior)[0])
    vol = math.prod(model.spacing)
    t0 = time.perf_counter()
    total_it, max_it, worst = 0, 0, 0.0
    periodic = f.periodic

    def cells_at(i: int) -> torch.Tensor:
        return gather_cells(psi[i:i + 2], st, periodic)

    bar = _bar(steps - 2, f"serve ({mode})", progress)
    cache: dict[str, Any] = {}
    start = 1  # first slice whose equations Newton (or the sweep) solves
    affine_slices = 0
    if mode == "newton" and affine and steps > 2:
        scale = float(f.values[:2].abs().max()) or 1.0
        probe = _AffineSlices.probe(model, st, m, scale)
        if probe is not None:
            try:
                op = _AffineSlices(sys, probe[0], probe[1])
            except np.linalg.LinAlgError:
                op = None  # singular slice matrix: Newton reports it with the slice and site
            if op is not None:
                v = flat.reshape(steps, sys.nsite * m).numpy()
                op.run(v, 1, steps - 1)
                res = _slice_residuals(model, f, psi, 1, steps - 1)
                absmax = np.array([np.abs(row).max() for row in v])  # per slice, without a copy of the field
                scl = np.maximum(np.maximum(absmax[:-2], absmax[1:-1]), absmax[2:]).clip(1e-300)
                good = np.isfinite(res) & (res <= rtol * vol * op.dmax * scl)
                affine_slices = int(np.argmin(good)) if not good.all() else steps - 2
                start = 1 + affine_slices
                if affine_slices:
                    worst = float(res[:affine_slices].max())
                    total_it, max_it = affine_slices, 1
                    cache["dmax"] = op.dmax
                bar.update(affine_slices)
    g_prev = CellDerivatives(model, cells_at(start - 1)).grad

    def solver() -> str:
        if mode == "sweep":
            return "sweep"
        return "newton" if not affine_slices else ("affine" if start >= steps - 1 else "affine+newton")

    def fail(i: int, msg: str, row: int | None, res: float) -> ServeError:
        bar.close()
        part = LatticeField.with_values(f, psi[: i + 1].clone())
        wall = time.perf_counter() - t0
        solved = (i + 1 - 2) * sys.n
        result = ServeResult(field=part.to_dataarray(), complete=False, reason=msg, slices=i + 1,
                             newton_iterations=total_it, max_newton_iterations=max_it, wall_time=wall,
                             sites_per_second=solved / wall if wall > 0 else 0.0, max_residual=res, mode=mode,
                             solver=solver())
        site = _site_label(f, sys, i, row) if row is not None else None
        tval = float(f.coords[f.dims[0]][0] + (i + 1) * f.spacing[0])
        text = f"slice {i + 1} (t = {tval:.6g}): {msg}" + (f" at site {site}" if site else "") + \
            (f", residual {res:.3e}" if math.isfinite(res) else "")
        return ServeError(text, result=result, slice=i + 1, site=site, residual=res)

    for i in range(start, steps - 1):
        # predictor 2 psi_i - psi_{i-1} on the unknown sites
        flat[i + 1, unk] = 2 * flat[i, unk] - flat[i - 1, unk]
        if mode == "newton":
            it, res, g_prev, err = _newton_slice(model, sys, psi, flat, unk, i, g_prev, vol, rtol, max_newton, cells_at,
                                                 cache)
        else:
            it, res, g_prev, err = _sweep_slice(model, sys, psi, flat, i, vol, rtol, max_newton, f)
        total_it += it
        max_it = max(max_it, it)
        worst = max(worst, res)
        if err is not None:
            msg, row, rval = err
            raise fail(i, msg, row, rval)
        bar.update(1)
    bar.close()
    wall = time.perf_counter() - t0
    out = LatticeField.with_values(f, psi)
    solved = (steps - 2) * sys.n
    return ServeResult(field=out.to_dataarray(), complete=True, reason="complete", slices=steps,
                       newton_iterations=total_it, max_newton_iterations=max_it, wall_time=wall,
                       sites_per_second=solved / wall if wall > 0 else math.inf, max_residual=worst, mode=mode,
                       solver=solver())


def _scale(flat: torch.Tensor, i: int, unk: torch.Tensor) -> float:
    return float(max(flat[i - 1].abs().max(), flat[i].abs().max(), flat[i + 1, unk].abs().max(), 1e-300))


def _fresh_blocks(ev: CellDerivatives, sys: _SliceSystem, cache: dict[str, Any]) -> dict:
    """Hessian blocks of the slice at the current state; records their diagonal size (the residual scale)."""
    blocks = ev.blocks(sys.pairs)
    cache["dmax"] = max((float(blocks[p].abs().max()) for p in sys.diag_pairs), default=1.0)
    return blocks


def _newton_slice(model, sys: _SliceSystem, psi, flat, unk, i, g_prev, vol, rtol, max_newton, cells_at, cache):
    """Newton on one slice. The first step reuses the cached factorised Jacobian (a chord step, exact for
    quadratic ``L_d``); fresh Hessian blocks are assembled only when that step did not converge."""
    m = sys.m
    res = math.inf
    r = np.zeros(0)
    rscale = None
    small = False
    for it in range(1, max_newton + 1):
        ev = CellDerivatives(model, cells_at(i))
        r = sys.residual(g_prev, ev.grad, vol)
        res = float(np.abs(r).max()) if r.size else 0.0
        if not math.isfinite(res):
            return it, res, ev.grad, ("residual is not finite", None, res)
        stale = it == 1 and "solve" in cache
        blocks = _fresh_blocks(ev, sys, cache) if "dmax" not in cache else None
        if rscale is None:
            rscale = vol * cache["dmax"] * _scale(flat, i, unk)
        if res <= rtol * rscale or small:
            # converged (or the last step was below rtol times the values: the residual stalls at round-off);
            # the cells anchored at slice i are evaluated at the solution: reuse them for slice i + 1
            return it, res, ev.grad, None
        try:
            if not stale:
                if blocks is None:
                    blocks = _fresh_blocks(ev, sys, cache)
                cache["solve"] = sys.factor(blocks, vol)
            delta = cache["solve"](-r)
        except (np.linalg.LinAlgError, ValueError) as exc:
            cache.pop("solve", None)
            row = int(np.argmax(np.abs(r)))
            return it, res, ev.grad, (f"singular Jacobian (mixed Hessian) of the slice: {exc}", row, res)
        if not np.all(np.isfinite(delta)):
            cache.pop("solve", None)
            if stale:
                continue
            return it, res, ev.grad, ("Newton step is not finite (singular mixed Hessian?)",
                                      int(np.argmax(np.abs(r))), res)
        flat[i + 1, unk] += torch.from_numpy(delta.reshape(-1, m))
        small = not stale and float(np.abs(delta).max()) <= rtol * _scale(flat, i, unk)
    row = int(np.argmax(np.abs(r))) if r.size else None
    return max_newton, res, ev.grad, (f"Newton did not converge in {max_newton} iterations", row, res)


def _sweep_slice(model, sys: _SliceSystem, psi, flat, i, vol, rtol, max_newton, f):
    """The paper's site-by-site sweep (Gauss-Seidel when the slice system is not triangular)."""
    st = sys.st
    m = sys.m
    nsp = len(sys.spatial)
    offs = np.array(st.offsets)
    sites = np.nonzero(sys.interior)[0]
    e0 = np.zeros(nsp + 1, dtype=np.int64)
    e0[0] = 1
    unk_scale = _scale(flat, i, torch.from_numpy(sites))
    total_it = 0
    worst = 0.0
    sweeps = 1 if sys.triangular else 100
    for sweep in range(sweeps):
        change = 0.0
        for row, site in enumerate(sites):
            y = np.array([i, *np.unravel_index(site, sys.spatial)])
            # the K cells y - s_a, each with its K points y - s_a + s_b
            pts = y[None, None, :] - offs[:, None, :] + offs[None, :, :]
            for k in range(nsp):
                if f.periodic[k + 1]:
                    pts[..., k + 1] %= sys.spatial[k]
            unknown = np.all(pts == (y + e0), axis=-1)  # (K, K)
            idx = tuple(torch.from_numpy(pts[..., d]) for d in range(nsp + 1))
            base = psi[idx].clone()  # (K, K, m)
            u = psi[tuple(int(v) for v in y + e0)].clone()
            mask = torch.from_numpy(unknown)
            for it in range(1, max_newton + 1):
                total_it += 1
                uu = u.clone().requires_grad_(True)
                with torch.enable_grad():
                    x = torch.where(mask[..., None], uu.expand_as(base), base)
                    (g,) = torch.autograd.grad(model(x).sum(), x, create_graph=True)
                    el = vol * g[torch.arange(st.size), torch.arange(st.size)].sum(0)  # sum_a d_a L(cell y - s_a)
                    jac = torch.stack([torch.autograd.grad(el[c], uu, retain_graph=True)[0] for c in range(m)])
                res = float(el.detach().abs().max())
                if not math.isfinite(res):
                    return total_it, res, None, ("residual is not finite", row * m, res)
                try:
                    step = torch.linalg.solve(jac, -el.detach())
                except RuntimeError:
                    return total_it, res, None, ("singular mixed Hessian", row * m, res)
                u = u + step
                if float(step.abs().max()) <= rtol * unk_scale:
                    break
            else:
                return total_it, res, None, (f"Newton did not converge in {max_newton} iterations", row * m, res)
            old = psi[tuple(int(v) for v in y + e0)]
            change = max(change, float((u - old).abs().max()))
            psi[tuple(int(v) for v in y + e0)] = u
            worst = max(worst, res)
        if sys.triangular or change <= 10 * rtol * unk_scale:
            break
    else:
        return total_it, worst, None, ("site-by-site sweeps did not converge", None, worst)
    return total_it, worst, None, None


# -- 1D serving: a batch of trajectories stepped together -------------------------------------------------------
def _serve_batch(model: AbstractLagrangian, fs: list[LatticeField], steps: list[int], mode: str, rtol: float,
                 max_newton: int, box: float | None, progress: bool | None) -> list[ServeResult]:
    """Step a batch of 1D trajectories together; a member that fails or leaves the box retires alone."""
    st = model.stencil
    a0, a1 = st.anchor, st.forward
    b = len(fs)
    m = fs[0].ncomp
    nmax = max(steps)
    psi = torch.full((b, nmax, m), math.nan, dtype=torch.float64)
    for k, f in enumerate(fs):
        psi[k, :2] = f.values[:2]
    vol = math.prod(model.spacing)
    length = list(steps)
    reason = ["complete"] * b
    failed = [False] * b
    fail_at: dict[int, tuple[int, float]] = {}
    active = list(range(b))
    worst = torch.zeros(b, dtype=torch.float64)
    iters = torch.zeros(b, dtype=torch.long)
    max_iters = torch.zeros(b, dtype=torch.long)
    t0 = time.perf_counter()
    groups = [active] if mode == "newton" else [[k] for k in active]
    g_prev_all, _ = cell_derivatives(model, psi[:, 0:2], [])
    g_prev_all = g_prev_all[:, a1].clone()  # d L(q_{i-1}, q_i) / d q_i, per member
    # A model whose mixed Hessian is constant by construction (the kinetic-potential MLP) has the same
    # Jacobian d r / d u at every state: it is assembled once, and Newton needs only gradients after that
    # (an exact Newton step, not a chord). Other models get fresh Hessian blocks every iteration: a chord
    # step with a stale Jacobian was seen to land near a spurious root at a stiff turning point.
    const_model = bool(getattr(model, "constant_mixed_hessian", False))
    jac_const: torch.Tensor | None = None
    bar = _bar(nmax - 2, f"serve ({mode}, {b} trajectories)", progress)

    def retire(k: int, slices: int, why: str, bad: bool, res: float = math.nan) -> None:
        length[k] = slices
        reason[k] = why
        failed[k] = bad
        if bad:
            fail_at[k] = (slices, res)

    for i in range(1, nmax - 1):
        for group in groups:
            act_list = [k for k in group if length[k] > i + 1 and reason[k] == "complete"]
            if not act_list:
                continue
            act = torch.tensor(act_list, dtype=torch.long)
            q_now, q_old = psi[act, i], psi[act, i - 1]
            g_prev = g_prev_all[act]
            u = 2 * q_now - q_old
            mag = torch.maximum(torch.maximum(q_now.abs().amax(-1), q_old.abs().amax(-1)), u.abs().amax(-1))
            rscale = None
            ok = torch.zeros(len(act_list), dtype=torch.bool)
            sing = torch.zeros(len(act_list), dtype=torch.bool)
            # Backtracking: a Newton step that does not lower the residual (a poor predictor at a stiff
            # turning point, say) is halved instead, so Newton finds the root near the predictor rather
            # than a spurious one far away. A step below rtol times the values counts as converged, as
            # in the n-D slice Newton (the residual can stall at round-off just above rtol * rscale).
            prev = torch.full((len(act_list),), math.inf, dtype=torch.float64)
            last = torch.zeros_like(u)
            halved = torch.zeros(len(act_list), dtype=torch.long)
            small = torch.zeros(len(act_list), dtype=torch.bool)
            for it in range(1, max_newton + 1):
                cells = torch.stack([q_now, u], dim=1)
                if jac_const is not None:  # constant mixed Hessian: the gradient is all that changes
                    g = CellDerivatives(model, cells).grad
                    jac = jac_const.expand(len(act_list), m, m)
                else:
                    g, blocks = cell_derivatives(model, cells, [(a0, a1)])
                    jac = vol * blocks[(a0, a1)]  # d r_i / d u_j = vol d^2 L / dx_{a0,i} dx_{a1,j}
                    if const_model:
                        jac_const = jac[0].clone()
                r = vol * (g[:, a0] + g_prev)
                rabs = r.abs().amax(-1)
                if rscale is None:  # size of the kinetic terms, per trajectory
                    rscale = torch.linalg.matrix_norm(jac, ord=math.inf).clamp_min(1e-300) * mag.clamp_min(1e-300)
                ok = (rabs <= rtol * rscale) | (small & torch.isfinite(rabs))
                iters[act] += (~ok).long() if it > 1 else 1
                if bool(ok.all()) or it == max_newton:
                    break
                worse = ~ok & ~sing & ~(rabs < prev) & (halved < 12)
                last = torch.where(worse[:, None], last / 2, last)
                step, info = torch.linalg.solve_ex(jac, -r)
                sing = sing | (~worse & ((info != 0) | ~torch.isfinite(step).all(-1)))
                take = ~ok & ~sing & ~worse
                u = torch.where(worse[:, None], u - last, torch.where(take[:, None], u + step, u))
                prev = torch.where(take, rabs, prev)
                last = torch.where(take[:, None], step, last)
                halved = torch.where(take, 0, halved + worse.long())
                small = (take | worse) & (last.abs().amax(-1) <= rtol * mag)
            psi[act, i + 1] = u
            g_prev_all[act] = g[:, a1]
            max_iters[act] = torch.maximum(max_iters[act], torch.tensor(it))
            worst[act] = torch.maximum(worst[act], torch.where(ok, rabs, worst[act]))
            bad = ~ok
            if bool(bad.any()):
                for j in torch.nonzero(bad).flatten().tolist():
                    k = act_list[j]
                    f = fs[k]
                    tval = float(f.coords[f.dims[0]][0] + (i + 1) * f.spacing[0])
                    why = "singular mixed Hessian" if bool(sing[j]) else \
                        f"Newton did not converge in {max_newton} iterations"
                    res = float(rabs[j])
                    retire(k, i + 1, f"slice {i + 1} (t = {tval:.6g}): {why}, residual {res:.3e}", True, res)
                    worst[k] = max(float(worst[k]), res)
            if box is not None:
                out = (u.norm(dim=-1) > box) & ok
                for j in torch.nonzero(out).flatten().tolist():
                    retire(act_list[j], i + 2, f"left the box |psi| <= {box:g} at slice {i + 1}", False)
        bar.update(1)
    bar.close()
    wall = time.perf_counter() - t0
    solved = sum(max(n - 2, 0) for n in length)
    out = []
    for k, f in enumerate(fs):
        n = length[k]
        lf = LatticeField.with_values(f, psi[k, :n].clone())
        out.append(ServeResult(field=lf.to_dataarray(), complete=not failed[k], reason=reason[k], slices=n,
                               newton_iterations=int(iters[k]), max_newton_iterations=int(max_iters[k]),
                               wall_time=wall, sites_per_second=solved / wall if wall > 0 else math.inf,
                               max_residual=float(worst[k]), mode=mode, solver=mode))
        out[-1].fail_at = fail_at.get(k)  # type: ignore[attr-defined]
    return out


# -- public ----------------------------------------------------------------------------------------------------
def serve(model: AbstractLagrangian, init: xr.DataArray | Sequence[xr.DataArray], *, steps: int | None = None,
          boundary: BoundaryKinds | None = None, mode: str = "newton", rtol: float = 1e-10, max_newton: int = 30,
          box: float | None = None, affine: bool = True,
          progress: bool | None = None) -> ServeResult | list[ServeResult]:
    """Predict a field from its first two time slices (and boundary strips) with the learned ``L_d``.

    Parameters
    ----------
    model : AbstractLagrangian
        A learned (or analytic) model.
    init : DataArray, or a list of 1D DataArrays
        The first two time slices, and for Dirichlet axes the boundary strips
        on every slice to serve (so usually the whole reference field). A
        list of 1D fields is served as one batch.
    steps : int, optional
        Number of time slices of the served field, the two initial ones
        included (default: the length of ``init`` along time).
    boundary : "dirichlet", "periodic" or dict axis -> kind, optional
        Per spatial axis; default from the coordinates' ``periodic`` attribute,
        else Dirichlet.
    mode : "newton" or "sweep"
        Whole-slice Newton (fast) or the paper's site-by-site sweep (reference).
    rtol : float
        Newton stops when the residual is below ``rtol`` times the size of the
        kinetic terms.
    box : float, optional
        1D only: a trajectory stops (completed) once ``|psi| > box``.
    affine : bool
        n-D ``mode="newton"`` only. When the DEL is affine in the field (a
        quadratic ``L_d`` such as the wave or Klein-Gordon ``L_d``: detected
        from the model's Hessian and gradient at random states), serve the
        affine recurrence ``P psi_{i-1} + C psi_i + N psi_{i+1} + c = 0`` with
        ``N`` factorised once: one sparse solve per slice instead of Newton's
        autograd passes. The served field is then checked against the model's
        own DEL (the same residual test as Newton's); from the first slice that
        fails it, Newton takes over. ``False``: always Newton.
    progress : bool, optional
        Progress bar; ``None`` shows it only on a terminal.

    Returns
    -------
    ServeResult, or a list of them for a list ``init``.

    Raises
    ------
    ServeError
        When Newton fails; the message names the slice, site and residual,
        and ``err.result`` holds what was solved.

    Examples
    --------
    Störmer–Verlet for the harmonic oscillator, served from its Lagrangian:

    >>> import numpy as np, xarray as xr, latticedft as ldft
    >>> osc = ldft.lagrangians.verlet(lambda q: 0.5 * q ** 2)
    >>> t = np.arange(2) * 0.1
    >>> init = xr.DataArray([1.0, np.cos(0.1)], dims="t", coords={"t": t}, name="psi")
    >>> out = ldft.serve(osc, init, steps=64)
    >>> out.complete, out.field.sizes["t"]
    (True, 64)
    """
    if mode not in MODES:
        raise InputError(f"mode: expected one of {list(MODES)}, got {mode!r}")
    if not (isinstance(rtol, float) and 0 < rtol < 1):
        raise InputError(f"rtol: expected a float in (0, 1), got {rtol!r}")
    if box is not None and not (isinstance(box, (int, float)) and box > 0):
        raise InputError(f"box: expected a positive number, got {box!r}")
    batch = isinstance(init, (list, tuple))
    items = list(init) if batch else [init]
    if not items:
        raise InputError("init: no initial fields given")
    fs = [as_lattice_field(d, source="init" if not batch else f"init[{k}]", boundary=boundary, min_slices=2)
          for k, d in enumerate(items)]
    _prepare_model(model, fs[0])
    for k, f in enumerate(fs):
        _check_model_lattice(model, f, "init" if not batch else f"init[{k}]")
    n = fs[0].ndim
    if n == 1:
        results = _serve_batch(model, fs, [_steps(steps, f) for f in fs], mode, rtol, max_newton, box, progress)
        failed = [r for r in results if not r.complete]
        if failed:
            first = failed[0]
            at_slice, res = first.fail_at
            raise ServeError(first.reason, result=results if batch else first, slice=at_slice, residual=res)
        return results if batch else results[0]
    if box is not None:
        raise InputError("box: stopping when leaving a box is for 1D trajectories only")
    out = [_serve_field(model, f, _steps(steps, f), mode, rtol, max_newton, progress, bool(affine)) for f in fs]
    return out if batch else out[0]
