"""``latticedft run CASE``: check, train, serve every task, export; publish CASE/results/."""

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
    refuse_existing,
    results_dir,
    run_device,
    set_threads,
    summary_head,
)

log = logging.getLogger("latticedft")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="check, train, serve every task and export (the whole case)", description=__doc__)
    add_case_arguments(p, overwrite=True)
    add_device_argument(p)
    _workers.add_argument(p)
    _resume.add_argument(p)


def main(args: argparse.Namespace, argv: list[str]) -> int:
    if args.resume:  # the model is in the killed run's stage: no training; split tasks are served split
        return _resume.resumed_run(args, argv)
    if (status := _workers.supervise(args, argv)) is not None:
        return status
    from .._results import hold_results, staged_results
    from .._run._resume import RESUME_FILE
    from .._run._split import check_split
    from ._work import finish, serve_into, train_into

    t0 = time.perf_counter()
    case = open_case(args)
    if _workers.is_helper():
        return _workers.train_only(case)
    dest = results_dir(args, case)
    with hold_results(dest):
        refuse_existing(dest, args)
        set_threads(case)
        data = checked_data(case, dest)
        check_split(data.tasks)  # more processes than planes: refused before training
        _workers.join(case.run.device)
        log.info("checked %s: %d training field(s), %d serving task(s)", case.name, len(data.train), len(data.tasks))
        with staged_results(dest, replace_foreign=False, keep=RESUME_FILE) as folder:
            case = run_device(case)  # in run.log too
            for line in data.summary_lines(case):
                log.debug("%s", line)
            model, train = train_into(folder, case, data, argv)
            if not check_split(data.tasks, model):  # a halo wider than a slab: the stage is discarded
                _workers.leave()  # no task is split: the other ranks are done, serving is rank 0's alone
            journal = _resume.journal_for(folder, "run", case, folder / "model.pt", False, train)
            tasks = serve_into(folder, case, data, model, argv, train, journal=journal)
            summary = summary_head(case, argv, "run")
            summary.update(train=train, tasks=tasks, wall_time=time.perf_counter() - t0)
            _workers.record_processes(summary)
            status = finish(folder, summary, strict=case.run.strict)
            _workers.leave()  # the other ranks are done (if they are still in the group): writing is rank 0's
            log.debug("all stages done in %.1f s; publishing %s", time.perf_counter() - t0, dest)
    log.info("results in %s (%.1f s)", dest, time.perf_counter() - t0)  # once published, never before
    return status
