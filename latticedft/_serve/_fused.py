"""Slice-Newton in one compiled kernel: every unknown site of a slice solved at once, the stencil gathered and
the residual and Jacobian formed inside the loop over the sites (``latticedft._kernel``, ``slice_newton``).

It serves a scalar closed-form ``L_d`` whose slice Jacobian is block diagonal by its form (each unknown's
equation involves that unknown alone: the first-order stencil with an ``L_d`` whose time difference does not
mix with the spatial ones, as wave, Klein-Gordon, sine-Gordon), once the first Newton slice has chosen the
site-wise solver. Each site iterates Newton's method until its residual is below the slice's tolerance (the
same ``rtol`` times the size of the kinetic terms as slice-Newton's), or one evaluation after a step below
``rtol`` times the values. A slice it cannot finish (a singular Jacobian, no convergence) is handed back, its
predictor restored, to slice-Newton, which reports the failure as usual.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from .._action import compiled_closed_forms
from .._kernel import CompiledForms
from .._lattice import keep_last
from ._slices import SINGULAR_RTOL, _SliceSystem

__all__ = ["FusedSlices", "LatticeTables", "fused_slices", "lattice_tables"]


class FusedSlices:
    """The compiled slice Newton of one served field: its kernels and the index maps they read."""

    def __init__(self, compiled: CompiledForms, sys: _SliceSystem, tables: LatticeTables):
        self.compiled = compiled
        self.site_of = tables.site_of  # (K, cells): the site of each stencil point of each cell
        self.cell_at = tables.cell_at  # (K, sites): the cell whose stencil point sits on the site (-1: none)
        self.interior = tables.interior  # per site: it carries an equation
        self.rows = tables.rows
        self.delta, self.plain = tables.delta, tables.plain
        self.res = np.empty(self.rows.size)
        self.its = np.empty(self.rows.size, dtype=np.int64)
        self.none = np.zeros(0)  # no slice before the previous one
        self.same_site = [
            (q, a) for q, (a, b) in enumerate(sys.pairs) if sys.st.offsets[a][1:] == sys.st.offsets[b][1:]
        ]

    def predict(self, flat: torch.Tensor, i: int, older: torch.Tensor | None) -> None:
        """Slice-Newton's predictor (``_stepper.solve_and_tally``'s) on the unknown sites of slice ``i + 1``."""
        values = flat.numpy()
        old = older.numpy()[:, 0] if older is not None else self.none
        self.compiled.module.predict(
            values[i - 1, :, 0], values[i, :, 0], values[i + 1, :, 0], old, self.rows, self.interior
        )

    def scales(self, flat: torch.Tensor, i: int) -> tuple[float, float, float, int] | None:
        """``(dmax, smin, smax, row)`` of slice ``i``'s Jacobian at the current values, as slice-Newton's
        ``_fresh_blocks`` finds them: the largest diagonal Hessian block over the cells, and the smallest and
        largest diagonal entry (in size) at an unknown site, with the row of the smallest; ``None`` without
        unknowns. Its off-diagonal blocks vanish by the ``L_d``'s form. The diagonal is summed in the
        compiled kernel as ``index_add_`` sums it (one cell per site and point: to the bit)."""
        if not self.rows.size or not self.same_site:
            return None
        diag = np.zeros(self.cell_at.shape[1])
        dmax = float(
            self.compiled.module.site_diagonal(flat[i].numpy()[:, 0], flat[i + 1].numpy()[:, 0], self.site_of, diag)
        )
        if dmax < 0:
            return None  # a block that is not finite: slice-Newton reports it
        sv = np.abs(diag if self.rows.size == diag.size else diag[self.rows])  # every site an unknown: no copy
        if not np.isfinite(sv).all():
            sv = np.nan_to_num(sv, nan=0.0)
        worst = int(np.argmin(sv))
        return dmax, float(sv[worst]), float(sv.max()), worst

    def solve(
        self,
        flat: torch.Tensor,
        i: int,
        older: torch.Tensor | None,
        vol: float,
        rtol: float,
        max_newton: int,
        cache: dict,
    ) -> tuple[int, float] | None:
        """Solve slice ``i``'s equations for slice ``i + 1`` of ``flat`` (``(slices, sites, 1)``) in place, from
        slice-Newton's predictor (with ``older``, slice ``i - 2``, where given): ``(evaluations, residual)``
        (the most of any site), or ``None`` where a site failed (slice-Newton then starts afresh). One call of
        the compiled ``slice_step``: the predictor and its scale, Newton on every site, their tally."""
        values = flat.numpy()
        old = older.numpy()[:, 0] if older is not None else self.none
        lo, hi, worst = self.compiled.slice_step(self.rows.size)(
            values[i - 1, :, 0],
            values[i, :, 0],
            values[i + 1, :, 0],
            old,
            *self._maps(),
            *self._tolerances(vol, rtol, max_newton, cache),
            self.res,
            self.its,
        )
        if not self.rows.size:
            return 1, 0.0
        if lo < 0:
            return None
        return int(hi), float(worst)

    def _maps(self) -> tuple[np.ndarray, ...]:
        """The lattice's maps, as the compiled slice steps take them."""
        return self.site_of, self.cell_at, self.plain, self.delta, self.rows, self.interior

    @staticmethod
    def _tolerances(vol: float, rtol: float, max_newton: int, cache: dict) -> tuple[float, float, float, float, int]:
        """``vol, rtol``, the DEL's largest second derivative, the singular bound and the iteration limit, as the
        compiled slice steps take them."""
        return vol, rtol, cache["dmax"], SINGULAR_RTOL * cache["mscale"] * vol, max_newton

    def solve_many(
        self,
        flat: torch.Tensor,
        i: int,
        stop: int,
        vol: float,
        rtol: float,
        max_newton: int,
        cache: dict,
        before: torch.Tensor | None = None,
    ) -> tuple[int, list[int], list[float]]:
        """Solve the equations of slices ``i .. stop - 1`` of ``flat`` one after the other in one call, each as
        :meth:`solve` solves it (the older slice from slice 2 on; for slice 1, ``before`` where given: the
        slice before ``flat``'s first in a window): ``(j, evaluations, residuals)``, the slice it stopped
        before (``stop`` when all were solved; a slice a site could not finish is left to slice-Newton) and,
        per slice solved, its evaluations and residual. Only for a slice with unknowns."""
        values = flat.numpy().reshape(flat.shape[0], -1)  # (slices, sites): a view, the field being scalar
        older = before.numpy().reshape(-1) if before is not None else self.none
        most = np.zeros(stop, dtype=np.int64)
        worst = np.zeros(stop)
        j = self.compiled.slice_steps(self.rows.size)(
            values,
            i,
            stop,
            older,
            *self._maps(),
            *self._tolerances(vol, rtol, max_newton, cache),
            self.res,
            self.its,
            most,
            worst,
        )
        return int(j), most[i:j].tolist(), worst[i:j].tolist()


@dataclass(frozen=True)
class LatticeTables:
    """The index tables of the compiled slice Newton on one lattice (stencil, spatial shape, boundary kinds):
    the cell maps, the unknown sites, and the sites read at fixed offsets (:func:`fixed_offsets`)."""

    site_of: np.ndarray
    cell_at: np.ndarray
    interior: np.ndarray
    rows: np.ndarray
    delta: np.ndarray
    plain: np.ndarray


#: The tables of the lattices served last (at most :data:`TABLES_KEPT`, each of at most :data:`KEPT_BYTES`),
#: by stencil offsets, spatial shape, components and boundary kinds (which fix them); ``None`` for a lattice
#: whose cell maps do not exist.
_TABLES: dict[tuple[Any, ...], LatticeTables | None] = {}
TABLES_KEPT = 2

#: The most bytes of one lattice's tables kept after its field is served (64^3 sites on the first-order
#: stencil hold about 23 MiB): a larger lattice builds them per field, a small share of its serving time.
KEPT_BYTES = 64 << 20


def lattice_tables(sys: _SliceSystem, module: Any) -> LatticeTables | None:
    """The tables of ``sys``'s lattice, built once and kept for the next fields on the same lattice (a few
    field-sized integer arrays, rebuilt in milliseconds; up to :data:`KEPT_BYTES`); ``None`` where two cells
    have a point on one site."""
    key = (tuple(sys.st.offsets), tuple(sys.spatial), sys.m, tuple(sys.kinds))
    if key in _TABLES:
        return _TABLES[key]
    site_of = np.ascontiguousarray(np.stack(sys.site_of), dtype=np.int64)
    cell_at = np.full((site_of.shape[0], sys.nsite), -1, dtype=np.int64)
    tables = None
    if module.cell_maps(site_of, cell_at):  # else: two cells' points on one site
        interior = np.ascontiguousarray(sys.interior, dtype=np.bool_)
        rows = np.ascontiguousarray(np.nonzero(interior)[0], dtype=np.int64)
        delta, plain = fixed_offsets(sys, site_of, cell_at, module)
        tables = LatticeTables(site_of, cell_at, interior, rows, delta, plain)
    if tables is not None and sum(a.nbytes for a in vars(tables).values()) > KEPT_BYTES:
        return tables
    keep_last(_TABLES, key, tables, TABLES_KEPT)
    return tables


def fused_slices(model: Any, sys: _SliceSystem, flat: torch.Tensor) -> FusedSlices | None:
    """The compiled slice Newton for ``model`` on ``sys``, or ``None``: for a model whose compiled kernels
    hold it (scalar, block-diagonal slice Jacobian by its form) on a lattice where every stencil point of a
    cell sits on a distinct site per cell and the values are on the CPU in double precision."""
    if flat.dtype != torch.float64 or flat.device.type != "cpu" or sys.m != 1 or not flat.is_contiguous():
        return None
    compiled = compiled_closed_forms(model, flat[:0])
    if compiled is None or not compiled.block_diagonal:
        return None
    tables = lattice_tables(sys, compiled.module)
    return None if tables is None else FusedSlices(compiled, sys, tables)


def fixed_offsets(
    sys: _SliceSystem, site_of: np.ndarray, cell_at: np.ndarray, module: Any
) -> tuple[np.ndarray, np.ndarray]:
    """``(delta, plain)``: ``delta[a, p]``, the flat offset from the site of stencil point ``a`` of a cell to
    that of its point ``p`` (row-major over the spatial axes); ``plain[y]``, whether at site ``y`` every cell
    with a point on ``y`` exists and has each of its points at ``y + delta`` (no wrap, no boundary), so that
    the kernel reads the stencil there without the cell maps (``module.plain_sites`` finds them)."""
    offsets = np.array([o[1:] for o in sys.st.offsets], dtype=np.int64).reshape(len(sys.st.offsets), -1)
    strides = np.array([int(np.prod(sys.spatial[k + 1 :])) for k in range(len(sys.spatial))], dtype=np.int64)
    flat = offsets @ strides if strides.size else np.zeros(len(offsets), dtype=np.int64)
    delta = np.ascontiguousarray(flat[None, :] - flat[:, None])
    plain = np.empty(cell_at.shape[1], dtype=np.bool_)
    module.plain_sites(site_of, cell_at, delta, plain)
    return delta, plain
