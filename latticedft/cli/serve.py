"""``latticedft serve CASE``: serve every task with the learned results/model.pt, re-export, update results/."""

from __future__ import annotations

import argparse
import logging
import time

from . import _resume, _workers
from ._common import (
    add_case_arguments,
    add_device_argument,
    checked_data,
    open_case,
    refuse_changed_learning,
    refuse_learning_overrides,
    require_results,
    results_dir,
    run_device,
    set_threads,
    summary_head,
)

log = logging.getLogger("latticedft")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="serve every task with an existing results/model.pt", description=__doc__)
    add_case_arguments(p)
    add_device_argument(p)
    _workers.add_argument(p)
    _resume.add_argument(p)


def main(args: argparse.Namespace, argv: list[str]) -> int:
    from .._results import hold_results, load_verified_model, read_summary, staged_results
    from .._run._resume import RESUME_FILE
    from .._run._split import check_split
    from ._work import finish, serve_into

    if args.resume and _workers.starts_group(args):  # a bad --resume is refused before the processes start
        case = open_case(args)
        dest = results_dir(args, case)
        _resume.checkpointed_stage(dest, "serve", case, dest / "model.pt", say=False)
    if (status := _workers.supervise(args, argv)) is not None:
        return status
    t0 = time.perf_counter()
    case = open_case(args)
    refuse_learning_overrides(case, "serve")
    dest = results_dir(args, case)
    if _workers.is_helper():  # its slab of each split task
        return _workers.serve_only(case, dest, resume=args.resume)
    with hold_results(dest, keep=RESUME_FILE if args.resume else None):
        require_results(dest, "model.pt")
        model = load_verified_model(dest)
        refuse_changed_learning(case, dest, "serve")
        old = read_summary(dest) or {}
        set_threads(case)
        data = checked_data(case, dest, train=False)
        stage = _resume.checkpointed_stage(dest, "serve", case, dest / "model.pt") if args.resume else None
        if check_split(data.tasks, model):  # some task is split: the group serves it
            _workers.join("cpu", "serving")
        with staged_results(dest, copy_existing=True, adopt=stage, keep=RESUME_FILE) as folder:
            case = run_device(case)  # in run.log too
            log.debug("serving with %s", dest / "model.pt")
            journal = _resume.journal_for(folder, "serve", case, dest / "model.pt", args.resume)
            tasks = serve_into(folder, case, data, model, argv, journal=journal, resume=args.resume)
            summary = summary_head(case, argv, "serve")
            summary.update(train=old.get("train"), tasks=tasks, wall_time=time.perf_counter() - t0)
            _workers.record_processes(summary)
            status = finish(folder, summary, strict=case.run.strict)
        _workers.leave()
    log.info("results in %s (%.1f s)", dest, time.perf_counter() - t0)
    return status
