"""One task served: :func:`serve_task` serves it, measures it against its reference and logs its line.

Serving gives the field (a Newton failure gives a partial field, not an exception); measuring gives the
task's :class:`~latticedft._run._record.TaskRecord` (errors, invariant, charges); the message step logs the
task's line and, in plain words, why a task stopped or why its field is not to be trusted.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from .._calibrate import candidates_disagreement, served_along
from .._case import ServeTask
from .._collective import is_parallel
from .._contract import AbstractLagrangian
from .._errors import InputError, ServeError
from .._learn._noise import DENOISE_SLICES, denoised_start
from .._part_file import PartFile
from .._serve import ServeResult, calibration, compare, serve
from .._serve._ensemble import calibration_warning
from .._serve._result import LEFT_THE_BOX
from ._calib import TaskBand, task_band
from ._charges import drift_text, task_charges
from ._data import TaskData
from ._meter import TaskMeter, compare_blocks
from ._record import TaskRecord, accuracy_warning
from ._resume import TaskCheckpoint, open_part
from ._split import Split, serve_split

__all__ = ["TaskOutcome", "serve_task"]

log = logging.getLogger("latticedft")


@dataclass
class TaskOutcome:
    """A served task: its field, reference and the numbers that go into summary.json."""

    name: str
    field: xr.DataArray
    reference: xr.DataArray | None
    invariant: xr.DataArray | None
    record: TaskRecord
    #: ``charge_<name>(t)`` and ``energy(t)`` of the task's ``charges`` (None when it lists none)
    charges: xr.Dataset | None = None
    #: ``extrapolation(t, feature)`` of the served field against the model's training range (None without one)
    extrapolation: xr.DataArray | None = None
    #: An ensemble served: the mean and standard deviation over its members (None for a single model)
    mean: xr.DataArray | None = None
    std: xr.DataArray | None = None
    #: A task with an output cadence served into a staging folder: the part file holding its kept slices
    part: Path | None = None
    #: The calibrated error bar (None without a calibration): ``std`` above is then the calibrated one
    band: TaskBand | None = None
    #: An ensemble's standard deviation before calibration (None when not calibrated)
    std_raw: xr.DataArray | None = None

    def spread(self, variable: str) -> dict[str, xr.DataArray]:
        """``{"<variable>_mean": ..., "<variable>_std": ...}`` for an ensemble (with ``<variable>_std_members``,
        the members' own spread, when calibrated), and ``<variable>_err_est`` when calibrated."""
        out = {}
        if self.mean is not None and self.std is not None:
            out = {f"{variable}_mean": self.mean, f"{variable}_std": self.std}
            if self.std_raw is not None:
                out[f"{variable}_std_members"] = self.std_raw
        if self.band is not None:
            out[f"{variable}_err_est"] = self.band.err_est.rename(f"{variable}_err_est")
        return out

    @property
    def complete(self) -> bool:
        return self.record.complete

    def file_attrs(self, model_warnings: list[str]) -> dict[str, Any]:
        """Global attributes of ``<task>.nc`` saying whether the field is complete and what to distrust.

        ``latticedft_complete`` ("true"/"false"), ``latticedft_warnings`` (a JSON list of one-line warnings:
        the model's, then the task's) and, for an incomplete task, ``latticedft_stopped_at_slice`` (slices
        written) and ``latticedft_stop_reason``. (``latticedft_steps`` is written by ``write_task``.)
        """
        rec = self.record
        attrs: dict[str, Any] = {
            "latticedft_complete": "true" if self.complete else "false",
            "latticedft_warnings": json.dumps([*model_warnings, *rec.warnings]),
        }
        if not self.complete:
            attrs["latticedft_stopped_at_slice"] = int(rec.slices)
            attrs["latticedft_stop_reason"] = str(rec.stop_reason or rec.reason or "")
        return attrs


def _start(model: AbstractLagrangian, td: TaskData) -> tuple[xr.DataArray, str]:
    """The task's initial data and how they were taken (``[[serve]] start``): ``denoised`` asks for it, ``auto``
    denoises when training corrected noisy data."""
    noise = (model.report_.noise if model.report_ is not None else None) or {}
    if td.task.start == "data" or (td.task.start == "auto" and noise.get("method", "none") == "none"):
        return td.init, "data"
    log.info(
        "serving %s from initial slices denoised by the learned DEL (first %d slices)", td.task.name, DENOISE_SLICES
    )
    return denoised_start(model, td.init), "denoised"


def serve_task(
    model: AbstractLagrangian,
    td: TaskData,
    device: str = "cpu",
    *,
    stage: Path | None = None,
    variable: str = "psi",
    resume: bool = False,
    calibration: dict[str, Any] | None = None,
    trial: AbstractLagrangian | None = None,
    runner: AbstractLagrangian | None = None,
) -> TaskOutcome:
    """Serve one task (the model evaluated on ``device``); a Newton failure gives an incomplete outcome (with a
    warning), not an exception.

    A task with an output cadence (``[[serve]] every > 1``) served into a staging folder ``stage`` appends
    each kept slice, as it is served, to the part file ``stage/.<task>.nc.part`` (the field as ``variable``):
    the outcome's ``part`` names it, and ``write_task`` completes it into ``<task>.nc``. So does a task with
    checkpoints (``[[serve]] checkpoint``), which with ``resume`` goes on from its checkpoint in ``stage``. A
    ``calibration`` (the law of ``[train] calibrate``) gives the outcome its calibrated error bar; its ``trial``
    model (learned on the held-in part of the data) is served from the same start, and its disagreement enters
    the bar; so is the ``runner`` (the runner-up candidate's trial, None without one), whose disagreement with
    the trial is compared with theirs on the training fields (a warning, not a band).
    """
    t = td.task
    if t.deprecated_steps:
        log.warning(
            "case.toml: %s.steps is deprecated: write %s.slices (the same count: time slices served, the two initial "
            "ones included)",
            t.label,
            t.label,
        )
    log.info("serving %s: %d slices from %s (%s)", t.name, td.slices, t.source.name, t.options.mode)
    part: PartFile | None = None
    resumed: dict[str, Any] | None = None  # the checkpoint the task goes on from
    if stage is not None and (t.cadence.thins or t.options.checkpoint):
        part, resumed = open_part(stage, t.name, variable, td.init, t.cadence.every, resume)
    try:
        served = _serve(model, td, device, part, resumed, resume)
    finally:
        if part is not None:
            part.close()
    band = _band(calibration, (trial, runner), served, td) if calibration else None
    rec, inv, charges = _measure(model, served, td, band)
    _message(served, td, rec)
    result = served.result
    return TaskOutcome(
        name=t.name,
        field=result.field,
        reference=td.reference,
        invariant=inv,
        record=rec,
        charges=charges,
        extrapolation=_kept(result.extrapolation, result.field),
        mean=result.mean,
        std=band.std if band is not None and band.std is not None else result.std,
        part=part.path if part is not None else None,
        band=band,
        std_raw=result.std if band is not None and band.std is not None else None,
    )


@dataclass
class _Served:
    """A task's serving run: its result, wall time, stop message, how it started and its meter (a cadence)."""

    result: ServeResult
    wall: float
    stopped: str
    start: str
    meter: TaskMeter | None
    #: the task served split over the processes of a group (None: in one process)
    split: Split | None = None
    init: xr.DataArray | None = None


# -- serve ----------------------------------------------------------------------------------------------------
def _serve(
    model: AbstractLagrangian,
    td: TaskData,
    device: str,
    part: PartFile | None,
    resumed: dict[str, Any] | None,
    resume: bool = False,
) -> _Served:
    """Serve ``td`` with the task's options; with an output cadence (or checkpoints), a meter measures every
    slice as it is served and hands each kept slice to ``part`` (and each checkpoint to its ``checkpointer``).
    ``resumed``: the checkpoint the task goes on from (None: from its start); ``resume``: the command's
    ``--resume``."""
    t = td.task
    t0 = time.perf_counter()
    stopped = ""
    options = t.options.replace(progress=None, device=device)
    meter = None
    if t.cadence.thins or t.options.checkpoint:  # errors and the invariant measured on every slice as served
        meter = TaskMeter(td.reference, td.invariant, part)
        if part is not None and t.options.checkpoint:
            meter.checkpointer = TaskCheckpoint(part, meter, t.name, resumed)
    init, start = _start(model, td)
    split = serve_split(model, td, init, part, resumed, resume) if is_parallel() else None
    if split is not None and split.result is not None:
        return _Served(split.result, time.perf_counter() - t0, split.stopped, start, split.meter, split)
    try:
        result = serve(model, init, slices=t.slices, boundary=t.boundary, options=options, on_slice=meter)
    except ServeError as err:
        result = err.result
        if isinstance(result, list):  # pragma: no cover - a single init gives one result
            result = result[0]
        log.warning("task %s stopped at %s; %d of %d slices written", t.name, err, result.slices, td.slices)
        stopped = str(err)  # the reason with its slice, site and residual
    wall = time.perf_counter() - t0
    log.debug("task %s served on %s", t.name, result.device)
    if meter is not None:
        meter.finish()
    return _Served(result=result, wall=wall, stopped=stopped, start=start, meter=meter, split=split, init=init)


def _band(
    calibration: dict[str, Any],
    trials: tuple[AbstractLagrangian | None, AbstractLagrangian | None],
    served: _Served,
    td: TaskData,
) -> TaskBand:
    """The task's calibrated error bar, with the trial model's disagreement when there is a trial, and the
    runner-up's trial's disagreement with it when there is one (``trials``: the two, or None)."""
    field, other, between = served.result.field, None, None
    trial, runner = trials
    if trial is not None and served.init is not None:
        options = td.task.options.replace(progress=None, device=served.result.device)
        kw = {"slices": td.task.slices, "boundary": td.task.boundary, "options": options}
        mine = served_along(trial, served.init, field, **kw)
        nt = field.sizes[field.dims[0]]
        other = candidates_disagreement(np.asarray(field.values, dtype=np.float64), mine, nt)  # disagreement()
        if runner is not None:
            between = candidates_disagreement(mine, served_along(runner, served.init, field, **kw), nt)
    return task_band(calibration, field, served.result.std, other, served.result.members, between)


# -- measure --------------------------------------------------------------------------------------------------
def _measure(
    model: AbstractLagrangian, served: _Served, td: TaskData, band: TaskBand | None
) -> tuple[TaskRecord, xr.DataArray | None, xr.Dataset | None]:
    """The task's record, its invariant over the served field and its charges."""
    rec = _record(served, td, band)
    inv = _invariant(served, td, rec)
    charges = task_charges(model, td.task, served.result.field, rec)
    return rec, inv, charges


def _record(served: _Served, td: TaskData, band: TaskBand | None) -> TaskRecord:
    """The task's record: the result's numbers, then the errors against the reference and the baseline's,
    and how well the error bar (an ensemble's spread, or the calibrated estimate) held."""
    t, result, pred = td.task, served.result, served.result.field
    rec = TaskRecord.served(
        result.to_dict(),
        every=t.cadence.every,
        kept_slices=int(pred.sizes[pred.dims[0]]),
        stop_reason=None if result.complete else served.stopped,
        requested_slices=td.slices,
        source=t.source.name,
        start=served.start,
    )
    rec.wall_time = served.wall
    if served.split is not None:
        rec.decomposition = served.split.decomposition
    for warning in result.warnings:  # the served field leaves the training range
        log.warning("task %s: %s", t.name, warning)
    if td.reference is not None:
        _errors(served, td, rec)
    std = result.std if band is None else band.std if band.std is not None else _broadcast(band.err_est, pred)
    if band is not None:
        rec.error_estimate = band.record
        for warning in band.warnings:  # the task runs longer than, or outside, the calibration's windows
            _warn(rec, t, warning)
    if std is not None and td.reference is not None:  # is the error bar honest?
        rec.calibration = calibration(pred, std, td.reference)
        _warn(rec, t, calibration_warning(rec.calibration))
    _warn(rec, t, accuracy_warning(rec))  # complete is not accurate: a field far from its reference
    return rec


def _broadcast(series: xr.DataArray, like: xr.DataArray) -> xr.DataArray:
    """A series over time at every site of ``like`` (the estimate per slice as a per-site std)."""
    shape = (-1,) + (1,) * (like.ndim - 1)
    values = np.broadcast_to(np.asarray(series.values).reshape(shape), like.shape)
    return like.copy(data=np.array(values))


def _warn(rec: TaskRecord, t: ServeTask, warning: str | None) -> None:
    """A task's warning, when there is one: to its record (summary.json, the task file) and to the log."""
    if warning:
        rec.warnings.append(warning)
        log.warning("task %s: %s", t.name, warning)


def _errors(served: _Served, td: TaskData, rec: TaskRecord) -> None:
    """The errors against the task's reference (and its largest magnitude there), and the baseline's."""
    assert td.reference is not None
    t, pred, meter = td.task, served.result.field, served.meter
    if served.split is not None and served.split.errors is not None:  # reduced over the processes' slabs
        cmp, scale = served.split.errors
    elif meter is None:
        cmp = compare(pred, td.reference)
        scale = float(np.max(np.abs(np.asarray(td.reference.values[: cmp["slices"]], dtype=np.float64))))
    else:
        cmp, scale = meter.errors(), meter.reference_max
    rec.max_error, rec.rms_error, rec.compared_slices = cmp["max_error"], cmp["rms_error"], int(cmp["slices"])
    rec.relative_error = cmp["max_error"] / max(scale, np.finfo(float).tiny)
    rec.reference = (t.reference or t.source).name
    if td.baseline is None:
        return
    if served.split is not None and served.split.baseline is not None:
        b, b_same = served.split.baseline
    elif meter is None:
        b = compare(td.baseline, td.reference)
        b_same = compare(td.baseline.isel({pred.dims[0]: slice(0, cmp["slices"])}), td.reference)
    else:  # block by block: the files stay on disk
        b, b_same = (
            compare_blocks(td.baseline, td.reference),
            compare_blocks(td.baseline, td.reference, int(cmp["slices"])),
        )
    rec.baseline = {
        "file": t.baseline.name if t.baseline else None,
        "max_error": b["max_error"],
        "rms_error": b["rms_error"],
        "slices": b["slices"],
        "max_error_same_slices": b_same["max_error"],
        "rms_error_same_slices": b_same["rms_error"],
    }


def _invariant(served: _Served, td: TaskData, rec: TaskRecord) -> xr.DataArray | None:
    """The task's invariant over the served field (on the kept slices) and its drift into ``rec``."""
    t, pred, meter = td.task, served.result.field, served.meter
    if td.invariant is None:
        return None
    try:
        if meter is not None and meter.error is not None:
            raise meter.error
        inv = td.invariant(pred) if meter is None else meter.invariant_series(str(pred.dims[0]))
        values = np.asarray(inv, dtype=np.float64)
        if not isinstance(inv, xr.DataArray) or inv.dims != (pred.dims[0],):
            raise TypeError(f"expected a DataArray over {pred.dims[0]!r}, got {type(inv).__name__}")
    except Exception as exc:
        raise InputError(
            f"{t.label}.invariant {t.invariant!r}: failed on the served field "
            f"({type(exc).__name__}: {' '.join(str(exc).split())[:120]})"
        ) from None
    finite = values[np.isfinite(values)]
    if finite.size and finite[0] != 0:
        rec.invariant_drift = float(np.max(np.abs(finite - finite[0])) / abs(finite[0]))
    else:
        rec.invariant_drift = float(np.max(np.abs(finite - finite[0]))) if finite.size else None
    rec.invariant = t.invariant
    return _kept(inv, pred) if meter is not None else inv  # the file holds the kept slices


def _kept(series: xr.DataArray | None, pred: xr.DataArray) -> xr.DataArray | None:
    """``series`` (over every slice served) on the slices ``pred`` keeps (its ``slice`` coordinate)."""
    if series is None or "slice" not in pred.coords:
        return series
    tdim = pred.dims[0]
    return series.isel({tdim: pred["slice"].values}).assign_coords({tdim: pred[tdim].values})


# -- message --------------------------------------------------------------------------------------------------
def _message(served: _Served, td: TaskData, rec: TaskRecord) -> None:
    """Log the task's line (with the charges' drifts) and, for a task that stopped, what happened in plain
    words and the next step."""
    log.info("%s", _task_line(served, td.task, rec) + drift_text(rec))
    if not served.result.complete:
        log.info("task %s: %s", td.task.name, stop_verdict(served.stopped, rec.slices, td.slices))


def _task_line(served: _Served, t: ServeTask, rec: TaskRecord) -> str:
    """The task's log line (without the charges' drifts)."""
    result = served.result
    how = (
        f"{result.newton_iterations} Newton iterations"
        if result.solver != "affine"
        else f"affine recurrence (quadratic L_d, {result.newton_iterations} linear solves)"
    )
    msg = (
        f"task {t.name}: {'complete' if result.complete else 'INCOMPLETE'}, {result.slices} slices, {how}, "
        f"{served.wall:.2f} s"
    )
    if rec.members_stopped:  # complete, but the error bar is over fewer members (a warning says which)
        msg += f" ({len(rec.members_stopped)} of {rec.ensemble_members} ensemble members stopped)"
    if rec.members_outside:  # their fields leave their own training range (a warning says which)
        resampled = (rec.ensemble_members or 1) - 1
        msg += f" ({len(rec.members_outside)} of {resampled} resampled members left their training range)"
    if t.cadence.thins:
        msg += f"{t.cadence.describe()}: {rec.kept_slices} slices kept"
    if rec.max_error is not None:
        msg += f", max error {rec.max_error:.3e}, rms {rec.rms_error:.3e}"
    if rec.baseline is not None:
        msg += f" (baseline max {rec.baseline['max_error_same_slices']:.3e})"
    if rec.invariant_drift is not None:
        msg += f", invariant drift {rec.invariant_drift:.2e}"
    if rec.calibration is not None and rec.calibration["slices"]:
        cal = rec.calibration
        msg += f", within 2/3 std {cal['within_2std']:.0%}/{cal['within_3std']:.0%}"
    return msg


def stop_verdict(stopped: str, written: int, requested: int) -> str:
    """A stopped task in plain words: what happened (from the serve error's text ``stopped``), what was kept,
    and the next step to try."""
    kept = f"the first {written} of {requested} slices are written"
    if "singular" in stopped:
        return (
            f"verdict: stopped: the learned L_d cannot step the field there (its mixed Hessian is singular); {kept}; "
            "next: check the training verdict, train on data that reach this state, or try another model kind"
        )
    if LEFT_THE_BOX in stopped:
        return f"verdict: stopped: the field left the box the task sets (box); {kept}; next: widen the box if intended"
    return (
        "verdict: stopped: the solver found no next slice that obeys the learned equations (Newton did not "
        f"converge); {kept}; next: serve fewer slices, raise max_newton or rtol, or, when the field left the "
        "training range, train on data that cover it"
    )
