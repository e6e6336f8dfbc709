"""n-D serving (n >= 2): a field filled slice by slice, by the affine recurrence where the DEL is affine, then by
slice-Newton or the site-by-site sweep."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from .._boundary import axis_kinds
from .._lattice import LatticeField, to_dataarrays
from .._models import AbstractLagrangian
from ._affine import _affine_prefix
from ._edges import known_slices, require_edges
from ._fused import KEPT_BYTES
from ._members import member_figures
from ._options import ServeOptions
from ._range import assess
from ._result import ServeResult
from ._slices import _SliceSystem
from ._stepper import SteppedRun, served_where, step_slices


def _initial_values(
    f: LatticeField, sys: _SliceSystem, steps: int, boundary_value: Any = None, nan: bool = True
) -> torch.Tensor:
    """``(steps, *spatial, m)`` values: the first two slices and the boundary (known) sites, NaN elsewhere
    (``nan=False``: left as allocated, for a run whose every solve writes its slice's unknown sites before it
    reads them: Newton's, which starts from its predictor); the boundary sites of slices beyond ``f``'s from
    ``boundary_value`` when given."""
    nt_given = f.shape[0]
    m = f.ncomp
    require_edges(f, nt_given, steps, boundary_value)
    psi = torch.empty((steps, *f.shape[1:], m), dtype=torch.float64)
    if nan:
        psi[2:] = math.nan
    psi[:2] = f.values[:2]
    known = np.ones(sys.nsite, dtype=bool)
    known[sys.interior] = False
    flat = psi.reshape(steps, sys.nsite, m)
    if known.any():
        kidx = torch.from_numpy(np.nonzero(known)[0])
        known_values = known_slices(f, lambda a, b: f.values[a:b], nt_given, boundary_value, 0, steps)
        flat[:, kidx] = known_values.reshape(-1, sys.nsite, m)[:, kidx]
    return psi


#: The slice system of the lattice served last, by stencil offsets, spatial shape, components and boundary
#: kinds (which fix it): the next field on that lattice reuses its index maps.
_SYSTEMS: dict[tuple[Any, ...], _SliceSystem] = {}


def slice_system(model: AbstractLagrangian, f: LatticeField) -> _SliceSystem:
    """The :class:`_SliceSystem` of ``model``'s stencil on ``f``'s lattice: the last one built where the
    lattice is the same, else a new one (kept in its place where its index maps hold at most
    :data:`._fused.KEPT_BYTES`)."""
    key = (tuple(model.stencil.offsets), tuple(f.shape[1:]), f.ncomp, axis_kinds(f.boundary))
    sys = _SYSTEMS.get(key)
    if sys is None:
        sys = _SliceSystem(model, f)
        _SYSTEMS.clear()
        if sum(a.nbytes for a in sys.site_of) + sys.index.nbytes <= KEPT_BYTES:
            _SYSTEMS[key] = sys
    return sys


class _FieldRun(SteppedRun):
    """One n-D field being served: its slice system, values, iteration counters and progress bar."""

    def __init__(
        self,
        model: AbstractLagrangian,
        f: LatticeField,
        steps: int,
        mode: str,
        progress: bool | None,
        solver: str,
        boundary_value: Any = None,
        where: torch.device | None = None,
    ):
        self.sys = slice_system(model, f)
        self.psi = _initial_values(f, self.sys, steps, boundary_value, nan=mode != "newton")
        self.flat = self.psi.reshape(steps, self.sys.nsite, f.ncomp)  # (steps, site, m): a view of psi
        self.unk = torch.from_numpy(np.nonzero(self.sys.interior)[0])
        # where the slice solves run: ``_stepper.on_device``
        super().__init__(model, f, steps, mode, solver, where or torch.device("cpu"), progress)
        self.start = 1  # first slice whose equations Newton (or the sweep) solves

    @property
    def values(self) -> torch.Tensor:
        """The whole field's slices, ``(steps, *spatial, m)``."""
        return self.psi

    def serve_affine(self, rtol: float) -> None:
        """Fill the leading slices that the affine recurrence serves to within ``rtol``; Newton starts after."""
        out = _affine_prefix(self.model, self.f, self.sys, self.psi, self.flat, rtol, self.vol)
        if out is None:
            return
        counts, worst, dmax, mscale = out
        if isinstance(counts, np.ndarray):  # a stacked ensemble's: each member keeps its own slices and scales
            self.cache["member_affine"] = counts  # Newton serves a member from its own first failing slice on
            own = counts > 0  # a member whose recurrence served no slice takes its scales from Newton, as alone
            self.cache["member_dmax"] = np.where(own, dmax, math.nan)
            self.cache["member_mscale"] = np.where(own, mscale, 0.0)
            member_figures(self.cache, counts.size).affine(counts, np.asarray(worst))  # each member's, as alone
            kept, self.affine_slices = int(counts.min()), int(counts[0])  # member 0's: the result's solver
            dmax, mscale = (float(np.max(np.asarray(x)[own])) if own.any() else 0.0 for x in (dmax, mscale))
            worst = float(np.max(worst))
        else:
            kept = self.affine_slices = int(counts)
        self.start = 1 + kept
        if np.any(counts):
            self.worst = float(worst)
            self.count_affine()
            self.cache["dmax"] = dmax
            self.cache["mscale"] = mscale
        self.bar.update(kept)

    def _result(
        self, field: LatticeField, complete: bool, reason: str, slices: int, wall: float, rate: float, residual: float
    ) -> ServeResult:
        folded = self.cache.get("folded")
        ext, warnings = assess(self.model, field, folded.excess if folded is not None else None)
        return ServeResult(
            field=to_dataarrays([field])[0],  # its coordinates built once per lattice
            complete=complete,
            reason=reason,
            slices=slices,
            wall_time=wall,
            sites_per_second=rate,
            max_residual=residual,
            extrapolation=ext,
            warnings=warnings,
            **self.counts(),
        )

    def partial(self, i: int, msg: str, res: float) -> ServeResult:
        """The result of a run stopped by slice ``i``'s equations: the slices solved."""
        part = LatticeField.with_values(self.f, self.psi[: i + 1].clone())
        return self._result(part, False, msg, i + 1, *self.timed(i + 1), res)

    def finish(self) -> ServeResult:
        """The complete served field."""
        self.bar.close()
        out = LatticeField.with_values(self.f, self.psi)
        return self._result(out, True, "complete", self.steps, *self.timed(self.steps), self.residual())


def _serve_field(model: AbstractLagrangian, f: LatticeField, steps: int, options: ServeOptions) -> ServeResult:
    """Serve one n-D field: the affine recurrence first where allowed, then Newton (or the sweep) slice by slice;
    ``options.solver`` solves Newton's steps (``_solvers.SOLVERS``)."""
    mode, rtol, max_newton = options.mode, options.rtol, options.max_newton
    where = served_where(options.device)
    run = _FieldRun(model, f, steps, mode, options.progress, options.solver, options.boundary_value, where)
    if mode == "newton" and options.affine and steps > 2:
        run.serve_affine(rtol)
    # the first Newton slice evaluates the gradients of its older cells (the compiled kernel needs none)
    step_slices(run, run.start, steps - 1, None, rtol, max_newton)
    return run.finish()
