"""The work shared by ``run``, ``train``, ``serve`` and ``export``, done inside a staging folder.

Exports: each task's files are those its last export wrote, as recorded in
``summary.json`` (``tasks.<name>.exports``); a new export of a task first
deletes exactly those files, so one task never deletes another's.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tqdm.std import tqdm  # not tqdm.auto: no ipywidgets warning in Jupyter (latticedft._progress)

from .._case import Case
from .._errors import InputError
from .._modelfile import load_model, save_model
from .._results import (
    config_attrs,
    export_task,
    json_safe,
    read_summary,
    read_task,
    write_model,
    write_summary,
    write_task,
)
from .._run import CaseData, TaskOutcome, case_calibration, serve_task, train_model
from .._run._split import skip_task
from ..io.exporters import remove_exports
from ._common import INCOMPLETE, OK, WARNED, command_line

if TYPE_CHECKING:
    from .._contract import AbstractLagrangian
    from .._run._resume import Journal

log = logging.getLogger("latticedft")

#: The calibration's trial model, beside model.pt (``[train] calibrate``).
TRIAL_FILE = "calibration.pt"
#: The runner-up candidate's trial model, beside it (``[train] calibrate`` with a runner-up in model selection).
RUNNER_FILE = "calibration_runner_up.pt"


def train_into(folder: Path, case: Case, data: CaseData, argv: list[str]) -> tuple[Any, dict[str, Any]]:
    """Learn the model and write ``model.pt`` + ``model.json``; returns (model, summary's train section)."""
    model, report = train_model(case, data)
    meta = {
        "command": command_line(argv),
        "overrides": list(case.overrides),
        "config": case.raw,
        "train_data": [
            str(p.relative_to(case.root)) if p.is_relative_to(case.root) else str(p) for p in case.train.data
        ],
    }
    record = write_model(folder, model, report, meta)
    log.info("wrote model.pt and model.json")
    measured = case_calibration(case, data, model, report)
    calibration, warnings = measured.law, measured.warnings
    if measured.trial is not None:  # the held-out trial model: its disagreement on each task enters the error bar
        save_model(measured.trial, folder / TRIAL_FILE)
    (folder / RUNNER_FILE).unlink(missing_ok=True)  # a runner-up of an earlier training is not this one's
    if measured.trial is not None and measured.runner is not None:  # its disagreement with the trial: a warning
        save_model(measured.runner, folder / RUNNER_FILE)
    for warning in warnings:  # too short for a held-out window, a failed noise-aware fit
        log.warning("%s", warning)
    for rep in {id(r): r for r in (report, getattr(model, "report_", None)) if r is not None}.values():
        rep.warnings.extend(warnings)  # in summary.json and every task file (model.json is written)
    train = {k: v for k, v in report.to_dict().items() if k != "history"}
    train["model_kind"] = model.kind
    train["model_sha256"] = record["sha256"]
    if calibration is not None:
        train["calibration"] = calibration
    return model, train


def recorded_exports(folder: Path) -> dict[str, list[str]]:
    """Task name -> the files its last export wrote, from ``folder/summary.json`` (empty when none)."""
    tasks = (read_summary(folder) or {}).get("tasks") or {}
    if not isinstance(tasks, dict):
        return {}
    return {
        str(name): [str(f) for f in (t.get("exports") or [])]
        for name, t in tasks.items()
        if isinstance(t, dict) and isinstance(t.get("exports"), list)
    }


def model_warnings_of(model: AbstractLagrangian, folder: Path) -> list[str]:
    """The warnings of the model's training: from its report, or (a model read from ``model.pt``) from the
    ``train`` section of ``folder/summary.json``."""
    report = getattr(model, "report_", None)
    if report is not None:
        return list(report.warnings)
    train = (read_summary(folder) or {}).get("train") or {}
    found = train.get("warnings") if isinstance(train, dict) else None
    return [str(w) for w in found] if isinstance(found, list) else []


def equation_attrs(model: AbstractLagrangian) -> dict[str, str]:
    """``latticedft_L_d``: the learned ``L_d`` in plain text, for a task file of a model that prints itself as an
    equation (:meth:`~latticedft.AbstractLagrangian.equation_text`; else none)."""
    text = model.equation_text()
    return {"latticedft_L_d": f"L_d = {text['L_d']}"} if text else {}


def calibration_of(folder: Path) -> dict[str, Any] | None:
    """The calibration law of the model in ``folder`` (``train.calibration`` of its ``summary.json``), or None."""
    train = (read_summary(folder) or {}).get("train") or {}
    found = train.get("calibration") if isinstance(train, dict) else None
    return found if isinstance(found, dict) else None


def trial_of(folder: Path, calibration: dict[str, Any] | None, name: str = TRIAL_FILE) -> AbstractLagrangian | None:
    """The calibration's trial model in ``folder`` (``calibration.pt``; ``name``: the runner-up's,
    ``calibration_runner_up.pt``, read only with a law that records the training disagreement), or None."""
    path = folder / name
    if calibration is None or (name == RUNNER_FILE and calibration.get("candidates") is None):
        return None
    return load_model(path) if path.is_file() else None


def serve_into(
    folder: Path,
    case: Case,
    data: CaseData,
    model: AbstractLagrangian,
    argv: list[str],
    train: dict[str, Any] | None = None,
    *,
    journal: Journal | None = None,
    resume: bool = False,
) -> dict[str, Any]:
    """Serve every task into ``<task>.nc`` and export it; returns the summary's tasks section. The error bars
    are calibrated by ``train["calibration"]`` (``train`` None: that of the folder's ``summary.json``).

    With a ``journal`` (tasks that write checkpoints) each task done is recorded in it; with ``resume`` the
    tasks it records as done are skipped and the task it was serving goes on from its checkpoint.
    """
    tasks: dict[str, Any] = {}
    attrs = config_attrs(case.raw, case.overrides, command_line(argv))
    history = command_line(argv) + (f" (overrides: {', '.join(case.overrides)})" if case.overrides else "")
    previous = recorded_exports(folder)
    model_warnings = model_warnings_of(model, folder)
    attrs.update(equation_attrs(model))
    calibration = calibration_of(folder) if train is None else train.get("calibration")
    trial = trial_of(folder, calibration)
    runner = trial_of(folder, calibration, RUNNER_FILE) if trial is not None else None
    owners: dict[str, str] = {}
    for td in tqdm(data.tasks, desc="tasks", disable=None, leave=False):
        if resume and journal is not None and td.task.name in journal.done:  # served before the run stopped
            tasks[td.task.name] = journal.done[td.task.name]
            owners.update({f: td.task.name for f in tasks[td.task.name].get("exports") or []})
            skip_task(model, td)  # the other processes skip it too
            continue
        out: TaskOutcome = serve_task(
            model,
            td,
            case.run.device,
            stage=folder,
            variable=case.field.variable,
            resume=resume,
            calibration=calibration,
            trial=trial,
            runner=runner,
        )
        path = write_task(
            folder,
            out.name,
            case.field.variable,
            out.field,
            out.reference,
            out.invariant,
            attrs={**attrs, "latticedft_task": out.name, **out.file_attrs(model_warnings)},
            history=history,
            charges=out.charges,
            baseline=td.baseline,
            steps=td.slices,
            extra={
                **({"extrapolation": out.extrapolation} if out.extrapolation is not None else {}),
                **out.spread(case.field.variable),
            },
            part=out.part,  # the kept slices, written as they were served: completed into <task>.nc
        )
        out.record.file = path.name
        log.debug("wrote %s", path.name)
        out.record.exports = export_one(folder, case, out.name, data, previous.get(out.name, ()), owners)
        tasks[out.name] = out.record.to_dict()
        if journal is not None:
            journal.task_done(out.name, json_safe(tasks[out.name]))
    if journal is not None:
        journal.close()
    return tasks


def export_one(
    folder: Path,
    case: Case,
    name: str,
    data: CaseData | None,
    previous: Iterable[str] = (),
    owners: dict[str, str] | None = None,
) -> list[str]:
    """Re-export one task from its ``<task>.nc`` in the case's formats; the names of the files written.

    ``previous`` are the files the task's last export wrote: they are deleted
    first, unless another task of this stage wrote them. ``owners`` (file ->
    task) collects the files of the stage's tasks; a file that two tasks would
    write is refused.
    """
    owners = {} if owners is None else owners
    remove_exports(folder, [f for f in previous if f not in owners])
    pred, ref, err = read_task(folder / f"{name}.nc", case.field.variable)
    files = [
        p.name
        for p in export_task(
            folder,
            name,
            case.field.variable,
            pred,
            ref,
            err,
            formats=case.export.formats,
            max_frames=case.export.max_frames,
            train=data.train if data is not None else None,
            title=f"{case.name}: {name}",
        )
    ]
    for f in files:
        if owners.get(f, name) != name:
            raise InputError(
                f"export file {f} of task {name!r} is also a file of task {owners[f]!r}; rename one of the tasks"
            )
        owners[f] = name
    return files


def finish(folder: Path, summary: dict[str, Any], *, strict: bool = False) -> int:
    """Write ``summary.json`` with the exit status and every warning of the stage (``warnings``: the
    training's, then each task's as ``"task <name>: ..."``); returns the exit status: 3 when a task stopped
    part-way, else with ``strict`` 4 when there is any warning, else 0."""
    incomplete = [n for n, t in summary.get("tasks", {}).items() if not t.get("complete")]
    train = summary.get("train")
    summary["warnings"] = [
        *((train.get("warnings") or []) if isinstance(train, dict) else []),
        *(f"task {n}: {w}" for n, t in summary.get("tasks", {}).items() for w in t.get("warnings") or []),
    ]
    status = INCOMPLETE if incomplete else (WARNED if strict and summary["warnings"] else OK)
    summary["incomplete_tasks"] = incomplete
    summary["strict"] = strict
    summary["exit_status"] = status
    write_summary(folder, summary)
    if incomplete:
        log.warning("incomplete task(s): %s (partial fields written); exit status %d", ", ".join(incomplete), status)
    elif status == WARNED:
        log.warning(
            "strict: %d warning(s), see above; exit status %d (the results are published)",
            len(summary["warnings"]),
            status,
        )
    return status
