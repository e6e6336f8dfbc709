"""A task served split into slabs (or pencils) over the processes of the group (``--workers N``, ``torchrun``).

Every process takes part in each task that can be split (:func:`split_refusal` is None and the learned DEL
is the explicit affine recurrence, or nonlinear: slice-Newton, its step site-wise or by GMRES over the
processes; ``solver = "lu"`` is refused by :func:`check_split`):
:func:`serve_split` serves it with :func:`latticedft._serve._decomp.serve_slabs`, each process reading only
its slab (with its halo planes) of ``from``, and measuring the errors against its slab of ``reference`` and
``baseline``; the sums and maxima are reduced over the processes. Rank 0 gets the gathered field and the
task's figures; it alone measures the invariant, the charges and the training range on the gathered field,
and writes the results. A task with an output cadence (``every > 1``) has rank 0 receive every slice whole,
to measure the invariant and the training range on every slice and to append the kept slices to the task's
part file, as one process does. A task that cannot be split is served by rank 0 alone (an info line says
why).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
import xarray as xr

from .._collective import is_parallel, reduce, world
from .._errors import InputError, ServeError
from .._lattice import as_lattice_field
from .._layout import lattice_dims
from .._models import AbstractLagrangian
from .._models._ensemble import EnsembleLagrangian
from .._options import option
from .._procenv import env_world
from .._serve import ServeResult
from .._serve._decomp import Block, _halo_width, plan_grid
from .._serve._decomp import serve_slabs as _serve_slabs
from .._serve._flag import SlabError
from .._serve._options import kept_slices
from .._serve._range import EXTRAPOLATION_TOL, _excess, assess, extrapolation_warning, feature_labels
from .._serve._slabkrylov import lu_refusal
from .._serve._stream import _with_slice_coord
from ._data import TaskData
from ._meter import TaskMeter
from ._splitckpt import served, split_checkpoint

__all__ = ["Split", "check_split", "serve_split", "skip_task", "split_refusal"]

log = logging.getLogger("latticedft")


def split_refusal(model: AbstractLagrangian | None, td: TaskData) -> str | None:
    """Why ``td`` is served in one process when there are several (None: it is split; ``model`` None: the
    task's settings only)."""
    opts = td.task.options
    reasons = (
        (len(lattice_dims(td.init)) < 2, "a 1D trajectory has no spatial axis to split"),
        (td.slices <= 2, "it serves no slice"),
        (opts.mode != "newton" or not opts.affine, "only the affine recurrence and slice-Newton split (mode, affine)"),
        (opts.boundary_value is not None, "its boundary_value is a function of the whole lattice"),
        (_denoised(model, td), "its start is denoised on the whole lattice"),
        (isinstance(model, EnsembleLagrangian), "an ensemble is served whole"),
    )
    return next((why for cond, why in reasons if cond), None)


def skip_task(model: AbstractLagrangian, td: TaskData) -> None:
    """Rank 0, under ``--resume``: a task done before the run stopped, which the others skip too when split."""
    if is_parallel() and split_refusal(model, td) is None:
        served(True, skip=True)


def _denoised(model: AbstractLagrangian | None, td: TaskData) -> bool:
    """True when the task starts from slices denoised by the learned DEL (``[[serve]] start``)."""
    report = getattr(model, "report_", None)
    noise = (report.noise if report is not None else None) or {}
    return td.task.start == "denoised" or (td.task.start == "auto" and noise.get("method", "none") != "none")


def check_split(tasks: list[TaskData], model: AbstractLagrangian | None = None) -> bool:
    """The bad input of split serving, before anything is written: more processes than planes of the outer
    axis, or (with ``model``) a halo wider than a slab, in one line naming ``--workers``; ``solver = "lu"``
    (not split), in one line naming the task's ``solver`` and the alternative. True when some task may be
    split (its settings allow it) over several processes."""
    size = world()[1] if is_parallel() else _env_size()
    split = [td for td in tasks if split_refusal(model, td) is None]
    if size <= 1 or not split:
        return False
    for td in split:
        if td.task.options.solver == "lu":
            raise lu_refusal(f"{td.task.label}.solver")
        axes = lattice_dims(td.init)[1:3]
        halos = tuple(_halo_width(model, k + 1) if model is not None else 0 for k in range(len(axes)))
        try:
            plan_grid(tuple(td.init.sizes[a] for a in axes), size, halos, (False,) * len(axes), axes)
        except InputError as exc:
            raise InputError.at("--workers", f"task {td.task.name!r}: {exc.problem}") from None
    return True


def _env_size() -> int:
    """The number of processes the environment describes (``torchrun``'s, or ``--workers``')."""
    return env_world()


@dataclass
class Split:
    """A task served split: rank 0's result, errors and the decomposition (the other processes: None)."""

    result: ServeResult | None
    #: ``(compare dict, the reference's largest magnitude)`` over the compared slices; None without reference
    errors: tuple[dict[str, float], float] | None
    #: ``(all slices both hold, the served slices)`` of the baseline against the reference; None without one
    baseline: tuple[dict[str, float], dict[str, float]] | None
    decomposition: dict[str, Any] = field(default_factory=dict)
    #: why the split serve stopped before its last slice (the result then holds what was served); "" when not
    stopped: str = ""
    #: a task with an output cadence: rank 0's invariant, measured on every slice (None otherwise)
    meter: TaskMeter | None = None


class _Whole:
    """Rank 0's measurements of a task with an output cadence on every slice served, as one process makes
    them: the invariant (a :class:`TaskMeter` without reference: the errors are measured on the slabs), the
    excess over the training range per anchor slice (``_range._excess``), and each kept slice handed to
    ``part``. The slices arrive whole (``serve_slabs(on_slice=...)``) and are measured in blocks."""

    def __init__(self, model: AbstractLagrangian, td: TaskData, part: Any):
        self.model, self.slices = model, td.slices
        tdim = lattice_dims(td.init)[0]
        two = td.init.isel({tdim: slice(0, 2)}).compute()
        self.f = f = as_lattice_field(two, source="init", boundary=td.task.boundary, min_slices=2)
        self.meter = TaskMeter(None, td.invariant, part)
        self.kept = set(kept_slices(td.slices, td.task.cadence.every).tolist())
        rng = model.trained_range()
        self.rng = rng.to(torch.float64) if rng is not None and tuple(rng.shape[1:]) == (f.ndim + 1, f.ncomp) else None
        self.per_anchor = np.zeros((td.slices - 1, self.rng[0].numel())) if self.rng is not None else None
        self.size = max(1, option("task_block_bytes") // max(1, 8 * int(np.prod(f.shape[1:])) * f.ncomp))
        self.block: list[np.ndarray] = []
        self.start = 0
        self.prev: torch.Tensor | None = None  # the last slice of the block before: its anchor's cells

    def __call__(self, i: int, values: np.ndarray) -> None:
        if i in self.kept:
            self.meter(i, values if self.f.components is not None else values[..., 0])
        self.block.append(values)
        if len(self.block) >= self.size or i == self.slices - 1:
            self.flush()

    def flush(self) -> None:
        """Measure the slices received since the last flush."""
        if not self.block:
            return
        vals = torch.from_numpy(np.stack(self.block))
        if self.per_anchor is not None and self.rng is not None:
            span = vals if self.prev is None else torch.cat([self.prev[None], vals])
            lo = self.start - (span.shape[0] - vals.shape[0])
            if span.shape[0] >= 2:
                self.per_anchor[lo : lo + span.shape[0] - 1] = _excess(self.model, self.rng, self.f, span)
        t0 = float(self.f.coords[self.f.dims[0]][0] + self.f.spacing[0] * self.start)
        self.meter.on_block(self.start, self.f.with_values(vals, t0=t0).to_dataarray())
        self.prev, self.start, self.block = vals[-1], self.start + vals.shape[0], []

    def field(self, got: xr.DataArray, every: int) -> xr.DataArray:
        """The kept slices ``got`` (gathered, with their ``slice`` coordinate) as one process's result."""
        idx = np.asarray(got["slice"].values, dtype=np.int64)
        values = np.asarray(got.values, dtype=np.float64)
        f, tdim = self.f, self.f.dims[0]
        da = f.with_values(torch.from_numpy(values if f.components is not None else values[..., None])).to_dataarray()
        t_all = f.coords[tdim][0] + f.spacing[0] * np.arange(int(idx[-1]) + 1, dtype=np.float64)
        da = da.assign_coords({tdim: (tdim, t_all[idx], dict(da[tdim].attrs))})
        return _with_slice_coord(da, idx, every)

    def extrapolation(self, nt: int) -> xr.DataArray | None:
        """The excess per slice over the ``nt`` slices served (as one process's ``ServeResult`` has it)."""
        if self.per_anchor is None or nt < 2:
            return None
        per_slice = np.zeros((nt, self.per_anchor.shape[1]))
        per_slice[:-1] = self.per_anchor[: nt - 1]
        per_slice[1:] = np.maximum(per_slice[1:], self.per_anchor[: nt - 1])
        f, tdim = self.f, self.f.dims[0]
        t_all = f.coords[tdim][0] + f.spacing[0] * np.arange(nt, dtype=np.float64)
        coords = {tdim: t_all, "feature": feature_labels(self.model, f.dims, f.components)}
        attrs = {
            "long_name": "excess of the stencil inputs beyond the training range, relative to its span",
            "tolerance": EXTRAPOLATION_TOL,
        }
        return xr.DataArray(per_slice, dims=(tdim, "feature"), coords=coords, name="extrapolation", attrs=attrs)


class _SlabErrors:
    """The errors of one process's slab against its slab of the reference, slice by slice (sums and maxima)."""

    def __init__(self, ref: xr.DataArray | None):
        self.ref = ref
        self.worst, self.sum_sq, self.count, self.compared, self.ref_max = 0.0, 0.0, 0, 0, 0.0

    def __call__(self, i: int, block: Block, own: np.ndarray) -> None:
        ref = self.ref
        if ref is None or i >= ref.sizes[ref.dims[0]]:
            return
        part = np.asarray(ref.isel({ref.dims[0]: i, **block.owned(ref.dims)}).values, np.float64)
        d = np.abs(own.reshape(part.shape) - part)
        self.worst = max(self.worst, float(d.max()))
        self.ref_max = max(self.ref_max, float(np.abs(part).max()))
        self.sum_sq += float(np.sum(d**2))
        self.count += d.size
        self.compared = i + 1

    def own(self) -> tuple[float, float, float, int, int]:
        """This process's figures (a checkpoint carries them)."""
        return self.worst, self.sum_sq, self.ref_max, self.count, self.compared

    def put(self, own: tuple[float, float, float, int, int] | None) -> None:
        """Go on from ``own`` (None: the figures were not this process's; rank 0 goes on from the totals)."""
        if own is not None:
            self.worst, self.sum_sq, self.ref_max, self.count, self.compared = own

    def reduced(self) -> tuple[dict[str, float], float]:
        worst, ref_max, sum_sq, count = _reduce_errors(self.worst, self.ref_max, self.sum_sq, self.count)
        rms = math.sqrt(sum_sq / count) if count else math.nan
        return {"max_error": worst, "rms_error": rms, "slices": self.compared}, ref_max


def _reduce_errors(worst: float, ref_max: float, sum_sq: float, count: float) -> tuple[float, float, float, float]:
    """The maxima and sums over the processes."""
    mx = reduce(torch.tensor([worst, ref_max], dtype=torch.float64), dist.ReduceOp.MAX)
    sm = reduce(torch.tensor([sum_sq, float(count)], dtype=torch.float64), dist.ReduceOp.SUM)
    return float(mx[0]), float(mx[1]), float(sm[0]), float(sm[1])


def _baseline_errors(td: TaskData, block: Block, slices: int) -> dict[str, float]:
    """The baseline against the reference over their first ``slices`` slices, on the slab, reduced."""
    base, ref = td.baseline, td.reference
    assert base is not None and ref is not None
    worst, sum_sq, count = 0.0, 0.0, 0
    for i in range(slices):
        own = block.owned(ref.dims)
        d = np.asarray(base.isel({base.dims[0]: i, **own}).values, np.float64) - np.asarray(
            ref.isel({ref.dims[0]: i, **own}).values, np.float64
        )
        worst, sum_sq, count = max(worst, float(np.abs(d).max())), sum_sq + float(np.sum(d**2)), count + d.size
    worst, _, sum_sq, total = _reduce_errors(worst, 0.0, sum_sq, count)
    return {"max_error": worst, "rms_error": math.sqrt(sum_sq / total) if total else math.nan, "slices": slices}


def serve_split(
    model: AbstractLagrangian,
    td: TaskData,
    init: xr.DataArray,
    part: Any = None,
    resumed: dict[str, Any] | None = None,
    resume: bool = False,
) -> Split:
    """Serve ``td`` over the processes (every process calls it); rank 0 gets its :class:`Split`, the others
    one without result. A task served in one process instead (by rank 0: its ``result`` None in every
    process) has the reason in its ``decomposition``. A task with an output cadence or checkpoints is
    measured on every slice by rank 0 (:class:`_Whole`), which hands its kept slices to ``part`` (the task's
    part file) and writes the checkpoints (``_splitckpt``), going on from ``resumed`` (the checkpoint read).
    ``resume``: the command's ``--resume`` (in every process; the tasks done before are skipped)."""
    why = split_refusal(model, td)
    if why is None and not served(resume):
        return Split(result=None, errors=None, baseline=None)
    if why is None:
        t0 = time.perf_counter()
        report: dict[str, Any] = {}
        meter = _SlabErrors(td.reference)
        whole_slices = td.task.cadence.thins or bool(td.task.options.checkpoint)
        whole = _Whole(model, td, part) if whole_slices and world()[0] == 0 else None
        ckpt = split_checkpoint(td, meter, whole, part, resumed) if td.task.options.checkpoint else None
        stopped = None
        try:
            got = _serve_slabs(
                model, init, td.slices, boundary=td.task.boundary, rtol=td.task.options.rtol,
                max_newton=td.task.options.max_newton, on_slab=meter, report=report, solver=td.task.options.solver,
                every=td.task.cadence.every, on_slice=whole or (_ignore if whole_slices else None), checkpoint=ckpt,
            )  # fmt: skip
        except SlabError as exc:  # the same in every process; rank 0 holds what was served before it
            if report:
                stopped, got = exc, exc.result
            else:  # it stopped while setting up: nothing was served, rank 0 serves the task alone
                why = str(exc)
        except (InputError, ServeError) as exc:  # the same in every process: the test is global
            why = str(exc).removeprefix("--workers: ").split("; serve it in one process")[0]
    if why is not None:
        if world()[0] == 0:
            log.info("task %s: served in one process, not split over %d: %s", td.task.name, world()[1], why)
        return Split(result=None, errors=None, baseline=None, decomposition={"processes": 1, "reason": why})
    errors = meter.reduced() if td.reference is not None else None
    baseline = None
    if td.baseline is not None and td.reference is not None:
        block = report["block"]
        n = min(td.baseline.sizes[td.baseline.dims[0]], td.reference.sizes[td.reference.dims[0]])
        baseline = (_baseline_errors(td, block, n), _baseline_errors(td, block, min(n, meter.compared)))
    decomposition = _decomposition(report, td.task.name)
    if got is None:
        return Split(result=None, errors=None, baseline=None)
    if whole is not None:
        whole.flush()
        whole.meter.finish()
    result = _result(model, td, got, report, time.perf_counter() - t0, stopped, whole)
    if stopped is not None:
        log.warning("task %s stopped at %s; %d of %d slices written", td.task.name, stopped, result.slices, td.slices)
    text = "" if stopped is None else str(stopped)
    meter_ = None if whole is None else whole.meter
    return Split(result, errors, baseline, decomposition, stopped=text, meter=meter_)


def _ignore(i: int, values: np.ndarray) -> None:
    """The ``on_slice`` of the processes but rank 0 (they take part in the gather and see nothing)."""


def _decomposition(report: dict[str, Any], name: str) -> dict[str, Any]:
    """The decomposition of a split task for ``summary.json`` (logged by rank 0): slabs as before pencils,
    pencils with their grid, axes and blocks."""
    if "slabs" in report:
        if world()[0] == 0:
            slabs = " ".join(f"[{lo}, {hi})" for lo, hi in report["slabs"])
            log.info("task %s: split over %d processes along %r, slabs %s", name, world()[1], report["axis"], slabs)
        return {k: report[k] for k in ("processes", "axis", "slabs")}
    if world()[0] == 0:
        log.info("task %s: split over %d processes, %s", name, world()[1], report["grid"])
    return {k: report[k] for k in ("processes", "grid", "axes", "blocks")}


def _result(
    model: AbstractLagrangian,
    td: TaskData,
    got: xr.DataArray,
    report: dict[str, Any],
    wall: float,
    stopped: SlabError | None = None,
    whole: _Whole | None = None,
) -> ServeResult:
    """Rank 0's result of the gathered field, as one process reports the affine recurrence or slice-Newton
    (``stopped``: the failure that ended it early, the field then holding the slices served before it)."""
    slices = int(got["slice"].values[-1]) + 1
    if whole is None:
        f = as_lattice_field(got.drop_vars("slice"), source="served", boundary=td.task.boundary, min_slices=2)
        field = f.to_dataarray()
        ext, warnings = assess(model, f)
    else:  # the kept slices, as one process's stream gives them; measured on every slice
        field = whole.field(got, td.task.cadence.every)
        ext = whole.extrapolation(slices)
        warning = extrapolation_warning(ext)
        warnings = [warning] if warning else []
    solved = (slices - 2) * int(np.prod(field.shape[1 : 1 + len(lattice_dims(got)) - 1]))
    return ServeResult(
        field=field,
        complete=stopped is None,
        reason="complete" if stopped is None else str(stopped),
        slices=slices,
        newton_iterations=int(report["newton_iterations"]),
        max_newton_iterations=int(report["max_newton"]),
        wall_time=wall,
        sites_per_second=solved / wall if wall > 0 else math.inf,
        max_residual=float(report["max_residual"]),
        mode=td.task.options.mode,
        solver=str(report["solver"]),
        slice_solver=report["slice_solver"],
        extrapolation=ext,
        warnings=warnings,
    )
