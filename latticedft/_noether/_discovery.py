"""Discovery of affine internal symmetries of a learned ``L_d`` (as SymDLNN does for ODEs).

The infinitesimal invariance of ``L_d`` under ``xi(psi) = M psi + w`` on one cell reads
``sum_a dL_d/dpsi_a . (M psi_a + w) = 0``: one linear equation in the ``m^2 + m`` unknowns
``(M, w)`` per cell. Stacked over the data's cells it is ``A theta = 0``; the least-squares generator
under ``|theta| = 1`` (which excludes ``M = 0, w = 0``) is the right singular vector of the smallest
singular value of ``A`` (after scaling its columns to unit norm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from .._contract import AbstractLagrangian
from ._core import FieldEval, prepare
from ._group import Symmetry
from ._invariance import DEFAULT_TOL, SymmetryReport, _check_tol, measure

__all__ = ["DiscoveryReport", "discover_symmetries"]


@dataclass
class DiscoveryReport:
    """What :func:`discover_symmetries` found.

    ``symmetries``: one :class:`SymmetryReport` per discovered generator (a basis of the near-null space:
    every singular vector whose invariance residual is at most ``tol``, at least the best one), named
    ``discovered-1``, ``discovered-2``, ...; the generator is ``{"matrix": M, "offset": w}`` scaled so
    that its largest entry is 1. ``singular_values``: of the column-scaled system, ascending, relative to
    the largest. ``gap``: the last kept singular value over the next one (small: a well-separated
    null space). ``unknowns``: the order of the entries of ``theta``.
    """

    symmetries: list[SymmetryReport]
    singular_values: list[float]
    gap: float
    n_cells: int
    unknowns: list[str] = field(default_factory=list)

    @property
    def best(self) -> SymmetryReport:
        return self.symmetries[0]

    def to_dict(self) -> dict[str, Any]:
        return {
            "symmetries": [s.to_dict() for s in self.symmetries],
            "singular_values": self.singular_values,
            "gap": self.gap,
            "n_cells": self.n_cells,
            "unknowns": self.unknowns,
        }

    def summary_line(self) -> str:
        b = self.best
        gen = b.generator
        mat, off = (np.round(gen[k], 6) + 0.0 for k in ("matrix", "offset"))  # + 0.0: no negative zeros
        return (
            f"{len(self.symmetries)} generator(s); best M = {mat.tolist()}, w = {off.tolist()}, "
            f"residual {b.residual:.1e}, gap {self.gap:.1e}"
        )


def _canonical(theta: np.ndarray) -> np.ndarray:
    """Scale to largest entry 1 in magnitude; sign: the last entry within half of the largest is positive."""
    big = np.abs(theta).max()
    theta = theta / big
    last = np.nonzero(np.abs(theta) >= 0.5)[0][-1]
    return theta if theta[last] > 0 else -theta


def discover_symmetries(
    model: AbstractLagrangian,
    data: Any,
    *,
    tol: float = DEFAULT_TOL,
    boundary: Any = None,
    max_generators: int | None = None,
) -> DiscoveryReport:
    """Fit the generators ``xi(psi) = M psi + w`` of the affine internal symmetries of ``L_d`` over data.

    Works for any lattice (mechanics with ``n = 1`` and fields): the symmetry acts on the component
    space, the same at every site. See the module docstring for the linear system; the residual of each
    generator is that of :func:`symmetries` (the per-step change of its Noether charge relative to the
    charge's terms). A model with no affine symmetry still gets its best candidate, with a large residual.
    """
    tol = _check_tol(tol)
    fields = prepare(model, data, boundary)
    evals = [FieldEval(model, f) for f in fields]
    m = fields[0].ncomp
    rows = []
    for ev in evals:
        g = ev.grad.reshape(-1, *ev.grad.shape[-2:])  # (cells, K, m)
        c = ev.cells.reshape(-1, *ev.cells.shape[-2:])
        a_m = torch.einsum("cki,ckj->cij", g, c).reshape(g.shape[0], m * m)
        a_w = g.sum(1)
        rows.append(torch.cat([a_m, a_w], dim=1))
    a = torch.cat(rows).numpy()
    norms = np.linalg.norm(a, axis=0)
    # unit columns, but a column at round-off (an exact symmetry direction) must stay at round-off
    norms = np.maximum(norms, 1e-8 * norms.max()) if norms.max() > 0 else np.ones_like(norms)
    _, s, vt = np.linalg.svd(a / norms, full_matrices=False)
    order = np.argsort(s)
    s_rel = s[order] / s.max() if s.max() > 0 else s[order]
    labels = [f"M[{i},{j}]" for i in range(m) for j in range(m)] + [f"w[{i}]" for i in range(m)]
    limit = len(order) if max_generators is None else max(1, int(max_generators))
    found: list[SymmetryReport] = []
    for rank, k in enumerate(order[:limit]):
        theta = _canonical(vt[k] / norms)
        sym = Symmetry.affine(theta[: m * m].reshape(m, m), theta[m * m :], name=f"discovered-{rank + 1}")
        rep = measure(model, evals, sym, tol)
        if rank > 0 and not rep.invariant:
            break
        found.append(rep)
        if not rep.invariant:
            break
    kept = len(found)
    gap = float(s_rel[kept - 1] / s_rel[kept]) if kept < len(s_rel) and s_rel[kept] > 0 else math.nan
    return DiscoveryReport(
        symmetries=found, singular_values=[float(v) for v in s_rel], gap=gap, n_cells=int(a.shape[0]), unknowns=labels
    )
