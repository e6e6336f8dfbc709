"""The slice stepper: one slice (or a run of slices) of an n-D field solved from the two before it, shared by
the whole-field run (``_field``) and the rolling window (``_stream``)."""

from __future__ import annotations

import functools
import math
import time
from typing import Any, Protocol

import numpy as np
import torch

from .._action import CellDerivatives
from .._device import resolve_device
from .._errors import ServeError
from .._lattice import LatticeField, gather_cells
from .._models import AbstractLagrangian
from . import _ondevice
from ._folded import FoldedSlices, folded_slices
from ._fused import FusedSlices, fused_slices
from ._members import MemberFigures, affine_held, counted_figures, newton_members
from ._newton import _newton_slice, predict
from ._potential import potential_slices
from ._result import ServeResult, _bar
from ._slices import _site_label, _SliceSystem, is_singular, site_text, slice_message
from ._solvers import OFFDIAG_RTOL
from ._stackfold import StackedFolded, stacked_folded
from ._sweep import _sweep_slice


class Progress(Protocol):
    """A run's progress bar, as the stepper moves it: one step a slice solved."""

    def update(self, n: int = 1) -> object: ...
    def close(self) -> object: ...


class SliceRun(Protocol):
    """What a run must provide for the stepper to solve its slices: the model and lattice, the slices it holds
    (``values``: ``(slices, *spatial, m)``, and ``flat``, its view ``(slices, sites, m)``), where they lie in
    the field (position ``0`` holds slice ``base``: ``0`` for the whole field, the window's first slice for a
    rolling window) and the older slice of each position (:meth:`older`), where the solves run, the Newton
    cache, and the counters and progress bar it tallies on.

    ``_field._FieldRun`` (the whole field) and ``_stream._Stream`` (a rolling window) are the two, both
    :class:`SteppedRun`; mypy checks them against it where they are passed to the stepper's functions."""

    @property
    def model(self) -> AbstractLagrangian: ...
    @property
    def f(self) -> LatticeField: ...
    @property
    def sys(self) -> _SliceSystem: ...
    @property
    def mode(self) -> str: ...
    @property
    def values(self) -> torch.Tensor: ...
    @property
    def flat(self) -> torch.Tensor: ...
    @property
    def unk(self) -> torch.Tensor: ...
    @property
    def vol(self) -> float: ...
    @property
    def where(self) -> torch.device: ...
    @property
    def base(self) -> int: ...
    @property
    def cache(self) -> dict[str, Any]: ...
    @property
    def bar(self) -> Progress: ...

    total_it: int
    max_it: int
    worst: float

    def cells_at(self, i: int) -> torch.Tensor:
        """The cells anchored on position ``i``."""
        ...

    def older(self, i: int) -> torch.Tensor | None:
        """Slice ``i - 2`` of position ``i`` (Newton's predictor), ``None`` for the field's first two slices."""
        ...

    def fail(self, i: int, msg: str, row: int | None, res: float) -> ServeError:
        """The error for position ``i``'s equations failing (at equation ``row``), with the partial result."""
        ...


class Stepping:
    """What every stepped run has, the whole field, the rolling window and the 1D batch alike: its mode and
    slices, the clock, the progress bar (``steps - 2`` slices, ``label`` after the mode), the slices the
    affine recurrence served, the solver name and the figures of its results. The clock starts here."""

    def __init__(self, mode: str, steps: int, progress: bool | None, label: str = ""):
        self.mode, self.steps = mode, steps
        self.affine_slices = 0  # slices the affine recurrence served (after the two given ones)
        self.t0 = time.perf_counter()
        self.bar = _bar(steps - 2, f"serve ({mode}{label})", progress)

    def solver(self) -> str:
        """The ``solver`` name of the result."""
        return solver_name(self.mode, self.affine_slices, self.steps)

    def rate(self, solved: int, whole: bool = True) -> tuple[float, float]:
        """The wall time since the clock started and the sites a second it makes over ``solved`` sites (no
        time: ``inf`` for a ``whole`` run, ``0`` for one stopped early)."""
        wall = time.perf_counter() - self.t0
        return wall, solved / wall if wall > 0 else (math.inf if whole else 0.0)

    def figures(self, total_it: int, max_it: int, slice_solver: str | None = None) -> dict[str, Any]:
        """The figures of a result that the stepping counted: evaluations, mode and solvers."""
        return {
            "newton_iterations": total_it,
            "max_newton_iterations": max_it,
            "mode": self.mode,
            "solver": self.solver(),
            "slice_solver": slice_solver,
        }


class SteppedRun(Stepping):
    """What the whole-field run and the rolling window share around the stepper: the model, lattice and mode,
    where the solves run, the Newton cache, the counters, the clock and the progress bar (:class:`Stepping`),
    the older slice of each position (from the slices held, or ``before`` the window's first), and the figures
    of the result that every run reports. A subclass holds the slices (``values``, ``flat``, ``unk``), ``sys``
    and ``cells_at`` and ``fail``, and calls ``__init__`` once they are set up (the clock starts there)."""

    sys: _SliceSystem
    flat: torch.Tensor

    def __init__(
        self,
        model: AbstractLagrangian,
        f: LatticeField,
        steps: int,
        mode: str,
        solver: str,
        where: torch.device,
        progress: bool | None,
        label: str = "",
    ):
        self.model, self.f, self.where = model, f, where
        self.vol = math.prod(model.spacing)
        self.total_it, self.max_it, self.worst = 0, 0, 0.0
        self.cache: dict[str, Any] = {"solver": solver}
        self.base = 0  # the slice held at position 0 (the whole field: the first)
        self.before: torch.Tensor | None = None  # the slice before position 0 (a window's; Newton's predictor)
        super().__init__(mode, steps, progress, label)

    def older(self, i: int) -> torch.Tensor | None:
        """Slice ``i - 2`` of position ``i`` (Newton's predictor): held, or the one before position 0."""
        if self.base + i < 2:
            return None
        return self.flat[i - 2] if i >= 2 else self.before

    @property
    def values(self) -> torch.Tensor:
        """The slices held, ``(slices, *spatial, m)`` (a subclass's)."""
        raise NotImplementedError

    def cells_at(self, i: int) -> torch.Tensor:
        """The cells anchored on position ``i``."""
        return gather_cells(self.values[i : i + 2], self.model.stencil, self.f.boundary)

    def partial(self, p: int, msg: str, res: float) -> ServeResult:
        """The result of a run stopped by position ``p``'s equations (``msg``, residual ``res``): the slices
        served up to there (a subclass's)."""
        raise NotImplementedError

    def fail(self, p: int, msg: str, row: int | None, res: float) -> ServeError:
        """The error for position ``p``'s equations failing (at equation ``row``): the bar closed, the run's
        :meth:`partial` result and the one line of :func:`slice_error`."""
        self.bar.close()
        return slice_error(self.f, self.sys, self.base + p, msg, row, res, self.partial(p, msg, res))

    def count_affine(self) -> None:
        """The slices of the affine recurrence counted as one evaluation each."""
        self.total_it, self.max_it = self.affine_slices, 1

    def timed(self, slices: int) -> tuple[float, float]:
        """The wall time since the clock started and the sites a second it makes over the first ``slices``
        slices (the two given ones not counted; no time: ``0`` for a run stopped early, ``inf`` for a whole
        one)."""
        return self.rate((slices - 2) * self.sys.n, slices == self.steps)

    def counts(self) -> dict[str, Any]:
        """The figures of the result that the stepper counted: evaluations, mode and solvers. A stacked
        ensemble's are member 0's own, as it counts them served alone (``_members.MemberFigures``): the
        result's field is member 0's."""
        own = self._members_counted()
        if own is not None:
            return self.figures(int(own.total[0]), int(own.most[0]), "+".join(own.used[0]) or None)
        return self.figures(self.total_it, self.max_it, "+".join(self.cache.get("used", [])) or None)

    def residual(self) -> float:
        """The largest residual converged to (``max_residual``): a stacked ensemble's member 0's own, as
        :meth:`counts`."""
        own = self._members_counted()
        return float(own.worst[0]) if own is not None else self.worst

    def _members_counted(self) -> MemberFigures | None:
        """A stacked ensemble's figures counted per member (``None`` for a single model, or where none were)."""
        return counted_figures(self.cache) if self.sys.members > 1 else None


class MemberBatch(Protocol):
    """What a batch of 1D trajectories gives the stepper (``_batch._Batch``, ``_fast1d.FastBatch``, both
    :class:`Stepping`): its members' fields, its longest member's slices, its mode and progress bar, and the
    step of one group of members."""

    @property
    def fs(self) -> list[LatticeField]: ...
    @property
    def nmax(self) -> int: ...
    @property
    def mode(self) -> str: ...
    @property
    def bar(self) -> Progress: ...

    def advance(self, group: np.ndarray, i: int, rtol: float, max_newton: int, box: float | None) -> None:
        """Slice ``i + 1`` of the members of ``group`` still running: solved, stored, the failed ones retired."""
        ...


def step_members(batch: MemberBatch, rtol: float, max_newton: int, box: float | None) -> None:
    """The slices of a batch of ``b`` 1D trajectories, one slice of every member at a time: all members in one
    batched Newton (``mode="newton"``), or one member after the other (``"sweep"``: in 1D the site-by-site
    sweep is that same Newton on the one site); the batch's progress bar moves a slice at a time."""
    b = len(batch.fs)
    members = np.arange(b)
    groups = [members] if batch.mode == "newton" else [members[k : k + 1] for k in range(b)]
    bar = batch.bar
    for i in range(1, batch.nmax - 1):
        for group in groups:
            batch.advance(group, i, rtol, max_newton, box)
        bar.update(1)
    bar.close()


def slice_error(
    f: LatticeField, sys: _SliceSystem, i: int, msg: str, row: int | None, res: float, result: ServeResult
) -> ServeError:
    """The error for slice ``i``'s equations failing (at equation ``row``): slice, time, site and residual in
    one line (:func:`._slices.slice_message`), with the partial ``result``."""
    site = _site_label(f, sys, i, row) if row is not None else None
    text = slice_message(f, i, msg, site_text(f.dims, site, f.coords) if site else None, res)
    return ServeError(text, result=result, slice=i + 1, site=site, residual=res)


def solve_and_tally(
    run: SliceRun, i: int, g_prev: torch.Tensor | None, rtol: float, max_newton: int
) -> torch.Tensor | None:
    """Solve the equations of slice ``i`` of ``run`` (a whole-field or a windowed run: ``run.values``/``run.flat``
    its slices) for slice ``i + 1``; the iterations are counted on ``run``, a failure raised by ``run.fail``.

    The predictor on the unknown sites is :func:`._newton.predict`'s: ``2 psi_i - psi_{i-1}`` plus, for Newton
    with ``older`` (slice ``i - 2``: ``run.older(i)``), the previous slice's correction to its own such
    predictor (``3 psi_i - 3 psi_{i-1} + psi_{i-2}``: the next term of the extrapolation).

    Where the device or the compiled slice Newton serves (:func:`_sitewise`) it solves the slice and ``None``
    is returned for the gradients (``g_prev``: the cells anchored at ``i - 1``; ``None`` has them evaluated
    afresh).
    """
    flat, unk, psi, older = run.flat, run.unk, run.values, run.older(i)
    done = _sitewise(run, i, older, rtol, max_newton)
    if done is not None:  # the compiled or device slice Newton: no per-cell gradients are carried to the next slice
        _tallied(run, *done)
        return None
    folded = _folded_of(run) if run.mode == "newton" and not on_device(run) else None
    held = affine_held(run.cache, flat, i) if run.sys.members > 1 else None  # its values before the predictor
    sizes = None  # _slices._scale's three sizes at the predictor, where the folded predictor measured them
    if folded is not None:
        sizes = folded.predict(flat, i, older)
    else:  # the sweep predicts from the two slices before alone
        predict(flat, unk, i, older if run.mode == "newton" else None)
    if run.mode == "newton":
        if g_prev is None and folded is not None:
            g_prev = torch.from_numpy(folded.grad(flat, i - 1))
        elif g_prev is None:
            g_prev = CellDerivatives(run.model, run.cells_at(i - 1)).grad
        evaluate = functools.partial(folded.evaluate, flat, run.vol) if folded else None
        if run.sys.members > 1:  # a stacked ensemble: every member judged on its own, as served alone
            it, res, g_prev, err = newton_members(
                run.model, run.sys, flat, unk, i, g_prev, run.vol, rtol, max_newton, run.cells_at, run.cache, evaluate,
                held,
            )  # fmt: skip
        else:
            it, res, g_prev, err = _newton_slice(
                run.model,
                run.sys,
                psi,
                flat,
                unk,
                i,
                g_prev,
                run.vol,
                rtol,
                max_newton,
                run.cells_at,
                run.cache,
                evaluate=evaluate,
                sizes=sizes,
            )
    else:
        it, res, g_prev, err = _sweep_slice(run.model, run.sys, psi, flat, i, run.vol, rtol, max_newton, run.f)
    if err is not None:
        _tallied(run, it, res)
        msg, row, rval = err
        raise run.fail(i, msg, row, rval)
    _tallied(run, it, res)
    return g_prev


def _sitewise(
    run: SliceRun, i: int, older: torch.Tensor | None, rtol: float, max_newton: int
) -> tuple[int, float] | None:
    """Slice ``i`` of ``run`` solved by the device slice Newton (a run on a device, :func:`on_device`) or the
    compiled one, where either serves it: ``(evaluations, residual)``; ``None`` where neither does (or a site
    failed: slice-Newton then solves the slice)."""
    if run.mode != "newton":
        return None
    flat, cache = run.flat, run.cache
    if on_device(run):
        at = run.base + i  # the slice's index in the whole field
        _choose_device(run, i, at, older)
        device = _device_of(run)
        return None if device is None else device.solve(flat, i, at, older, run.vol, rtol, max_newton, cache)
    _choose_fused(run, i, older)
    fused = _fused_of(run)
    return None if fused is None else fused.solve(flat, i, older, run.vol, rtol, max_newton, cache)


def solve_run(run: SliceRun, i: int, stop: int, rtol: float, max_newton: int) -> int:
    """Slices ``i .. stop - 1`` of ``run`` (a whole-field or a windowed run: ``run.flat`` its slices, slice
    ``j - 2`` the older one of slice ``j`` from ``j = 2`` on, ``run.older(1)`` that of slice 1) solved in
    one call of the compiled slice Newton once it serves the run (as :func:`_sitewise` would call it slice by
    slice; at most :data:`RUN_SITES` unknowns a call, so that the progress bar moves), tallied as
    :func:`solve_and_tally` tallies them: how many (``0``: none; a slice a site could not finish is left to
    :func:`solve_and_tally`)."""
    fused = run.cache.get("fused")
    if fused is None or not fused.rows.size or run.mode != "newton" or on_device(run):
        return 0
    stop = min(stop, i + max(1, RUN_SITES // fused.rows.size))
    before = run.older(1) if i == 1 else None
    j, its, res = fused.solve_many(run.flat, i, stop, run.vol, rtol, max_newton, run.cache, before)
    if its:
        run.total_it += sum(its)
        run.max_it = max(run.max_it, *its)
        run.worst = max(run.worst, *res)
        run.bar.update(len(its))
    return int(j - i)


def step_slices(
    run: SliceRun, i: int, stop: int, g_prev: torch.Tensor | None, rtol: float, max_newton: int
) -> torch.Tensor | None:
    """The equations of positions ``i .. stop - 1`` of ``run`` solved one after the other, each for the next
    position: runs of slices by the compiled slice Newton where it serves (:func:`solve_run`), the others one
    by one (:func:`solve_and_tally`, from ``g_prev``, the gradients of the cells anchored at ``i - 1`` where
    known); returns the gradients of the cells anchored at the last position solved (``None``: not known)."""
    while i < stop:
        solved = solve_run(run, i, stop, rtol, max_newton)  # the compiled slice Newton: many slices a call
        if solved:
            i, g_prev = i + solved, None
            continue
        g_prev = solve_and_tally(run, i, g_prev, rtol, max_newton)
        i += 1
    return g_prev


def _tallied(run: SliceRun, it: int, res: float) -> None:
    """Count a solved slice's iterations and residual on ``run`` (and its progress bar)."""
    run.total_it += it
    run.max_it = max(run.max_it, it)
    run.worst = max(run.worst, res)
    run.bar.update(1)


def _choose_fused(run: SliceRun, i: int, older: torch.Tensor | None) -> None:
    """Before the first Newton slice, where the compiled slice Newton could serve: the site-wise solver chosen
    and the scales set from the Hessian blocks at the predictor, as slice-Newton's first iteration would
    (``_newton._fresh_blocks``; ``_solvers.choose_solver`` chooses site-wise for a Jacobian block diagonal by
    the L_d's form), so that the kernel serves the first slice too. Anything else (a singular Jacobian,
    another solver asked for, a checkpointed run) is left to slice-Newton, which reports it as before."""
    cache = run.cache
    if "fused" in cache or "dmax" in cache or cache.get("keep_factored"):
        return
    fused = fused_slices(run.model, run.sys, run.flat) if cache.get("solver") in ("auto", "sitewise") else None
    if fused is None:
        return
    fused.predict(run.flat, i, older)  # solve_and_tally's predictor, to the bit
    found = fused.scales(run.flat, i)
    if found is None:
        return
    dmax, smin, smax, _ = found
    scale = max(cache.get("mscale", 0.0), smax)
    if is_singular(smin, scale):
        return
    cache["dmax"], cache["mscale"] = dmax, scale
    cache["used"] = ["sitewise"]
    cache["fused"] = fused


def solver_name(mode: str, affine_slices: int, steps: int) -> str:
    """The ``solver`` of a served field's result: ``"sweep"``, ``"newton"``, ``"affine"`` (every slice by the
    affine recurrence) or ``"affine+newton"`` (the recurrence first, then Newton), from ``steps`` slices of
    which ``affine_slices`` the recurrence served (after the two given ones)."""
    if mode == "sweep":
        return "sweep"
    if not affine_slices:
        return "newton"
    return "affine" if affine_slices >= steps - 2 else "affine+newton"


def served_where(device: str | None) -> torch.device:
    """The device of a field's slice solves: CUDA where ``device`` asks for it and it is here (the request was
    checked, and a fallback said, when serving began), else the CPU."""
    if device in (None, "cpu") or not torch.cuda.is_available():
        return torch.device("cpu")
    return resolve_device(device)


def on_device(run: SliceRun) -> bool:
    """Whether ``run``'s Newton slices are solved on its device (:mod:`._ondevice`) once the site-wise solver
    is chosen: on CUDA (or on the CPU where the tests ask), for Newton on a run not checkpointed."""
    where: torch.device = run.where
    wanted = where.type == "cuda" or _ondevice.ON_CPU
    return wanted and run.mode == "newton" and not run.cache.get("keep_factored")


def _choose_device(run: SliceRun, i: int, at: int, older: torch.Tensor | None) -> None:
    """Before the first Newton slice of a run on a device: the site-wise solver chosen and the scales set from
    the Hessian blocks at the predictor, as slice-Newton's first iteration would (``_choose_fused`` on the
    CPU), so that the device serves the first slice too. A Jacobian that is not block diagonal (to
    ``OFFDIAG_RTOL``) or is singular, another solver asked for, or scales already set are left to
    slice-Newton (which may still choose the site-wise solver, the device then serving the later slices)."""
    cache = run.cache
    if "probed" in cache or "used" in cache or "dmax" in cache or cache.get("solver") not in ("auto", "sitewise"):
        return
    cache["probed"] = True
    device = _ondevice.device_slices(run.model, run.sys, run.flat, run.where)
    if device is None:
        return
    found = device.probe(run.flat, i, at, older)
    mscale = max(cache.get("mscale", 0.0), found["smax"])
    if not found["off"] <= OFFDIAG_RTOL * found["smax"] or is_singular(found["smin"], mscale):
        return
    cache["dmax"], cache["mscale"] = found["dmax"], mscale
    cache["used"] = ["sitewise"]
    cache["on_device"] = device


def _device_of(run: SliceRun) -> _ondevice.DeviceSlices | None:
    """The device slice Newton of ``run`` once slice-Newton has chosen the site-wise solver (and only that
    one) for it; ``None`` before, or where the field is not scalar."""
    cache = run.cache
    if "on_device" not in cache:
        if cache.get("used") != ["sitewise"] or "dmax" not in cache or "mscale" not in cache:
            return None
        cache["on_device"] = _ondevice.device_slices(run.model, run.sys, run.flat, run.where)
    device: _ondevice.DeviceSlices | None = cache["on_device"]
    return device


def _folded_of(run: SliceRun) -> FoldedSlices | StackedFolded | None:
    """The folded polynomial kernels of ``run`` (:mod:`._folded`; a stacked ensemble's, one member at a time:
    :mod:`._stackfold`) or a kinetic-potential MLP's closed forms on them (:mod:`._potential`), or ``None`` where
    none serves it."""
    cache = run.cache
    if "folded" not in cache:
        cache["folded"] = (
            folded_slices(run.model, run.sys, run.flat)
            or stacked_folded(run.model, run.sys, run.flat)
            or potential_slices(run.model, run.sys, run.flat)
        )
    folded: FoldedSlices | StackedFolded | None = cache["folded"]
    return folded


def _fused_of(run: SliceRun) -> FusedSlices | None:
    """The compiled slice Newton of ``run`` (:mod:`._fused`) once slice-Newton has chosen the site-wise solver
    (and only that one) for it; ``None`` before, or where the model or lattice has none."""
    cache = run.cache
    if "fused" not in cache:
        if cache.get("used") != ["sitewise"] or "dmax" not in cache or "mscale" not in cache:
            return None
        cache["fused"] = fused_slices(run.model, run.sys, run.flat)
    fused: FusedSlices | None = cache["fused"]
    return fused


#: The unknowns (sites times slices) the compiled slice Newton solves in one call at most.
RUN_SITES = 1 << 22
