"""``latticedft check CASE``: validate case.toml and every data file, print a summary; writes nothing."""

from __future__ import annotations

import argparse
import logging

from .._pipeline import check_case
from ._common import OK, add_case_arguments, open_case, results_dir

log = logging.getLogger("latticedft")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "check", help="validate case.toml and the data; print a summary (writes nothing)", description=__doc__
    )
    add_case_arguments(p)


def main(args: argparse.Namespace, argv: list[str]) -> int:
    case = open_case(args)
    data = check_case(case)
    for line in data.summary_lines(case):
        print(line)
    dest = results_dir(args, case)
    print(f"results: {dest} " + ("exists (run needs --overwrite)" if dest.exists() else "does not exist yet"))
    log.info("case %s is valid", case.name)
    return OK
