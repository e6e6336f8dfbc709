"""The exact solve of a linear model: the gauge-constrained least-squares problem for ``coef``.

For ``L_d = features @ coef`` the DEL residual on the interior sites is ``R @ coef`` and the gauge a set
of linear equations ``G coef = g``; ``coef`` minimises ``|R coef|^2`` (plus an optional ridge) subject to
them.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg
import torch

from .._errors import InputError
from .._lattice import LatticeField, gather_cells, interior_slices
from .._models import LinearLagrangian
from ._data import kinetic_scale, time_split
from ._gauge import Gauge

__all__ = ["learn_exact", "residual_matrix", "gauge_matrix"]

_RIDGE_GRID = (0.0, 1e-14, 1e-12, 1e-10, 1e-8, 1e-6, 1e-4)


def residual_matrix(model: LinearLagrangian, f: LatticeField) -> np.ndarray:
    """Rows: DEL residual components on interior sites; columns: basis functions. ``EL = R @ coef``.

    Per-cell derivatives of every basis function (:meth:`LinearLagrangian.feature_derivatives`), then the
    adjoint of the cell gather puts them on the sites.
    """
    st = model.stencil
    x = gather_cells(f.values, st, f.boundary)
    d, _ = model.feature_derivatives(x)  # (*cells, K, m, C)
    c = d.shape[-1]
    z = torch.zeros(*f.values.shape, c, dtype=torch.float64, requires_grad=True)
    with torch.enable_grad():
        (sites,) = torch.autograd.grad((gather_cells(z, st, f.boundary) * d).sum(), z)
    sites = math.prod(model.spacing) * sites  # (*N, m, C)
    inner = interior_slices(f.shape, st, f.boundary)
    return sites[inner].reshape(-1, c).numpy()


def gauge_matrix(
    model: LinearLagrangian, fields: list[LatticeField], gauge: Gauge
) -> tuple[np.ndarray, np.ndarray] | None:
    """Constraint rows ``G coef = g`` of the gauge on the mean mixed Hessian over all training cells
    (``None`` for no gauge)."""
    if not gauge.fixes:
        return None
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
    return gauge.constraint((total / ncells).numpy(), model.spacing[0])  # mean: (C, m, m)


def _constrained_lstsq(r: np.ndarray, g_mat: np.ndarray | None, g_vec: np.ndarray | None, ridge: float) -> np.ndarray:
    c = r.shape[1]
    colsq = float((r**2).sum(0).mean()) or 1.0
    lam = ridge * colsq
    if g_mat is None:  # no gauge: the unit-norm minimiser (what an unconstrained trainer drifts to)
        a = np.vstack([r, math.sqrt(lam) * np.eye(c)]) if lam > 0 else r
        _, _, vt = np.linalg.svd(a, full_matrices=True)
        return vt[-1]
    u, s, vt = np.linalg.svd(g_mat, full_matrices=True)
    if s.size == 0 or s[0] == 0:
        raise InputError(
            "model: no basis function gives a mixed time Hessian, so no L_d of this class can "
            "describe dynamics (raise the orders)"
        )
    rank = int((s > 1e-12 * s[0]).sum())
    theta_p = vt[:rank].T @ ((u[:, :rank].T @ g_vec) / s[:rank])
    null = vt[rank:].T
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
    z, *_ = scipy.linalg.lstsq(a, b, cond=1e-10, lapack_driver="gelsd")
    return theta_p + null @ z


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


def _pick_ridge(
    model: LinearLagrangian,
    fields: list[LatticeField],
    rs: list[np.ndarray],
    g_mat: np.ndarray | None,
    g_vec: np.ndarray | None,
) -> tuple[float, dict[str, float]]:
    """The ridge weight of the grid with the smallest held-out relative residual, and every score."""
    folds = _ridge_folds(model, fields, rs)
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


def learn_exact(
    model: LinearLagrangian, fields: list[LatticeField], gauge: Gauge, ridge: float | str, nsites: int
) -> tuple[float, dict[str, float]]:
    """Solve for ``model.coef`` in place; returns the ridge weight used and the validation scores of
    ``ridge="auto"`` (empty otherwise)."""
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
