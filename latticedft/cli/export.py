"""``latticedft export CASE``: rewrite ParaView files and figures from the existing results/<task>.nc."""

from __future__ import annotations

import argparse
import logging
import time

from .._results import Staging, read_summary, write_summary
from ._common import (OK, add_case_arguments, attach_run_log, detach, open_case, require_results, results_dir)
from ._work import export_one

log = logging.getLogger("latticedft")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="re-export ParaView files and figures from results/<task>.nc",
                       description=__doc__)
    add_case_arguments(p)


def main(args: argparse.Namespace, argv: list[str]) -> int:
    t0 = time.perf_counter()
    case = open_case(args)
    dest = results_dir(args, case)
    for task in case.serve:
        require_results(dest, f"{task.name}.nc")
    staging = Staging(dest, copy_existing=True)
    handler = attach_run_log(staging.tmp)
    try:
        summary = read_summary(staging.tmp) or {}
        for task in case.serve:
            files = export_one(staging.tmp, case, task.name, None)
            log.info("exported %s: %s", task.name, ", ".join(files[:3]) + (" ..." if len(files) > 3 else ""))
            if task.name in summary.get("tasks", {}):
                summary["tasks"][task.name]["exports"] = files
        if summary:
            summary.setdefault("exports", []).append({"command": " ".join(["latticedft", *argv]),
                                                      "overrides": list(case.overrides)})
            write_summary(staging.tmp, summary)
        detach(handler)
        handler = None
        staging.publish()
        log.info("exported into %s (%.1f s)", dest, time.perf_counter() - t0)
    finally:
        detach(handler)
        staging.discard()
    return OK
