"""The stages of a case run: check, train, serve, export (used by the command line).

Each stage logs INFO lines (to stderr via the CLI) and DEBUG details (to
``results/run.log``). Bad input raises :class:`latticedft.InputError` or
:class:`latticedft.ConfigError` before anything is written.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from ._boundary import missing_edges
from ._case import Case, ServeTask, load_invariant
from ._case_charges import check_charges, drift_text, task_charges
from ._contract import AbstractLagrangian
from ._errors import ConfigError, InputError, LatticeDFTError, ServeError
from ._lattice import as_lattice_field
from ._layout import component_labels, field_spacing, lattice_dims
from ._part_file import PartFile
from .io.fields import read_field

__all__ = ["CaseData", "TaskData", "TaskOutcome", "check_case", "train_model", "serve_task"]

log = logging.getLogger("latticedft")


@dataclass
class TaskData:
    """What one serving task needs: the initial field, its reference and baseline."""

    task: ServeTask
    init: xr.DataArray
    reference: xr.DataArray | None
    baseline: xr.DataArray | None
    slices: int
    invariant: Callable[[xr.DataArray], Any] | None = None


@dataclass
class CaseData:
    """Every field a case reads, validated."""

    train: list[xr.DataArray]
    tasks: list[TaskData]
    dims: tuple[str, ...]
    spacing: tuple[float, ...]
    components: tuple[str, ...] | None

    def summary_lines(self, case: Case) -> list[str]:
        lines = [
            f"case {case.name}: lattice dims {self.dims}, spacing "
            f"{tuple(float(f'{h:.6g}') for h in self.spacing)}"
            + (f", components {list(self.components)}" if self.components else "")
        ]
        opts = ", ".join(f"{k}={v!r}" for k, v in case.model.options.items())
        lines.append(
            f"model: {case.model.kind}({opts})" + (f", stencil {case.model.stencil}" if case.model.stencil else "")
        )
        for path, da in zip(case.train.data, self.train):
            lines.append(f"train: {_rel(path, case.root)} {dict(da.sizes)}")
        for td in self.tasks:
            t = td.task
            lines.append(
                f"serve {t.name}: from {_rel(t.source, case.root)} {dict(td.init.sizes)}, "
                f"{td.slices} slices, boundary {t.boundary or 'from file/dirichlet'}, mode {t.options.mode}"
                + (", reference" if td.reference is not None else ", no reference")
                + (", baseline" if td.baseline is not None else "")
                + (f", charges {list(t.charges)}" if t.charges else "")
                + t.cadence.describe()
                + (f" (warning: {t.label}.steps is deprecated: write {t.label}.slices)" if t.deprecated_steps else "")
            )
        return lines


def _rel(path: Path, root: Path) -> str:
    try:
        return str(path.relative_to(root))
    except ValueError:
        return str(path)


def _same_spacing(a: tuple[float, ...], b: tuple[float, ...]) -> bool:
    return len(a) == len(b) and all(math.isclose(x, y, rel_tol=1e-6) for x, y in zip(a, b))


def _read(path: Path, case: Case, components: tuple[str, ...] | None, lazy: bool = False) -> xr.DataArray:
    """A field of the case, validated; ``lazy``: its values left in the file (a task with ``every > 1``)."""
    return read_field(path, case.field.variable, components=list(components) if components else None, lazy=lazy)


def _as_case_error(exc: LatticeDFTError, key: str) -> ConfigError:
    """An error about a keyword argument (``exc.key``) as an error about the case key ``key`` that set it."""
    return ConfigError(f"case.toml: {key}: {exc.problem}", key=key, problem=exc.problem)


def check_case(case: Case) -> CaseData:
    """Read and validate every field of the case (nothing is written)."""
    comps = case.field.components
    train: list[xr.DataArray] = []
    dims: tuple[str, ...] = ()
    spacing: tuple[float, ...] = ()
    for path in case.train.data:
        da = _read(path, case, comps)
        if comps is None:
            comps = component_labels(da)
            if comps is None and train:
                pass
        if not train:
            dims, spacing = lattice_dims(da), field_spacing(da, str(path))
            first = path
        else:
            if lattice_dims(da) != dims:
                raise InputError(f"{path}: lattice dims {lattice_dims(da)} differ from {dims} of {first}")
            if not _same_spacing(field_spacing(da, str(path)), spacing):
                raise InputError(f"{path}: spacing {field_spacing(da, str(path))} differs from {spacing} of {first}")
        try:
            as_lattice_field(da, source=str(path), boundary=case.train.boundary)
        except InputError as exc:
            if exc.key == "boundary":
                raise _as_case_error(exc, "train.boundary") from None
            raise
        train.append(da)
    if comps is None and any(component_labels(d) is not None for d in train):  # pragma: no cover - caught above
        raise InputError("train.data: some files have components and some do not")
    tasks = [_check_task(case, t, dims, spacing, comps) for t in case.serve]
    return CaseData(train=train, tasks=tasks, dims=dims, spacing=spacing, components=comps)


def _check_task(
    case: Case, t: ServeTask, dims: tuple[str, ...], spacing: tuple[float, ...], comps: tuple[str, ...] | None
) -> TaskData:
    lazy = t.cadence.thins and len(dims) > 1  # served slice by slice: the files are read where they are needed
    init = _read(t.source, case, comps, lazy)
    if lattice_dims(init) != dims:
        raise InputError(
            f"{t.source}: lattice dims {lattice_dims(init)} differ from the training data's {dims} ({t.label}.from)"
        )
    if not _same_spacing(field_spacing(init, str(t.source)), spacing):
        raise InputError(
            f"{t.source}: spacing {field_spacing(init, str(t.source))} differs from the training "
            f"data's {spacing}; a learned L_d serves on the lattice it was learned on"
        )
    nt = init.sizes[dims[0]]
    if nt < 2:
        raise InputError(f"{t.source}: holds {nt} time slice(s); expected at least the first two")
    slices = t.slices if t.slices is not None else nt
    key = f"{t.label}.{'steps' if t.deprecated_steps else 'slices'}"
    try:
        head = init.isel({dims[0]: slice(0, 2)}).compute() if lazy else init  # the boundary needs no values
        f = as_lattice_field(head, source=str(t.source), boundary=t.boundary, min_slices=2)
    except InputError as exc:
        if exc.key == "boundary":
            raise _as_case_error(exc, f"{t.label}.boundary") from None
        raise
    check_charges(t.charges, f, f"{t.label}.charges")
    if t.cadence.thins and t.charges:
        raise ConfigError(
            f"case.toml: {t.label}.every: the Noether charges ({t.label}.charges) are measured on the whole "
            "served field; give every = 1 or no charges",
            key=f"{t.label}.every",
        )
    if t.cadence.thins and case.train.learn.get("ensemble"):
        raise ConfigError(
            f"case.toml: {t.label}.every: an ensemble (train.ensemble) is served whole, every member on every "
            "slice; give every = 1 or no ensemble",
            key=f"{t.label}.every",
        )
    missing = missing_edges(f.boundary, f.dims, nt, slices)
    if missing:
        axis, kind = missing
        raise ConfigError(
            f"case.toml: {key}: {slices} slices need the {kind.title} strips along "
            f"{axis!r} on every slice, but {t.source.name} holds {nt}; give the whole field "
            "or fewer slices",
            key=key,
        )
    if t.options.box is not None and len(dims) != 1:
        raise ConfigError(f"case.toml: {t.label}.box: stopping at a box is for 1D trajectories only")
    ref: xr.DataArray | None
    if t.reference is not None:
        ref = _read(t.reference, case, comps, lazy)
        if ref.shape[1:] != init.shape[1:] or lattice_dims(ref) != dims:
            raise InputError(
                f"{t.reference}: shape {dict(ref.sizes)} does not match {t.source.name} "
                f"{dict(init.sizes)} beyond time ({t.label}.reference)"
            )
    else:
        ref = init if nt > 2 else None
    base = None
    if t.baseline is not None:
        base = _read(t.baseline, case, comps, lazy)
        if base.shape[1:] != init.shape[1:] or lattice_dims(base) != dims:
            raise InputError(
                f"{t.baseline}: shape {dict(base.sizes)} does not match {t.source.name} "
                f"{dict(init.sizes)} beyond time ({t.label}.baseline)"
            )
        if ref is None:
            raise ConfigError(f"case.toml: {t.label}.baseline: a baseline needs a reference to be scored against")
    inv = None
    if t.invariant is not None:
        try:
            inv = load_invariant(t.invariant, case.root)
        except ConfigError as exc:
            raise ConfigError(f"case.toml: {t.label}.{exc}") from None
    return TaskData(task=t, init=init, reference=ref, baseline=base, slices=slices, invariant=inv)


def train_model(case: Case, data: CaseData) -> tuple[Any, Any]:
    """Build the model of ``[model]`` and learn it from the training fields."""
    from ._learn import learn

    model = case.model.build(len(data.dims))
    try:
        if case.model.select is not None:
            model, report = _select_and_learn(case, data, model)
        else:
            log.info("training %s model on %d field(s) ...", case.model.kind, len(data.train))
            report = learn(
                model,
                data.train,
                boundary=case.train.boundary,
                progress=None,
                device=case.run.device,
                **case.train.learn,
            )
    except InputError as exc:
        if exc.key is not None and exc.key in case.train.learn:
            raise _as_case_error(exc, f"train.{exc.key}") from None
        raise
    log.info("%s", report.summary_line())
    if report.noise is not None:  # [train] noise = "auto" | "correct"
        nz = report.noise
        est = f"sigma {nz['sigma']:.2e} ({nz['relative']:.1e} of the amplitude)" if nz["resolved"] else "unresolved"
        done = f"{nz['method']}, rms shift {nz['shift']:.2e}" if nz["method"] != "none" else "none"
        log.info("noise (%s): %s; correction: %s", nz["mode"], est, done)
    log.debug("training device: %s", report.device)
    if model.ensemble_ is not None:  # [train] ensemble: serve every member, member 0 the full-data model
        model = model.ensemble_
        log.info(
            "ensemble: %d members on resamples of %d time windows", len(model), (report.ensemble or {}).get("windows")
        )
    if report.symmetries is not None:
        log.info("symmetries of the learned L_d over the training data (verdicts at tol 1e-9):")
        for line in report.symmetry_lines():
            log.info("  %s", line)
    log.debug("training report: %s", {k: v for k, v in report.to_dict().items() if k != "history"})
    for warning in report.warnings:  # a degenerate M, a poor fit (thresholds in docs/outputs.md)
        log.warning("%s", warning)
    return model, report


def _select_and_learn(case: Case, data: CaseData, model: AbstractLagrangian) -> tuple[Any, Any]:
    """``[model] select``: score the candidates by serving held-out data (table to the log); the chosen model,
    learned on all the data. With ``[train] ensemble`` the candidates are scored as single models and the chosen
    one is then learned as the ensemble's member 0 (its report keeps the selection table and warnings)."""
    from ._learn import learn
    from ._select import select

    learn_kw = dict(case.train.learn)
    ens = {k: learn_kw.pop(k) for k in ("ensemble", "ensemble_seed") if k in learn_kw}
    candidates = case.model.select if isinstance(case.model.select, str) else list(case.model.select or ())
    log.info("selecting a model by serving held-out data (select = %s) ...", "auto" if candidates == "auto" else "list")
    try:
        sel = select(model, data.train, candidates, boundary=case.train.boundary, device=case.run.device, **learn_kw)
    except InputError as exc:
        if exc.key == "candidates":
            raise ConfigError(f"case.toml: model.select: {exc.problem}", key="model.select") from None
        raise
    for line in sel.table_lines():
        log.info("  %s", line)
    log.info("selection: %s", sel.reason)
    chosen: Any = sel.model
    report = chosen.report_
    if ens.get("ensemble"):
        selection, warnings = report.selection, list(report.warnings)
        learn_kw["ridge"] = report.ridge
        report = learn(
            chosen, data.train, boundary=case.train.boundary, progress=None, device=case.run.device, **learn_kw, **ens
        )
        report.selection = selection
        report.warnings[:0] = [w for w in warnings if w not in report.warnings]
        chosen.report_ = report
    return chosen, report


@dataclass
class TaskOutcome:
    """A served task: its field, reference and the numbers that go into summary.json."""

    name: str
    field: xr.DataArray
    reference: xr.DataArray | None
    invariant: xr.DataArray | None
    record: dict[str, Any] = dataclasses.field(default_factory=dict)  # not the `field` attribute above
    #: ``charge_<name>(t)`` and ``energy(t)`` of the task's ``charges`` (None when it lists none)
    charges: xr.Dataset | None = None
    #: ``extrapolation(t, feature)`` of the served field against the model's training range (None without one)
    extrapolation: xr.DataArray | None = None
    #: An ensemble served: the mean and standard deviation over its members (None for a single model)
    mean: xr.DataArray | None = None
    std: xr.DataArray | None = None
    #: A task with an output cadence served into a staging folder: the part file holding its kept slices
    part: Path | None = None

    def spread(self, variable: str) -> dict[str, xr.DataArray]:
        """``{"<variable>_mean": ..., "<variable>_std": ...}`` for an ensemble, else empty."""
        if self.mean is None or self.std is None:
            return {}
        return {f"{variable}_mean": self.mean, f"{variable}_std": self.std}

    @property
    def complete(self) -> bool:
        return bool(self.record.get("complete"))

    def file_attrs(self, model_warnings: list[str]) -> dict[str, Any]:
        """Global attributes of ``<task>.nc`` saying whether the field is complete and what to distrust.

        ``latticedft_complete`` ("true"/"false"), ``latticedft_warnings`` (a JSON list of one-line warnings:
        the model's, then the task's) and, for an incomplete task, ``latticedft_stopped_at_slice`` (slices
        written) and ``latticedft_stop_reason``. (``latticedft_steps`` is written by ``write_task``.)
        """
        rec = self.record
        attrs: dict[str, Any] = {
            "latticedft_complete": "true" if self.complete else "false",
            "latticedft_warnings": json.dumps([*model_warnings, *rec.get("warnings", [])]),
        }
        if not self.complete:
            attrs["latticedft_stopped_at_slice"] = int(rec.get("slices", 0))
            attrs["latticedft_stop_reason"] = str(rec.get("stop_reason") or rec.get("reason") or "")
        return attrs


def _start(model: AbstractLagrangian, td: TaskData) -> tuple[xr.DataArray, str]:
    """The task's initial data and how they were taken (``[[serve]] start``): ``denoised`` asks for it, ``auto``
    denoises when training corrected noisy data."""
    from ._learn._noise import DENOISE_SLICES, denoised_start

    noise = (model.report_.noise if model.report_ is not None else None) or {}
    if td.task.start == "data" or (td.task.start == "auto" and noise.get("method", "none") == "none"):
        return td.init, "data"
    log.info(
        "serving %s from initial slices denoised by the learned DEL (first %d slices)", td.task.name, DENOISE_SLICES
    )
    return denoised_start(model, td.init), "denoised"


def serve_task(
    model: AbstractLagrangian, td: TaskData, device: str = "cpu", *, stage: Path | None = None, variable: str = "psi"
) -> TaskOutcome:
    """Serve one task (the model evaluated on ``device``); a Newton failure gives an incomplete outcome (with a
    warning), not an exception.

    A task with an output cadence (``[[serve]] every > 1``) served into a staging folder ``stage`` appends
    each kept slice, as it is served, to the part file ``stage/.<task>.nc.part`` (the field as ``variable``):
    the outcome's ``part`` names it, and ``write_task`` completes it into ``<task>.nc``.
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
    part = None
    if stage is not None and t.cadence.thins:
        part = PartFile(stage, t.name, variable, td.init, t.cadence.every)
    try:
        served = _serve(model, td, device, part)
    finally:
        if part is not None:
            part.close()
    result, pred = served.result, served.result.field
    rec = _record(served, td)
    inv = _invariant(served, td, rec)
    charges = task_charges(model, td, pred, rec)
    log.info("%s", _message(served, t, rec) + drift_text(rec))
    return TaskOutcome(
        name=t.name,
        field=pred,
        reference=td.reference,
        invariant=inv,
        record=rec,
        charges=charges,
        extrapolation=_kept(result.extrapolation, pred),
        mean=result.mean,
        std=result.std,
        part=part.path if part is not None else None,
    )


@dataclass
class _Served:
    """A task's serving run: its result, wall time, stop message, how it started and its meter (a cadence)."""

    result: Any
    wall: float
    stopped: str
    start: str
    meter: Any


def _serve(model: Any, td: TaskData, device: str, part: Callable[[int, np.ndarray], Any] | None) -> _Served:
    """Serve ``td`` with the task's options; with an output cadence, a meter measures every slice as it is
    served and hands each kept slice to ``part``."""
    from ._serve import serve

    t = td.task
    t0 = time.perf_counter()
    stopped = ""
    options = t.options.replace(progress=None, device=device)
    meter = None
    if t.cadence.thins:  # errors and the invariant measured on every slice as it is served
        from ._task_stream import TaskMeter

        meter = TaskMeter(td.reference, td.invariant, part)
    init, start = _start(model, td)
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
    return _Served(result=result, wall=wall, stopped=stopped, start=start, meter=meter)


def _record(served: _Served, td: TaskData) -> dict[str, Any]:
    """The task's record for summary.json, in its order: the result's numbers, then the errors against the
    reference and the baseline's, and an ensemble's calibration."""
    from ._serve import calibration
    from ._serve._ensemble import calibration_warning

    t, result, pred = td.task, served.result, served.result.field
    rec: dict[str, Any] = result.to_dict()
    rec["every"] = t.cadence.every
    rec["kept_slices"] = int(pred.sizes[pred.dims[0]])
    rec["stop_reason"] = None if result.complete else served.stopped
    for warning in result.warnings:  # the served field leaves the training range
        log.warning("task %s: %s", t.name, warning)
    rec["wall_time"] = served.wall
    rec["requested_slices"] = td.slices
    rec["from"] = t.source.name
    rec["start"] = served.start
    rec["reference"] = None
    if td.reference is not None:
        _errors(served, td, rec)
    if result.std is not None and td.reference is not None:  # an ensemble: is its spread an honest error bar?
        rec["calibration"] = calibration(pred, result.std, td.reference)
        bad = calibration_warning(rec["calibration"])
        if bad:
            rec["warnings"].append(bad)
            log.warning("task %s: %s", t.name, bad)
    return rec


def _errors(served: _Served, td: TaskData, rec: dict[str, Any]) -> None:
    """The errors against the task's reference, and the baseline's, into ``rec``."""
    from ._serve import compare

    assert td.reference is not None
    t, pred, meter = td.task, served.result.field, served.meter
    cmp = compare(pred, td.reference) if meter is None else meter.errors()
    rec.update(max_error=cmp["max_error"], rms_error=cmp["rms_error"], compared_slices=cmp["slices"])
    rec["reference"] = (t.reference or t.source).name
    if td.baseline is None:
        return
    if meter is None:
        b = compare(td.baseline, td.reference)
        b_same = compare(td.baseline.isel({pred.dims[0]: slice(0, cmp["slices"])}), td.reference)
    else:  # block by block: the files stay on disk
        from ._task_stream import compare_blocks

        b, b_same = (
            compare_blocks(td.baseline, td.reference),
            compare_blocks(td.baseline, td.reference, int(cmp["slices"])),
        )
    rec["baseline"] = {
        "file": t.baseline.name if t.baseline else None,
        "max_error": b["max_error"],
        "rms_error": b["rms_error"],
        "slices": b["slices"],
        "max_error_same_slices": b_same["max_error"],
        "rms_error_same_slices": b_same["rms_error"],
    }


def _invariant(served: _Served, td: TaskData, rec: dict[str, Any]) -> xr.DataArray | None:
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
        rec["invariant_drift"] = float(np.max(np.abs(finite - finite[0])) / abs(finite[0]))
    else:
        rec["invariant_drift"] = float(np.max(np.abs(finite - finite[0]))) if finite.size else None
    rec["invariant"] = t.invariant
    return _kept(inv, pred) if meter is not None else inv  # the file holds the kept slices


def _message(served: _Served, t: ServeTask, rec: dict[str, Any]) -> str:
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
    if t.cadence.thins:
        msg += f"{t.cadence.describe()}: {rec['kept_slices']} slices kept"
    if "max_error" in rec:
        msg += f", max error {rec['max_error']:.3e}, rms {rec['rms_error']:.3e}"
    if "baseline" in rec:
        msg += f" (baseline max {rec['baseline']['max_error_same_slices']:.3e})"
    if "invariant_drift" in rec and rec["invariant_drift"] is not None:
        msg += f", invariant drift {rec['invariant_drift']:.2e}"
    if "calibration" in rec and rec["calibration"]["slices"]:
        cal = rec["calibration"]
        msg += f", within 2/3 std {cal['within_2std']:.0%}/{cal['within_3std']:.0%}"
    return msg


def _kept(series: xr.DataArray | None, pred: xr.DataArray) -> xr.DataArray | None:
    """``series`` (over every slice served) on the slices ``pred`` keeps (its ``slice`` coordinate)."""
    if series is None or "slice" not in pred.coords:
        return series
    tdim = pred.dims[0]
    return series.isel({tdim: pred["slice"].values}).assign_coords({tdim: pred[tdim].values})
