"""Serving one field split into slabs or pencils over the processes of a :mod:`torch.distributed` group.

The lattice is split along its outer spatial axis (the first after time) into one slab a process
(:func:`plan_slabs`), or, where the shape asks, along its two outer spatial axes into one block a process
(pencils: :mod:`._grid`, whose :func:`plan_grid` chooses). Each process holds its slab (or block) and
``halo`` planes of each neighbour's (the stencil's reach along each split axis), reads only that part of
the initial field, and serves it by the affine recurrence, one slice at a time: the slab's new slice is
solved with the halo planes as known sites, then each process sends its edge planes to its neighbours (the
halo exchange, once a slice). The recurrence's check against the
model's own DEL is the one-process test made global: the largest residual and the largest value of each
slice are all-reduced. The kept slices are gathered to rank 0, which returns the field; the others return
None.

What is split: a DEL that is affine and explicit (the recurrence's matrix ``N`` on the new slice is
diagonal, as for the first-order stencil with the wave, Klein-Gordon and other quadratic ``L_d``: each new
value depends on its own equation only), and a nonlinear DEL by slice-Newton: the predictor of one process,
the unknown slice's halo exchanged before each evaluation of its cells (once a Newton iteration) and every
convergence test of :func:`._newton._newton_slice` all-reduced, so each process iterates as one process
would; its step site-wise where the slice Jacobian is block-diagonal (one stencil point at ``t + 1``, as
sine-Gordon's on the first-order stencil), else by GMRES over the processes (:mod:`._slabkrylov`: global dot
products, the Krylov vector's halo exchanged at each product). LU is not split (``solver = "lu"`` is refused
in one line naming ``solver = "krylov"``), nor is an affine recurrence whose new slice couples neighbouring
sites (refused in one line naming the alternative: one process), nor an ensemble (its members stacked are each
judged on their own, which these all-reduced tests are not: :func:`ensemble_refusal`; the command line serves it
whole). A failure, of every process (slice-Newton not converging) or of one alone (an exception, a singular
block of its part of the slice), stops them all with the same one-line error (:mod:`._flag`: an error flag
travels with every all-reduce, and one comes before each exchange); rank 0 keeps the slices served before it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING, Any, NoReturn

import numpy as np
import torch
import torch.distributed as dist
import xarray as xr

from .._action import CellDerivatives, check_model_lattice
from .._boundary import BoundaryKinds
from .._collective import group_device, world
from .._errors import InputError, ServeError
from .._lattice import LatticeField, as_lattice_field, gather_cells
from .._layout import lattice_dims
from .._models import AbstractLagrangian
from ._affine import _AffineSlices, _slice_residuals
from ._checkpoint import keep_factored
from ._edges import known_slices
from ._flag import Failure, Flag, SlabError
from ._grid import Block, Slab, assemble, exchange, grid_text, plan_grid, plan_slabs
from ._newton import _newton_slice, predict
from ._options import kept_slices
from ._slabkrylov import SlabSolver, lu_refusal
from ._slices import _site_label, _SliceSystem, site_text, slice_message

if TYPE_CHECKING:  # _slabstate reads and restores the slab run (no import at run time)
    from ._slabstate import SlabCheckpoint

__all__ = ["ROUNDOFF", "Block", "Slab", "plan_grid", "plan_slabs", "serve_slabs"]

#: Entries of the cell Hessian at most this fraction of its largest are taken as zero: a learned quadratic
#: ``L_d`` couples the new slice's neighbouring sites at round-off (1e-16 of the kinetic entries), which
#: would make the split recurrence's solve LU; dropped, the field moves at round-off, and every slice is still
#: checked against the model's own DEL.
ROUNDOFF = 1e-12


def _halo_width(model: AbstractLagrangian, axis: int = 1) -> int:
    """The stencil's reach along lattice axis ``axis`` (1: the outer spatial axis): a site's equation sees
    this many planes each side."""
    offsets = np.asarray(model.stencil.offsets)[:, axis]
    return int(offsets.max() - offsets.min())


def _local_field(init: xr.DataArray, block: Block, boundary: dict[str, str]) -> LatticeField:
    """The block's part of ``init`` (only it is read), its split axes Dirichlet (the halo planes are known)."""
    part, kinds = init.isel({axis: p.local for axis, p in zip(block.axes, block.parts)}), dict(boundary)
    for axis, p in zip(block.axes, block.parts):
        coord = np.asarray(init[axis].values, dtype=np.float64)
        step = float(coord[1] - coord[0])
        part = part.assign_coords({axis: coord[0] + step * np.arange(p.start, p.start + len(p.local))})
        part[axis].attrs = {k: v for k, v in init[axis].attrs.items() if k != "periodic"}
        kinds[axis] = "dirichlet"
    return as_lattice_field(part.compute(), source="init", boundary=kinds, min_slices=2)


def _recurrence(model: AbstractLagrangian, f: LatticeField, sys: _SliceSystem, flag: Flag) -> _AffineSlices | None:
    """The affine recurrence of the slab (None: the DEL is not affine, slice-Newton serves), refused in one line
    when its new slice's sites are coupled."""
    scale = flag.maxima(float(f.values[:2].abs().max()))[0] or 1.0
    probe = _AffineSlices.probe(model, sys.st, f.ncomp, scale)
    if probe is None:
        return None
    h = probe[0].copy()
    h[np.abs(h) <= ROUNDOFF * np.abs(h).max()] = 0.0  # a learned L_d's round-off couplings: none
    op = _AffineSlices(sys, h, probe[1])
    if op.nk.nnz or getattr(op.solve, "__name__", "") != "<lambda>":  # not the diagonal solve of _affine
        raise InputError.at(
            "--workers",
            "the DEL couples neighbouring sites of the new slice (the slice solve is LU, not site by site), "
            "which is not split across processes; serve it in one process (without --workers)",
        )
    return op


class _SlabNewton:
    """Site-wise slice-Newton on a slab: the window's rows ``0 .. 3`` hold slices ``i - 2 .. i + 1``; the halo
    planes of the unknown slice are exchanged before each gather of its cells, and every convergence test is
    all-reduced (so all processes iterate alike); a failure, of every process or of one, is told to all by
    ``flag``, with the global site of the largest residual."""

    def __init__(
        self,
        model: AbstractLagrangian,
        f: LatticeField,
        sys: _SliceSystem,
        window: np.ndarray,
        block: Block,
        flag: Flag,
        init: xr.DataArray,
        solver: str,
    ):
        self.model, self.f, self.sys, self.window, self.block = model, f, sys, window, block
        self.flag, self.init = flag, init
        self.psi = torch.from_numpy(window).view(4, *f.shape[1:], f.ncomp)
        self.flat = self.psi.view(4, sys.nsite, f.ncomp)
        self.unk = torch.from_numpy(np.nonzero(sys.interior)[0])
        self.vol = math.prod(model.spacing)
        steps = SlabSolver(sys, f, block, partial(exchange, block=block, rank=world()[0], size=world()[1]), flag.maxima)
        self.cache: dict[str, Any] = {"solver": solver, "factor": steps.factor}
        self.g_prev: torch.Tensor | None = None
        self.total_it, self.max_it = 0, 0

    def refactor(self, blocks: dict[tuple[int, int], torch.Tensor], target: float) -> None:
        """The factorisation of a checkpoint's Hessian blocks (a resumed run's chord steps), in every process."""
        solver = self.cache.get("solver", "auto")
        self.cache["solve"], _ = self.cache["factor"](self.sys, blocks, self.vol, solver, target)
        self.cache["factored"] = (blocks, target)

    def cells_at(self, k: int) -> torch.Tensor:
        """The cells anchored on window row ``k`` (the unknown slice's halo exchanged first)."""
        if k == 2:
            self.flag.maxima()  # the gate before the exchange
            exchange(self.window[3], self.block, *world())
        return gather_cells(self.psi[k : k + 2], self.model.stencil, self.f.boundary)

    def step(self, i: int, rtol: float, max_newton: int) -> float:
        """Solve slice ``i``'s equations for slice ``i + 1`` (row 3); its residual."""
        flat, unk = self.flat, self.unk
        predict(flat, unk, 2, flat[0] if i >= 2 else None)  # the predictor of one process (``solve_and_tally``)
        if self.g_prev is None:
            self.g_prev = CellDerivatives(self.model, self.cells_at(1)).grad
        g_prev = self.g_prev
        it, res, self.g_prev, err = _newton_slice(
            self.model, self.sys, self.psi, flat, unk, 2, g_prev, self.vol, rtol, max_newton, self.cells_at,
            self.cache, self.flag.maxima,
        )  # fmt: skip
        self.total_it, self.max_it = self.total_it + it, max(self.max_it, it)
        if err is not None:
            self.fail(i, err, self.sys.residual(g_prev, self.g_prev, self.vol))
        return float(res)

    def fail(self, i: int, err: tuple[str, int | None, float], r: np.ndarray) -> NoReturn:
        """Tell every process that slice ``i``'s equations failed (``err``: the message, this process's row of
        its worst residual ``r``, the residual); the one-process message, its site in the whole lattice."""
        msg, row, res = err
        site = None
        if row is not None:
            local = _site_label(self.f, self.sys, i, row)
            split = len(self.block.parts)
            at = [(local[1 + k] + p.start) % p.n for k, p in enumerate(self.block.parts)]
            site = (i, *at, *local[1 + split :])
        where = site_text(lattice_dims(self.init), site, self.init.coords) if site else None
        text = slice_message(self.f, i, msg, where, res)  # as one process says it, the site in the whole lattice
        weight = float(np.abs(r).max()) if r.size else 0.0
        self.flag.fail(Failure(text, weight, slice=i + 1, site=site, residual=res))


def serve_slabs(
    model: AbstractLagrangian,
    init: xr.DataArray,
    slices: int,
    *,
    boundary: BoundaryKinds | None = None,
    every: int = 1,
    rtol: float = 1e-10,
    max_newton: int = 30,
    on_slab: Callable[[int, Block, np.ndarray], None] | None = None,
    report: dict[str, Any] | None = None,
    solver: str = "auto",
    on_slice: Callable[[int, np.ndarray], None] | None = None,
    checkpoint: SlabCheckpoint | None = None,
    grid: tuple[int, int] | None = None,
) -> xr.DataArray | None:
    """Serve ``init`` (every slice held for Dirichlet strips; a periodic field needs two) over the processes of
    the group, one block each (:mod:`._grid`: slabs, or pencils where the shape asks; ``grid`` ``(p1, p2)``
    imposes one); rank 0 gets the kept slices ``0, every, ...`` and the last, the others None.

    ``on_slab(i, block, values)``, in every process, sees each slice ``i`` served (the first two included)
    on the process's own block (``(planes, ..., components)``): the task's meters measure the block there.
    ``report``, when given, receives ``max_residual`` (the largest DEL residual of the recurrence's check),
    ``processes``, ``grid`` (its text, ``slabs 2 over x``), ``axis`` and ``slabs`` (the planes ``[lo, hi)``
    of each process along ``axis``) for slabs, ``axes`` and ``blocks`` (each process's ``[lo, hi]`` along
    each) for pencils, ``block`` (this process's), the solvers, and ``gather_seconds`` (the wall time of
    the kept slices' gather to rank 0).
    ``solver`` is slice-Newton's linear solver (``"auto"``, ``"sitewise"`` or ``"krylov"``; ``"lu"`` is
    refused). ``on_slice(i, values)``, when given, sees on rank 0 every slice ``i`` whole (``(planes, ...,
    components)``, gathered slice by slice: the measurements a process makes on whole slices).
    ``checkpoint`` (a :class:`._slabstate.SlabCheckpoint`, in every process) puts back the state it holds and
    writes the checkpoints; the slices served before a resumed run's checkpoint are not seen again.

    A failure in any process (slice-Newton not converging, or an exception of one process alone) stops every
    process with the same :class:`SlabError` (:mod:`._flag`), whose ``result`` on rank 0 is the field served
    before it: the kept slices up to the last slice every process completed, and that slice."""
    flag = Flag()
    run: _SlabRun | None = None
    try:
        try:
            if solver == "lu":
                raise lu_refusal()
            if model.n_members > 1:
                raise ensemble_refusal()
            run = _SlabRun(model, init, slices, boundary, every, flag, solver, grid)
            if checkpoint is not None:
                run.checkpointed(checkpoint)
            run.serve(rtol, max_newton, on_slab, on_slice)
            flag.maxima()  # the gate before the gather: a process that failed after the last test says so
        except SlabError:
            raise
        except Exception as exc:
            flag.fail(Failure.of(exc, _failure_text(exc, run), None if run is None else run.done + 1))
    except SlabError as err:
        if run is not None:
            err.result = _partial(run)
            run.tell(report)
        raise
    run.tell(report)
    start = time.perf_counter()
    field = _gathered(run)
    if report is not None:
        report["gather_seconds"] = time.perf_counter() - start
    return field


def ensemble_refusal() -> InputError:
    """The one-line refusal of an ensemble (or its members stacked) under several processes: its slice tests are
    each member's own (``._members``), which the all-reduced tests of a split slice are not."""
    return InputError.at(
        "model",
        "an ensemble is served whole, in one process (each member's slice solve judged on its own); serve it "
        "without --workers",
    )


def _failure_text(exc: Exception, run: _SlabRun | None) -> str:
    """One line for an exception of this process alone: the slice it was serving, the process, the error."""
    first = (str(exc).strip().splitlines() or [""])[0]
    where = "setting up" if run is None else f"slice {run.done + 1}"
    return f"{where}: process {world()[0]} of {world()[1]} failed: {type(exc).__name__}: {first}".rstrip(": ")


class _SlabRun:
    """One process's part of a split serve: its slab of the field, the window of slices ``i - 2 .. i + 1``,
    the kept slices, and the last slice it completed (``done``, in window row 2 between slices)."""

    def __init__(
        self,
        model: AbstractLagrangian,
        init: xr.DataArray,
        slices: int,
        boundary: BoundaryKinds | None,
        every: int,
        flag: Flag,
        solver: str = "auto",
        grid: tuple[int, int] | None = None,
    ):
        rank, size = world()
        dims = lattice_dims(init)
        kinds = _kinds(model, init, dims, boundary)
        self.axis, axes = dims[1], dims[1:3]
        sizes, halos = tuple(init.sizes[a] for a in axes), tuple(_halo_width(model, k + 1) for k in range(len(axes)))
        self.blocks = plan_grid(sizes, size, halos, tuple(kinds[a] == "periodic" for a in axes), axes, grid)
        self.block = block = self.blocks[rank]
        self.data = any(k != "periodic" for k in kinds.values())  # Dirichlet strips: every slice of the slab is read
        nt = min(init.sizes[dims[0]], slices) if self.data else 2
        self.f = f = _local_field(init.isel({dims[0]: slice(0, nt)}), block, kinds)
        self.model, self.init, self.slices, self.flag = model, init, slices, flag
        self.sys = sys = _SliceSystem(model, f)
        self.op = _recurrence(model, f, sys, flag)
        self.window = np.full((4, sys.nsite * f.ncomp), np.nan)  # slices i - 2 .. i + 1
        self.window[1:3] = f.values[:2].reshape(2, -1).numpy()
        self.newton = _SlabNewton(model, f, sys, self.window, block, flag, init, solver) if self.op is None else None
        self.kept_at = kept_slices(slices, every)
        self.known = None if sys.interior.all() else np.repeat(~sys.interior, f.ncomp)
        self.shape = (*f.shape[1:], f.ncomp)
        self.kept = [self.own(k + 1).copy() for k in range(2) if k in self.kept_at]  # the block's own sites
        self.done, self.worst = 1, 0.0
        self.on_done: Callable[[_SlabRun], None] | None = None

    def checkpointed(self, checkpoint: SlabCheckpoint) -> None:
        """Write checkpoints by ``checkpoint`` (after each slice) and go on from the state it holds."""
        if self.newton is not None:
            keep_factored(self.newton.cache)
        checkpoint.start(self)
        self.on_done = checkpoint

    def own(self, row: int) -> np.ndarray:
        """Window row ``row`` on the block's own sites, ``(planes, ..., components)``."""
        return self.window[row].reshape(self.shape)[self.block.own]

    def serve(
        self,
        rtol: float,
        max_newton: int,
        on_slab: Callable[[int, Block, np.ndarray], None] | None,
        on_slice: Callable[[int, np.ndarray], None] | None = None,
    ) -> None:
        """Serve every slice (``on_slab`` sees each on the slab's planes, ``on_slice`` on rank 0 whole)."""
        window = self.window
        for k in range(2 if self.done == 1 else 0):  # a resumed run: served from its checkpoint's slice on
            if on_slab is not None:
                on_slab(k, self.block, self.own(k + 1))
            self.whole(k, k + 1, on_slice)
        for i in range(self.done, self.slices - 1):
            self.step(i, rtol, max_newton)
            if on_slab is not None:
                on_slab(i + 1, self.block, self.own(3))
            self.whole(i + 1, 3, on_slice)
            if i + 1 in self.kept_at:
                self.kept.append(self.own(3).copy())
            window[:3] = window[1:]
            self.done = i + 1
            if self.on_done is not None:
                self.on_done(self)

    def whole(self, k: int, row: int, on_slice: Callable[[int, np.ndarray], None] | None) -> None:
        """Slice ``k`` (window row ``row``) gathered whole to rank 0's ``on_slice`` (after a gate)."""
        if on_slice is None:
            return
        self.flag.maxima()
        parts: list[Any] = [self.own(row)]
        if world()[1] > 1:
            parts = [None] * world()[1]
            dist.gather_object(self.own(row), parts if world()[0] == 0 else None, dst=0)
        if world()[0] == 0:
            on_slice(k, assemble(parts, self.block.grid, 0))

    def step(self, i: int, rtol: float, max_newton: int) -> None:
        """Solve slice ``i``'s equations for slice ``i + 1`` (window row 3), its halo planes exchanged."""
        f, window = self.f, self.window
        if self.known is not None:  # the Dirichlet strips (the halo planes: placeholders until the exchange)
            nxt = known_slices(f, lambda a, b: f.values[a:b], f.shape[0], None, i + 1, i + 2) if self.data else None
            window[3, self.known] = 0.0 if nxt is None else np.asarray(nxt).reshape(-1)[self.known]
        if self.newton is not None:
            self.worst = max(self.worst, self.newton.step(i, rtol, max_newton))
            return
        assert self.op is not None
        self.op.run(window[1:], 1, 2)
        self.flag.maxima()  # the gate before the exchange
        exchange(window[3], self.block, *world())
        vol = math.prod(self.model.spacing)
        self.worst = max(self.worst, _check(self.model, f, window[1:], vol, self.op.dmax, rtol, i, self.flag))

    def tell(self, report: dict[str, Any] | None) -> None:
        """Fill ``report`` (when given) with the decomposition and the solver's figures."""
        if report is None:
            return
        report.update(max_residual=self.worst, processes=world()[1], grid=grid_text(self.blocks), block=self.block)
        if len(self.block.parts) == 1:
            report.update(axis=self.axis, slabs=[[b.parts[0].lo, b.parts[0].hi] for b in self.blocks])
        else:
            report.update(axes=list(self.block.axes), blocks=[b.bounds() for b in self.blocks])
        newton = self.newton
        its = (self.done - 1, 1) if newton is None else (newton.total_it, newton.max_it)
        report.update(solver="affine" if newton is None else "newton", newton_iterations=its[0], max_newton=its[1])
        report.update(slice_solver=None if newton is None else "+".join(newton.cache.get("used", [])) or None)


def _kinds(
    model: AbstractLagrangian, init: xr.DataArray, dims: tuple[str, ...], boundary: BoundaryKinds | None
) -> dict[str, str]:
    """The boundary kind of every spatial axis (``boundary``, else the coordinates' ``periodic`` attribute),
    read from the first two slices, on which ``model`` is checked (an analytic model bound to the lattice)."""
    f = as_lattice_field(init.isel({dims[0]: slice(0, 2)}).compute(), source="init", boundary=boundary, min_slices=2)
    if model.rebinds_to_any_lattice:
        model.bind(f.ndim, f.ncomp, f.spacing, f.components)
    check_model_lattice(model, f, "init")
    return {d: ("periodic" if p else "dirichlet") for d, p in zip(dims[1:], f.periodic[1:])}


def _check(
    model: AbstractLagrangian,
    f: LatticeField,
    window: np.ndarray,
    vol: float,
    dmax: float,
    rtol: float,
    i: int,
    flag: Flag,
) -> float:
    """The one-process test of the recurrence against the model's DEL, on slice ``i``'s equations, global;
    the slice's largest residual."""
    psi = torch.from_numpy(window.reshape(3, *f.shape[1:], f.ncomp))
    res, scl = flag.maxima(float(_slice_residuals(model, f, psi, 1, 2)[0]), float(np.abs(window).max()))
    if not (math.isfinite(res) and res <= rtol * vol * dmax * max(scl, 1e-300)):
        raise ServeError(
            f"slice {i + 1}: the affine recurrence fails the DEL test (residual {res:.3e}); split serving has no "
            "slice-Newton to take over: serve in one process",
            slice=i + 1,
            residual=res,
        )
    return res


def _gathered(run: _SlabRun) -> xr.DataArray | None:
    """The kept slices of every block, gathered to rank 0 as one field: each process sends its block of one
    kept slice at a time (a tensor, point to point), which rank 0 copies into place, so that rank 0 holds the
    kept field once and a block of one slice beside it, and the others their own blocks of the kept slices."""
    rank, size = world()
    if rank != 0:
        for values in run.kept:
            dist.send(torch.from_numpy(np.ascontiguousarray(values)).to(group_device()), dst=0)
        return None
    dims = lattice_dims(run.init)
    out = np.empty((len(run.kept), *(run.init.sizes[d] for d in dims[1:]), run.f.ncomp))
    for r, block in enumerate(run.blocks):
        where = tuple(slice(p.lo, p.hi) for p in block.parts)
        for j in range(len(run.kept)):
            place = out[j]
            if r == 0:
                place[where] = run.kept[j]
                continue
            buf = torch.empty(place[where].shape, dtype=torch.float64, device=group_device())
            dist.recv(buf, src=r)
            place[where] = buf.cpu().numpy()
    run.kept.clear()
    return _as_field(run.init, run.f, out, run.kept_at)


def _as_field(init: xr.DataArray, f: LatticeField, values: np.ndarray, idx: np.ndarray) -> xr.DataArray:
    """The slices ``idx`` of the whole lattice (``values``: ``(len(idx), planes, ...)``) as a field like ``init``
    (its coordinates along time taken at ``idx``'s length from its first slice: no copy of the field's
    values is made)."""
    values = values.reshape(len(idx), *(init.sizes[d] for d in lattice_dims(init)[1:]), f.ncomp)
    tdim = lattice_dims(init)[0]
    t = np.asarray(init[tdim].values[:2], dtype=np.float64)
    first = init.isel({tdim: [0]})
    coords = {k: c.isel({tdim: [0] * len(idx)}) if tdim in c.dims else c for k, c in first.coords.items()}
    data = values if f.components is not None else values[..., 0]
    out = xr.DataArray(data, dims=init.dims, coords=coords, name=init.name, attrs=dict(init.attrs))
    out.encoding = dict(init.encoding)
    return out.assign_coords({tdim: t[0] + (t[1] - t[0]) * idx.astype(np.float64), "slice": (tdim, idx)})


def _partial(run: _SlabRun) -> xr.DataArray | None:
    """Rank 0's field of a stopped split serve: the kept slices up to the last slice every process completed,
    and that slice (the processes that failed later hold it in window row 1); the others get None."""
    kept = np.stack(run.kept) if run.kept else None
    last = np.stack([run.own(1), run.own(2)])
    mine = (run.done, run.kept_at[: len(run.kept)].tolist(), kept, last)
    parts: list[Any] = [mine]
    if world()[1] > 1:
        parts = [None] * world()[1]
        dist.gather_object(mine, parts if world()[0] == 0 else None, dst=0)
    if world()[0] != 0:
        return None
    done = min(p[0] for p in parts)
    idx = [int(k) for k in run.kept_at if k <= done]
    idx += [done] if idx[-1] != done else []

    def planes(part: tuple[int, list[int], np.ndarray | None, np.ndarray], k: int) -> np.ndarray:
        at, held, kept, last = part
        return kept[held.index(k)] if k in held else last[1 - (at - k)]  # type: ignore[index]

    values = np.stack([assemble([planes(p, k) for p in parts], run.block.grid, 0) for k in idx])
    return _as_field(run.init, run.f, values, np.asarray(idx))
