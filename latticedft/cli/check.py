"""``latticedft check CASE``: validate case.toml, every data file and the limits (file names, memory) of a run;
print a summary; writes nothing."""

from __future__ import annotations

import argparse
import logging

from ._common import OK, add_case_arguments, checked_data, open_case, results_dir

log = logging.getLogger("latticedft")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "check", help="validate case.toml and the data; print a summary (writes nothing)", description=__doc__
    )
    add_case_arguments(p)


def main(args: argparse.Namespace, argv: list[str]) -> int:
    from .._results import held_by_another, leftovers

    case = open_case(args)
    dest = results_dir(args, case)
    data = checked_data(case, dest)
    for line in data.summary_lines(case):
        print(line)
    shown = args.out if getattr(args, "out", None) else case.results
    print(f"results: {shown} " + ("exists (run needs --overwrite)" if dest.exists() else "does not exist yet"))
    left = leftovers(dest)
    if left and held_by_another(dest):
        print(f"results: a run in progress is writing {', '.join(p.name for p in left)} (it holds the lock)")
    elif left:
        print(
            f"results: an interrupted run left {', '.join(p.name for p in left)}; the next run, serve or export "
            "cleans up (restoring earlier results parked there)"
        )
    log.info("case %s is valid", case.name)
    return OK
