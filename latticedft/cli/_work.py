"""The work shared by ``run``, ``train``, ``serve`` and ``export``: write into a staging folder."""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

from tqdm.auto import tqdm

from .._case import Case
from .._pipeline import CaseData, TaskOutcome, serve_task, train_model
from .._results import (config_attrs, export_task, read_task, write_model, write_summary, write_task)
from ._common import INCOMPLETE, OK, command_line

log = logging.getLogger("latticedft")


def train_into(folder: Path, case: Case, data: CaseData, argv: list[str]) -> tuple[Any, dict[str, Any]]:
    """Learn the model and write ``model.pt`` + ``model.json``; returns (model, summary's train section)."""
    model, report = train_model(case, data)
    meta = {"command": command_line(argv), "overrides": list(case.overrides), "config": case.raw,
            "train_data": [str(p.relative_to(case.root)) if p.is_relative_to(case.root) else str(p)
                           for p in case.train.data]}
    record = write_model(folder, model, report, meta)
    train = {k: v for k, v in report.to_dict().items() if k != "history"}
    train["model_kind"] = model.kind
    train["model_sha256"] = record["sha256"]
    log.info("wrote model.pt and model.json")
    return model, train


def _clear_exports(folder: Path, name: str) -> None:
    pattern = re.compile(rf"^{re.escape(name)}(_(\d+|spacetime))?\.(pvd|vtr|vtp|png)$")
    for p in folder.iterdir():
        if pattern.match(p.name):
            p.unlink()


def serve_into(folder: Path, case: Case, data: CaseData, model: Any, argv: list[str]) -> dict[str, Any]:
    """Serve every task into ``<task>.nc`` and export it; returns the summary's tasks section."""
    tasks: dict[str, Any] = {}
    attrs = config_attrs(case.raw, case.overrides, command_line(argv))
    history = command_line(argv) + (f" (overrides: {', '.join(case.overrides)})" if case.overrides else "")
    for td in tqdm(data.tasks, desc="tasks", disable=None, leave=False):
        out: TaskOutcome = serve_task(model, td)
        path = write_task(folder, out.name, case.field.variable, out.field, out.reference, out.invariant,
                          attrs={**attrs, "latticedft_task": out.name,
                                 "latticedft_complete": "true" if out.complete else "false"},
                          history=history)
        out.record["file"] = path.name
        log.debug("wrote %s", path.name)
        out.record["exports"] = export_one(folder, case, out.name, data)
        tasks[out.name] = out.record
    return tasks


def export_one(folder: Path, case: Case, name: str, data: CaseData | None) -> list[str]:
    """Re-export ParaView files and the figure of one task from its ``<task>.nc``."""
    _clear_exports(folder, name)
    pred, ref, err = read_task(folder / f"{name}.nc", case.field.variable)
    files = export_task(folder, name, case.field.variable, pred, ref, err, paraview=case.export.paraview,
                        figures=case.export.figures, max_frames=case.export.max_frames,
                        train=data.train if data is not None else None, title=f"{case.name}: {name}")
    return [p.name for p in files]


def finish(folder: Path, summary: dict[str, Any]) -> int:
    incomplete = [n for n, t in summary.get("tasks", {}).items() if not t.get("complete")]
    status = INCOMPLETE if incomplete else OK
    summary["incomplete_tasks"] = incomplete
    summary["exit_status"] = status
    write_summary(folder, summary)
    if incomplete:
        log.warning("incomplete task(s): %s (partial fields written); exit status %d",
                    ", ".join(incomplete), status)
    return status
