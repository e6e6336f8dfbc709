"""``--resume`` of ``serve`` and ``run``: take up the staging folder a killed checkpointed run left.

A run whose tasks write checkpoints (``[[serve]] checkpoint = K``) keeps a journal in its staging folder
(``latticedft._run._resume``). When the run is killed (or interrupted by SIGINT or SIGTERM) that folder stays
beside the results folder; ``--resume`` finds it, checks it against the case (one line naming the key that
changed), skips the tasks done, continues the task that was being served from its last checkpoint and
publishes the results as the uninterrupted run would have. Without ``--resume`` the next command removes it
and starts afresh.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .._errors import InputError

if TYPE_CHECKING:  # the CLI's help and usage errors load no engine (torch, xarray)
    from .._case import Case
    from .._run._resume import Journal

log = logging.getLogger("latticedft")

__all__ = ["add_argument", "checkpointed_stage", "journal_for", "resumed_run"]


def add_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the killed run of this case from its last checkpoint ([[serve]] checkpoint = K): the "
        "results equal those of an uninterrupted run",
    )


def checkpointed_stage(dest: Path, command: str, case: Case, model: Path | None = None, say: bool = True) -> Path:
    """The staging folder of ``dest`` that a killed checkpointed ``command`` left, checked against ``case`` and
    the model file (``model``; default the staging folder's ``model.pt``); a one-line InputError otherwise.
    ``say``: log which folder is taken up."""
    from .._results import leftovers
    from .._run._resume import RESUME_FILE, Journal

    found = [p for p in leftovers(dest) if (p / RESUME_FILE).is_file()]
    if not found:
        raise InputError.at(
            "--resume",
            f"no checkpointed run of {dest.name}/ to resume (a run whose tasks set [[serve]] checkpoint = K leaves "
            "one when it is killed); run without --resume",
        )
    stage = max(found, key=lambda p: p.stat().st_mtime)
    Journal.read(stage).check(command, case, model or stage / "model.pt")
    if say:
        log.info("resuming the checkpointed run in %s", stage.name)
    return stage


def journal_for(folder: Path, command: str, case: Case, model: Path, resume: bool, train: Any = None) -> Journal | None:
    """The stage's journal: the one read back with ``resume``, else a new one when a task writes checkpoints
    (None when none does)."""
    from .._run._resume import Journal

    if resume:
        return Journal.read(folder)
    if not any(t.options.checkpoint for t in case.serve):
        return None
    return Journal.begin(folder, command, case, model, train)


def resumed_run(args: argparse.Namespace, argv: list[str]) -> int:
    """``latticedft run CASE --resume``: the model was learned and written by the killed run; serve on (with
    ``--workers N`` or under ``torchrun``, each task that can be split served split, as ``serve --resume``)."""
    from .._results import hold_results, load_verified_model, staged_results
    from .._run._resume import RESUME_FILE
    from .._run._split import check_split
    from . import _workers
    from ._common import checked_data, open_case, results_dir, run_device, set_threads, summary_head
    from ._work import finish, serve_into

    if _workers.starts_group(args):  # a bad --resume is refused before the processes start
        case = open_case(args)
        checkpointed_stage(results_dir(args, case), "run", case, say=False)
    if (status := _workers.supervise(args, argv)) is not None:
        return status
    t0 = time.perf_counter()
    case = open_case(args)
    dest = results_dir(args, case)
    if _workers.is_helper():  # its slab of each split task, with the model of the stage rank 0 takes up
        return _helper(case, dest)
    with hold_results(dest, keep=RESUME_FILE):
        set_threads(case)
        data = checked_data(case, dest, train=False)
        stage = checkpointed_stage(dest, "run", case)
        with staged_results(dest, adopt=stage, keep=RESUME_FILE) as folder:
            case = run_device(case)
            model = load_verified_model(folder)
            if check_split(data.tasks, model):  # some task is split: the group serves it
                _workers.join("cpu", "serving")
            journal = journal_for(folder, "run", case, folder / "model.pt", True)
            assert journal is not None
            tasks = serve_into(folder, case, data, model, argv, journal.data["train"], journal=journal, resume=True)
            summary = summary_head(case, argv, "run")
            summary.update(train=journal.data["train"], tasks=tasks, wall_time=time.perf_counter() - t0)
            _workers.record_processes(summary)
            status = finish(folder, summary, strict=case.run.strict)
        _workers.leave()
    log.info("results in %s (%.1f s)", dest, time.perf_counter() - t0)
    return status


def _helper(case: Case, dest: Path) -> int:
    """A rank other than 0 of ``run --resume``: serve its slab of each split task with the model of the
    checkpointed run's stage. Where that stage cannot be taken up, rank 0 says why (or, when rank 0 has
    already published it, no task was split and there is nothing to serve)."""
    from . import _workers
    from ._common import OK

    try:
        stage = checkpointed_stage(dest, "run", case, say=False)
    except InputError:
        return OK
    return _workers.serve_only(case, stage, resume=True)
