"""The exact solve of a linear model: the gauge-constrained least-squares problem for ``coef``.

For ``L_d = features @ coef`` the DEL residual on the interior sites is ``R @ coef`` and the gauge a set
of linear equations ``G coef = g``; ``coef`` minimises ``|R coef|^2`` (plus an optional ridge) subject to
them.

Streamed (the default), ``R`` is never held: its rows are computed chunk by chunk and folded into the
triangular factor ``T`` of a QR factorisation (``R = Q T``, so ``|R x| = |T x|`` for every ``x``), a
``C x C`` matrix whatever the data size; the gauge rows are sums over cells. Householder QR is backward
stable, so ``T`` keeps the singular values of ``R`` down to round-off of ``|R|``; the normal equations
``R^T R`` would square the condition number and lose the directions below ``sqrt(eps)`` that the solve's
cut-off (``1e-10``) must see. Several processes each fold their share and the factors are stacked and
folded again (TSQR). In memory (``chunk_sites=0``) ``R`` itself is built and solved, as before.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.linalg.lapack
import torch

from .._errors import InputError
from .._lattice import LatticeField, gather_cells, interior_slices
from .._models import LinearLagrangian
from . import _dist
from ._data import kinetic_scale, kinetic_sums, site_sums, split_point, time_split
from ._gauge import Gauge
from ._source import FieldSource, Piece, pieces
from ._stream import TrainingData, share_of

__all__ = ["learn_exact", "residual_matrix", "gauge_matrix", "mean_mixed_hessian", "site_rows", "Triangle"]

_RIDGE_GRID = (0.0, 1e-14, 1e-12, 1e-10, 1e-8, 1e-6, 1e-4)


def residual_matrix(model: LinearLagrangian, f: LatticeField) -> np.ndarray:
    """Rows: DEL residual components on interior sites; columns: basis functions. ``EL = R @ coef``.

    Per-cell derivatives of every basis function (:meth:`LinearLagrangian.feature_derivatives`), then the
    adjoint of the cell gather puts them on the sites.
    """
    d, _ = model.feature_derivatives(gather_cells(f.values, model.stencil, f.boundary))
    return _site_rows(model, f, d)


def _site_rows(model: LinearLagrangian, f: LatticeField, d: torch.Tensor) -> np.ndarray:
    """:func:`residual_matrix` from the per-cell first derivatives ``d`` of the basis functions on ``f``."""
    st = model.stencil
    c = d.shape[-1]
    z = torch.zeros(*f.values.shape, c, dtype=torch.float64, requires_grad=True)
    with torch.enable_grad():
        (sites,) = torch.autograd.grad((gather_cells(z, st, f.boundary) * d).sum(), z)
    sites = math.prod(model.spacing) * sites  # (*N, m, C)
    inner = interior_slices(f.shape, st, f.boundary)
    return sites[inner].reshape(-1, c).numpy()


def residual_matrices(
    model: LinearLagrangian, fields: list[LatticeField], mean: bool
) -> tuple[list[np.ndarray], np.ndarray | None]:
    """:func:`residual_matrix` of every field and, if ``mean``, :func:`mean_mixed_hessian` (else None), the
    basis functions differentiated once per field for both (the same numbers as the two apart)."""
    st = model.stencil
    pair = (st.anchor, st.forward)
    m, c = model.m, model.n_terms
    total = torch.zeros(c, m, m, dtype=torch.float64)
    ncells = 0
    rows = []
    for f in fields:
        x = gather_cells(f.values, st, f.boundary)
        d, blocks = model.feature_derivatives(x, [pair] if mean else [])
        rows.append(_site_rows(model, f, d))
        if mean:
            ncells += x[..., 0, 0].numel()
            total += blocks[pair].reshape(-1, m, m, c).sum(0).permute(2, 0, 1)
    return rows, (total / ncells).numpy() if mean else None


def gauge_matrix(
    model: LinearLagrangian, fields: list[LatticeField], gauge: Gauge
) -> tuple[np.ndarray, np.ndarray] | None:
    """Constraint rows ``G coef = g`` of the gauge on the mean mixed Hessian over all training cells
    (``None`` for no gauge)."""
    if not gauge.fixes:
        return None
    return gauge.constraint(mean_mixed_hessian(model, fields), model.spacing[0])


def mean_mixed_hessian(model: LinearLagrangian, fields: list[LatticeField]) -> np.ndarray:
    """Every basis function's mixed time Hessian (anchor, forward) averaged over all training cells: ``(C, m, m)``."""
    st = model.stencil
    pair = (st.anchor, st.forward)
    m, c = model.m, model.n_terms
    total = torch.zeros(c, m, m, dtype=torch.float64)
    ncells = 0
    for f in fields:
        x = gather_cells(f.values, st, f.boundary)
        ncells += x[..., 0, 0].numel()
        _, blocks = model.feature_derivatives(x, [pair], first=False)
        total += blocks[pair].reshape(-1, m, m, c).sum(0).permute(2, 0, 1)
    return (total / ncells).numpy()


def ridge_weight(r: np.ndarray, ridge: float) -> float:
    """The weight of the ridge term: ``ridge`` times the mean squared column norm of the rows ``r`` (1 for zero
    rows), so that ``ridge`` is relative to the data's own scale."""
    return ridge * (float((r**2).sum(0).mean()) or 1.0)


def _constrained_lstsq(r: np.ndarray, g_mat: np.ndarray | None, g_vec: np.ndarray | None, ridge: float) -> np.ndarray:
    c = r.shape[1]
    lam = ridge_weight(r, ridge)
    if g_mat is None:  # no gauge: the unit-norm minimiser (what an unconstrained trainer drifts to)
        a = np.vstack([r, math.sqrt(lam) * np.eye(c)]) if lam > 0 else r
        _, _, vt = np.linalg.svd(a, full_matrices=True)
        return vt[-1]
    assert g_vec is not None
    split = _gauge_split(g_mat, g_vec)
    if split is None:
        raise _no_hessian()
    return _null_solve(r, *split, lam)


def _no_hessian() -> InputError:
    return InputError(
        "model: no basis function gives a mixed time Hessian, so no L_d of this class can "
        "describe dynamics (raise the orders)"
    )


def _gauge_split(g_mat: np.ndarray, g_vec: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``(theta_p, null)``: the minimum-norm solution of the gauge rows ``G coef = g`` and an orthonormal basis
    of their null space (columns), every solution being ``theta_p + null @ z``; None where ``G`` is zero. They
    depend on the gauge rows alone, so a sparse fit keeps them per support."""
    u, s, vt = np.linalg.svd(g_mat, full_matrices=True)
    if s.size == 0 or s[0] == 0:
        return None
    rank = int((s > 1e-12 * s[0]).sum())
    theta_p = vt[:rank].T @ ((u[:, :rank].T @ g_vec) / s[:rank])
    return theta_p, vt[rank:].T


def _null_solve(r: np.ndarray, theta_p: np.ndarray, null: np.ndarray, lam: float) -> np.ndarray:
    """The coefficients ``theta_p + null @ z`` minimising ``|r coef|^2 + lam |coef|^2`` (:func:`_gauge_split`)."""
    if null.shape[1] == 0:
        return theta_p
    a = r @ null
    b = -(r @ theta_p)
    if lam > 0:
        a = np.vstack([a, math.sqrt(lam) * null])
        b = np.concatenate([b, -math.sqrt(lam) * theta_p])
    # Null Lagrangians (discrete divergences, e.g. a term linear in one difference) have zero columns in
    # exact arithmetic but round-off ones in practice: without a cutoff they get huge coefficients that
    # swamp L_d and break the gauge (seen on the 1+1D wave string). Drop directions below 1e-10 relative.
    return theta_p + null @ _gelsd(a, b, 1e-10)


_DGELSD, _DGELSD_LWORK = scipy.linalg.lapack.get_lapack_funcs(("gelsd", "gelsd_lwork"), (np.zeros(1),))
_GELSD_WORK: dict[tuple[int, int, float], tuple[int, int]] = {}


def _gelsd(a: np.ndarray, b: np.ndarray, cond: float) -> np.ndarray:
    """``scipy.linalg.lstsq(a, b, cond, lapack_driver="gelsd")[0]`` for a vector ``b``, the same LAPACK call
    without the wrapper's per-call set-up (the workspace query is kept per shape): a sparse fit solves some
    hundred systems of a few columns, where that set-up outweighed the arithmetic."""
    m, n = a.shape
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise ValueError("array must not contain infs or NaNs")
    if m == 0 or n == 0:
        return np.zeros(n)
    key = (m, n, cond)
    if key not in _GELSD_WORK:
        work, iwork, info = _DGELSD_LWORK(m, n, 1, cond)
        if info != 0:
            raise ValueError(f"internal work array size computation failed: {info}")
        _GELSD_WORK[key] = (int(work.real), int(iwork))
    lwork, liwork = _GELSD_WORK[key]
    if m < n:  # room for the solution
        b = np.concatenate([b, np.zeros(n - m)])
    x, _, _, info = _DGELSD(a, b, lwork, liwork, cond, False, False)
    if info > 0:
        raise np.linalg.LinAlgError("SVD did not converge in Linear Least Squares")
    if info < 0:
        raise ValueError(f"illegal value in {-info}-th argument of internal gelsd")
    return np.asarray(x[:n])


def _ridge_folds(
    model: LinearLagrangian, fields: list[LatticeField], rs: list[np.ndarray]
) -> list[tuple[list[np.ndarray], list[np.ndarray], list[LatticeField]]]:
    """(training residual matrices, held-out ones, held-out fields): leave one field out (up to 6 folds),
    or for a single field its first 70 % against the rest."""
    if len(fields) >= 2:
        return [([r for j, r in enumerate(rs) if j != i], [rs[i]], [fields[i]]) for i in range(min(len(fields), 6))]
    split = time_split(fields[0])
    if split is None:
        raise InputError.at("ridge", "'auto' needs two or more fields, or one field of at least 9 time slices")
    return [([residual_matrix(model, split[0])], [residual_matrix(model, split[1])], [split[1]])]


def _moving(kinetic: list[float]) -> list[int]:
    """The folds whose held-out data move (a nonzero second time difference): a residual is measured relative
    to that motion, so a field at rest (an equilibrium) cannot validate a ridge weight; raises
    :class:`InputError` when no fold is left."""
    keep = [i for i, k in enumerate(kinetic) if k > 0 and math.isfinite(k)]
    if not keep:
        raise InputError.at("ridge", "'auto' has no held-out field in motion (every one is at rest)")
    return keep


def _pick_ridge(
    model: LinearLagrangian,
    fields: list[LatticeField],
    rs: list[np.ndarray],
    g_mat: np.ndarray | None,
    g_vec: np.ndarray | None,
) -> tuple[float, dict[str, float]]:
    """The ridge weight of the grid with the smallest held-out relative residual, and every score (folds
    whose held-out fields do not move are left out: see :func:`_moving`)."""
    folds = _ridge_folds(model, fields, rs)
    folds = [folds[i] for i in _moving([kinetic_scale(v, model, None) for _, _, v in folds])]
    validation: dict[str, float] = {}
    best, best_score = 0.0, math.inf
    for lam in _RIDGE_GRID:
        scores = []
        for train, val, vfields in folds:
            rt = np.vstack(train) / math.sqrt(sum(r.shape[0] for r in train) / model.m)
            theta = _constrained_lstsq(rt, g_mat, g_vec, lam)
            rv = np.vstack(val)
            res = math.sqrt(float(((rv @ theta) ** 2).sum()) / (rv.shape[0] / model.m))
            scores.append(res / kinetic_scale(vfields, model, None))
        score = float(np.mean(scores))
        validation[f"{lam:g}"] = score
        if score < best_score * (1 - 1e-9):
            best, best_score = lam, score
    return best, validation


def _learn_in_memory(
    model: LinearLagrangian, fields: list[LatticeField], gauge: Gauge, ridge: float | str, nsites: int
) -> tuple[float, dict[str, float]]:
    rs = [residual_matrix(model, f) for f in fields]
    g_mat, g_vec = gauge_matrix(model, fields, gauge) or (None, None)
    validation: dict[str, float] = {}
    if ridge == "auto":
        ridge, validation = _pick_ridge(model, fields, rs, g_mat, g_vec)
    r = np.vstack(rs) / math.sqrt(nsites)
    theta = _constrained_lstsq(r, g_mat, g_vec, float(ridge))
    with torch.no_grad():
        model.coef.copy_(torch.from_numpy(theta))
    return float(ridge), validation


# -- streamed --------------------------------------------------------------------------------------------------
def _qr_r(a: np.ndarray) -> np.ndarray:
    """The triangular factor of ``a`` (``min(rows, C) x C``)."""
    return np.asarray(np.linalg.qr(a, mode="r"))  # mode "r": the array R alone


def _fold_rows(t: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The triangular factor of ``t`` stacked on ``rows``. Once ``t`` is square, LAPACK's triangular-pentagonal
    QR (``dtpqrt``) skips the known zeros below ``t``'s diagonal (about twice as fast as a QR of the stack)."""
    c = t.shape[1]
    if t.shape[0] == c and rows.shape[0] > 0:
        r, _, _, info = scipy.linalg.lapack.dtpqrt(0, min(32, c), np.asfortranarray(t), np.asfortranarray(rows))
        if info == 0:
            return np.triu(r)
    return _qr_r(np.vstack([t, rows]))


class Triangle:
    """Rows of a least-squares system folded as they come: the triangular factor ``T`` with ``|R x| = |T x|``
    for the rows ``R`` added so far. Rows are buffered up to a few thousand and folded by one QR of ``T``
    stacked on them."""

    def __init__(self, c: int):
        self.c = c
        self.t = np.zeros((0, c))
        self._buffer: list[np.ndarray] = []
        self._buffered = 0
        self._flush = max(8 * c, 1024)

    def add(self, rows: np.ndarray) -> None:
        self._buffer.append(rows)
        self._buffered += rows.shape[0]
        if self._buffered >= self._flush:
            self._fold()

    def _fold(self) -> None:
        if self._buffer:
            self.t = _fold_rows(self.t, np.vstack(self._buffer) if len(self._buffer) > 1 else self._buffer[0])
            self._buffer, self._buffered = [], 0

    def factor(self) -> np.ndarray:
        """``T`` padded to ``C x C`` (zero rows change no norm)."""
        self._fold()
        out = np.zeros((self.c, self.c))
        out[: self.t.shape[0]] = self.t
        return out


def _stacked_factor(ts: list[np.ndarray]) -> np.ndarray:
    """The factor of the rows of several factors (one QR of them stacked)."""
    return ts[0] if len(ts) == 1 else _qr_r(np.vstack(ts))


def site_rows(model: LinearLagrangian, f: LatticeField, d: torch.Tensor) -> np.ndarray:
    """Rows of ``R`` on the interior sites of ``f`` from the basis functions' per-cell derivatives ``d``
    (``(*cells, K, m, C)``): one row per site and component."""
    return site_sums(model, f, d).reshape(-1, d.shape[-1]).numpy()


@dataclass
class _Group:
    """The streamed system of one group of fields (a ridge fold's unit): its factor, sites and kinetic sums."""

    tri: Triangle
    sites: float = 0.0
    kinetic: list[float] = field(default_factory=lambda: [0.0, 0.0])
    t: np.ndarray | None = None


@dataclass
class _Pass:
    """Sources read in one pass: each source's group, and whether its cells enter the gauge rows."""

    sources: list[FieldSource]
    chunks: list[list[Piece]]
    group: list[int]
    gauge: bool


def _passes(data: TrainingData, ridge: float | str) -> tuple[list[_Pass], int, list[tuple[list[int], int]], list[int]]:
    """(passes over the data, number of groups, ridge folds as (training groups, held-out group), the groups of
    the final fit). Without ``ridge="auto"`` one group holds everything; with it each of the first six fields
    is a group of its own (leave one field out), or a single field's first 70 % and the rest are two groups
    read in a second pass besides the whole field."""
    n = len(data.sources)
    if ridge != "auto":
        return [_Pass(data.sources, data.chunks, [0] * n, True)], 1, [], [0]
    if n >= 2:
        held = min(n, 6)
        group = [min(i, held) for i in range(n)]
        ngroups = held + (1 if n > held else 0)
        folds = [([g for g in range(ngroups) if g != i], i) for i in range(held)]
        return [_Pass(data.sources, data.chunks, group, True)], ngroups, folds, list(range(ngroups))
    cut = split_point(data.sources[0].nt)
    if cut is None:
        raise InputError.at("ridge", "'auto' needs two or more fields, or one field of at least 9 time slices")
    src = data.sources[0]
    parts = [src.window(0, cut), src.window(cut, src.nt)]
    assert data.stencil is not None
    extra = pieces(parts, data.stencil, data.budget)
    return (
        [_Pass(data.sources, data.chunks, [2], True), _Pass(parts, extra, [0, 1], False)],
        3,
        [([0], 1)],
        [2],
    )


def _learn_streamed(
    model: LinearLagrangian, data: TrainingData, gauge: Gauge, ridge: float | str, nsites: int
) -> tuple[float, dict[str, float]]:
    st = model.stencil
    m, c = model.m, model.n_terms
    pair = (st.anchor, st.forward)
    passes, ngroups, folds, final = _passes(data, ridge)
    held_out = {v for _, v in folds}
    groups = [_Group(Triangle(c)) for _ in range(ngroups)]
    gsum = torch.zeros(m, m, c, dtype=torch.float64)
    ncells = torch.zeros((), dtype=torch.float64)
    for ps in passes:
        for chunk in share_of(ps.chunks, ps.sources):
            for piece in chunk:
                f, skip = piece.read(ps.sources, st)
                cells = gather_cells(f.values, st, f.boundary)
                want = [pair] if gauge.fixes and ps.gauge else []
                d, blocks = model.feature_derivatives(cells, want, first=True)
                g = groups[ps.group[piece.source]]
                rows = site_rows(model, f, d)
                g.tri.add(rows)
                g.sites += rows.shape[0] / m
                if want:
                    own = blocks[pair].reshape(-1, m, m, c)
                    own = own[skip * (own.shape[0] // (f.shape[0] - int(st.width[0]))) :] if skip else own
                    gsum += own.sum(0)
                    ncells += own.shape[0]
                if ps.group[piece.source] in held_out:
                    total, count = kinetic_sums(f, model, None)
                    g.kinetic[0] += total
                    g.kinetic[1] += count
    # combine the processes' shares: factors stacked and folded, sums summed
    for g in groups:
        g.t = _stacked_factor(_dist.all_gather(g.tri.factor()))
        sums = _dist.all_sum(torch.tensor([g.sites, *g.kinetic], dtype=torch.float64))
        g.sites, g.kinetic = float(sums[0]), [float(sums[1]), float(sums[2])]
    g_mat = g_vec = None
    if gauge.fixes:
        gsum, ncells = _dist.all_sum(gsum), _dist.all_sum(ncells)
        rows_ = gauge.constraint((gsum / ncells).permute(2, 0, 1).numpy(), model.spacing[0])
        g_mat, g_vec = rows_ if rows_ is not None else (None, None)
    validation: dict[str, float] = {}
    if ridge == "auto":
        ridge, validation = _pick_ridge_streamed(groups, folds, g_mat, g_vec)
    t = _stacked_factor([g.t for g in (groups[i] for i in final) if g.t is not None]) / math.sqrt(nsites)
    theta = _constrained_lstsq(t, g_mat, g_vec, float(ridge))
    with torch.no_grad():
        model.coef.copy_(torch.from_numpy(theta))
    return float(ridge), validation


def _pick_ridge_streamed(
    groups: list[_Group], folds: list[tuple[list[int], int]], g_mat: np.ndarray | None, g_vec: np.ndarray | None
) -> tuple[float, dict[str, float]]:
    """:func:`_pick_ridge` on the groups' factors: ``|R_v theta| = |T_v theta|`` on the held-out group."""
    folds = [folds[i] for i in _moving([groups[v].kinetic[0] for _, v in folds])]
    factors = [  # each fold's training system, once
        _stacked_factor([t for t in (groups[i].t for i in train) if t is not None])
        / math.sqrt(sum(groups[i].sites for i in train))
        for train, _ in folds
    ]
    validation: dict[str, float] = {}
    best, best_score = 0.0, math.inf
    for lam in _RIDGE_GRID:
        scores = []
        for rt, (_, val) in zip(factors, folds):
            theta = _constrained_lstsq(rt, g_mat, g_vec, lam)
            v = groups[val]
            assert v.t is not None
            res = math.sqrt(float(((v.t @ theta) ** 2).sum()) / v.sites)
            scores.append(res / math.sqrt(v.kinetic[0] / max(v.kinetic[1], 1.0)))
        score = float(np.mean(scores))
        validation[f"{lam:g}"] = score
        if score < best_score * (1 - 1e-9):
            best, best_score = lam, score
    return best, validation


def learn_exact(
    model: LinearLagrangian, data: TrainingData, gauge: Gauge, ridge: float | str, nsites: int
) -> tuple[float, dict[str, float]]:
    """Solve for ``model.coef`` in place; returns the ridge weight used and the validation scores of
    ``ridge="auto"`` (empty otherwise)."""
    if data.in_memory:
        return _learn_in_memory(model, data.fields, gauge, ridge, nsites)
    return _learn_streamed(model, data, gauge, ridge, nsites)
