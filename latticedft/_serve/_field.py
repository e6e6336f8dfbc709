"""n-D serving (n >= 2): a field filled slice by slice, by the affine recurrence where the DEL is affine, then by
slice-Newton or the site-by-site sweep."""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import torch

from .._boundary import axis_kinds, missing_edges
from .._errors import InputError, ServeError
from .._lattice import LatticeField, gather_cells, to_dataarrays
from .._models import AbstractLagrangian
from ._affine import _affine_prefix
from ._edges import known_slices
from ._fused import KEPT_BYTES
from ._options import ServeOptions
from ._range import assess
from ._result import ServeResult, _bar
from ._slices import _SliceSystem
from ._stepper import served_where, slice_error, solver_name, step_slices


def _initial_values(
    f: LatticeField, sys: _SliceSystem, steps: int, boundary_value: Any = None, nan: bool = True
) -> torch.Tensor:
    """``(steps, *spatial, m)`` values: the first two slices and the boundary (known) sites, NaN elsewhere
    (``nan=False``: left as allocated, for a run whose every solve writes its slice's unknown sites before it
    reads them: Newton's, which starts from its predictor); the boundary sites of slices beyond ``f``'s from
    ``boundary_value`` when given."""
    nt_given = f.shape[0]
    m = f.ncomp
    missing = missing_edges(f.boundary, f.dims, nt_given, steps)
    if missing and boundary_value is None:
        axis, kind = missing
        raise InputError(
            f"init: holds {nt_given} time slices but the {kind.title} boundary along "
            f"{axis!r} needs its strips on all {steps} slices; give the whole field, "
            "fewer slices, a boundary_value, or a periodic boundary"
        )
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


class _FieldRun:
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
        self.model, self.f, self.steps, self.mode = model, f, steps, mode
        self.where = where or torch.device("cpu")  # where the slice solves run (:func:`on_device`)
        self.sys = slice_system(model, f)
        self.psi = _initial_values(f, self.sys, steps, boundary_value, nan=mode != "newton")
        self.flat = self.psi.reshape(steps, self.sys.nsite, f.ncomp)  # (steps, site, m): a view of psi
        self.unk = torch.from_numpy(np.nonzero(self.sys.interior)[0])
        self.vol = math.prod(model.spacing)
        self.t0 = time.perf_counter()
        self.total_it, self.max_it, self.worst = 0, 0, 0.0
        self.bar = _bar(steps - 2, f"serve ({mode})", progress)
        self.cache: dict[str, Any] = {"solver": solver}
        self.start = 1  # first slice whose equations Newton (or the sweep) solves
        self.base = 0  # the slice held at position 0 (the whole field: the first)
        self.affine_slices = 0

    def cells_at(self, i: int) -> torch.Tensor:
        """The cells anchored on slice ``i``."""
        return gather_cells(self.psi[i : i + 2], self.model.stencil, self.f.boundary)

    def serve_affine(self, rtol: float) -> None:
        """Fill the leading slices that the affine recurrence serves to within ``rtol``; Newton starts after."""
        out = _affine_prefix(self.model, self.f, self.sys, self.psi, self.flat, rtol, self.vol)
        if out is None:
            return
        self.affine_slices, worst, dmax, mscale = out
        self.start = 1 + self.affine_slices
        if self.affine_slices:
            self.worst = worst
            self.total_it, self.max_it = self.affine_slices, 1
            self.cache["dmax"] = dmax
            self.cache["mscale"] = mscale
        self.bar.update(self.affine_slices)

    def solver(self) -> str:
        """The ``solver`` name of the result."""
        return solver_name(self.mode, self.affine_slices, self.steps)

    @property
    def values(self) -> torch.Tensor:
        """The whole field's slices, ``(steps, *spatial, m)``."""
        return self.psi

    def older(self, i: int) -> torch.Tensor | None:
        """Slice ``i - 2`` of slice ``i`` (Newton's predictor)."""
        return self.flat[i - 2] if i >= 2 else None

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
            newton_iterations=self.total_it,
            max_newton_iterations=self.max_it,
            wall_time=wall,
            sites_per_second=rate,
            max_residual=residual,
            mode=self.mode,
            solver=self.solver(),
            slice_solver="+".join(self.cache.get("used", [])) or None,
            extrapolation=ext,
            warnings=warnings,
        )

    def fail(self, i: int, msg: str, row: int | None, res: float) -> ServeError:
        """The error for slice ``i``'s equations failing (at equation ``row``), holding the slices solved."""
        f, sys = self.f, self.sys
        self.bar.close()
        part = LatticeField.with_values(f, self.psi[: i + 1].clone())
        wall = time.perf_counter() - self.t0
        solved = (i + 1 - 2) * sys.n
        result = self._result(part, False, msg, i + 1, wall, solved / wall if wall > 0 else 0.0, res)
        return slice_error(f, sys, i, msg, row, res, result)

    def finish(self) -> ServeResult:
        """The complete served field."""
        self.bar.close()
        wall = time.perf_counter() - self.t0
        out = LatticeField.with_values(self.f, self.psi)
        solved = (self.steps - 2) * self.sys.n
        return self._result(
            out, True, "complete", self.steps, wall, solved / wall if wall > 0 else math.inf, self.worst
        )


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
