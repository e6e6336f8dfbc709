"""``latticedft export CASE``: rewrite the export files ([export] formats) from the existing results/<task>.nc."""

from __future__ import annotations

import argparse
import logging
import time

from .._errors import ConfigError
from ._common import (
    OK,
    add_case_arguments,
    open_case,
    refuse_changed_learning,
    refuse_learning_overrides,
    require_results,
    results_dir,
)

log = logging.getLogger("latticedft")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        description=__doc__,
        help="re-export the [export] formats (ParaView files, figures ...) from results/<task>.nc",
    )
    add_case_arguments(p)


def main(args: argparse.Namespace, argv: list[str]) -> int:
    from .._results import hold_results, load_verified_model, read_summary, staged_results, write_summary
    from ..io.exporters import EXPORTERS
    from ._work import export_one, recorded_exports

    t0 = time.perf_counter()
    case = open_case(args)
    refuse_learning_overrides(case, "export")
    if not case.serve:
        raise ConfigError("case.toml: serve: nothing to export: the case has no [[serve]] tasks")
    if not case.export.formats:
        raise ConfigError(
            f"case.toml: export.formats: nothing to export: every format is off (formats: {', '.join(EXPORTERS)})"
        )
    dest = results_dir(args, case)
    with hold_results(dest):
        for task in case.serve:
            require_results(dest, f"{task.name}.nc")
        if (dest / "model.pt").is_file():
            load_verified_model(dest)  # results whose model was changed after serving are not re-exported
            refuse_changed_learning(case, dest, "export")
        with staged_results(dest, copy_existing=True) as folder:
            summary = read_summary(folder) or {}
            previous = recorded_exports(folder)
            owners: dict[str, str] = {}
            for task in case.serve:
                files = export_one(folder, case, task.name, None, previous.get(task.name, ()), owners)
                log.info("exported %s: %s", task.name, ", ".join(files[:3]) + (" ..." if len(files) > 3 else ""))
                if task.name in summary.get("tasks", {}):
                    summary["tasks"][task.name]["exports"] = files
            if summary:
                summary.setdefault("exports", []).append(
                    {"command": " ".join(["latticedft", *argv]), "overrides": list(case.overrides)}
                )
                write_summary(folder, summary)
    log.info("exported into %s (%.1f s)", dest, time.perf_counter() - t0)
    return OK
