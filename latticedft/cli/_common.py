"""Shared pieces of the subcommands: arguments, logging, the results folder, the summary.

Staging and publishing the results folder is :func:`latticedft._results.staged_results`, inside
:func:`latticedft._results.hold_results` (the lock); the checks made before anything is written are
:mod:`latticedft._run._guards`.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as _dt
import json
import logging
import os
import shlex
import sys
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .._errors import ConfigError, InputError, not_a_regular_file
from ._terminal import TqdmHandler

if TYPE_CHECKING:
    from .._case import Case

# The engine (torch, xarray) is imported inside the functions that need it: `latticedft --help` and usage
# errors answer without it.

log = logging.getLogger("latticedft")

#: exit statuses (SIGINT: 130, SIGTERM: 143, as a shell reports a process stopped by the signal)
OK, BAD_INPUT, INCOMPLETE, WARNED, INTERRUPTED, TERMINATED = 0, 1, 3, 4, 130, 143


class Terminated(BaseException):
    """Raised in the main thread by the command line's SIGTERM handler (like KeyboardInterrupt for SIGINT)."""


def add_case_arguments(p: argparse.ArgumentParser, *, overwrite: bool = False, out: bool = True) -> None:
    p.add_argument("case", help="case folder (holding case.toml)")
    if out:
        p.add_argument("--out", metavar="DIR", help="results folder (default: CASE/results)")
    p.add_argument(
        "--set",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        dest="overrides",
        help="override a case.toml key for this run (TOML value), e.g. model.orders=[2,2], "
        "train.max_time=10, serve.test.slices=31; repeatable",
    )
    if overwrite:
        p.add_argument("--overwrite", action="store_true", help="replace an existing results folder")
    g = p.add_mutually_exclusive_group()
    g.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors on stderr")
    g.add_argument("-v", "--verbose", action="store_true", help="debug messages on stderr too")


class _Formatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        msg = record.getMessage()
        if record.levelno >= logging.WARNING:
            return f"latticedft: {record.levelname.lower()}: {msg}"
        return msg


def setup_logging(args: argparse.Namespace) -> logging.Handler:
    """INFO (or WARNING with -q, DEBUG with -v) to the current stderr."""
    log.setLevel(logging.DEBUG)
    log.propagate = False
    handler = TqdmHandler(sys.stderr)  # lines through tqdm.write: a progress bar stays whole
    level = (
        logging.WARNING
        if getattr(args, "quiet", False)
        else (logging.DEBUG if getattr(args, "verbose", False) else logging.INFO)
    )
    handler.setLevel(level)
    handler.setFormatter(_Formatter())
    log.addHandler(handler)
    return handler


def detach(handler: logging.Handler | None) -> None:
    if handler is not None:
        log.removeHandler(handler)
        handler.close()


def command_line(argv: list[str]) -> str:
    return "latticedft " + " ".join(shlex.quote(a) for a in argv)


def add_device_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--strict",
        action="store_true",
        help="any warning (a poor or degenerate fit, extrapolation, an inaccurate task ...) makes the exit "
        "status 4, the results still published; the same as --set run.strict=true",
    )
    p.add_argument(
        "--device",
        metavar="DEVICE",
        help="where the model computes: cpu, cuda, cuda:N or auto (cuda when available); the same as "
        "--set run.device=DEVICE (default: [run] device, else cpu)",
    )


def open_case(args: argparse.Namespace) -> Case:
    from .._case import load_case

    device = getattr(args, "device", None)
    extra = [f"run.device={json.dumps(device)}"] if device is not None else []
    if getattr(args, "strict", False):
        extra.append("run.strict=true")
    case = load_case(args.case, [*args.overrides, *extra])
    log.debug("case %s, overrides %s", case.root, list(case.overrides))
    return case


def results_dir(args: argparse.Namespace, case: Case) -> Path:
    """The results folder (``--out`` or ``CASE/results``), checked: not a file, not the case folder or a folder
    holding it, not one of the case's inputs, nor holding or inside one. A symlinked results folder is
    followed: the real path is returned."""
    from .._results import check_destination
    from .._run import case_inputs

    out = getattr(args, "out", None)
    dest = Path(out) if out else case.results
    return check_destination(dest, inputs=case_inputs(case), root=case.root, what="--out" if out else "results folder")


def checked_data(case: Case, dest: Path, *, train: bool = True, serve: bool = True) -> Any:
    """Read and check every field of the case, then the limits (file names, model size, memory) of the stages
    the command runs (``train``, ``serve``); nothing is written."""
    from .._run import check_before_writing, check_case

    data = check_case(case)
    check_before_writing(case, data, dest, train=train, serve=serve)
    return data


def refuse_learning_overrides(case: Case, command: str) -> None:
    """``serve`` and ``export`` use the learned model: a ``--set model.*`` or ``train.*`` would be recorded
    without taking effect, so it is refused."""
    from .._case import parse_override

    for text in case.overrides:
        table = parse_override(text)[0][0]
        if table in ("model", "train"):
            raise ConfigError(
                f"--set {text.split('=', 1)[0].strip()}: [{table}] settings take effect in "
                f"`latticedft train` and `run`; `{command}` uses the learned model in "
                "results/model.pt"
            )


def refuse_changed_learning(case: Case, dest: Path, command: str) -> None:
    """``serve`` and ``export`` use the learned model: when case.toml's ``[model]`` or ``[train]`` differs from the
    one ``model.json`` records (an edit after training), the outputs would record settings that were not used, so
    the command is refused with the first difference."""
    try:
        record = json.loads((dest / "model.json").read_text(encoding="utf-8"))
        learned, overrides = record.get("config"), record.get("overrides") or []
    except (OSError, ValueError, AttributeError):
        return  # no record to compare with: the model file's own check reports a missing model.json
    if not isinstance(learned, dict):
        return
    # a key set by --set when the model was learned is expected to differ from the file: not an edit
    overridden = {str(o).split("=", 1)[0].strip() for o in overrides}
    for table in ("model", "train"):
        now, then = case.raw.get(table) or {}, learned.get(table) or {}
        changed = [
            k
            for k in sorted({*now, *then})
            if now.get(k, _ABSENT) != then.get(k, _ABSENT) and f"{table}.{k}" not in overridden
        ]
        if not changed:
            continue
        key = changed[0]
        raise ConfigError(
            f"{_show(case.root / 'case.toml')}: {table}.{key}: is {_shown(now.get(key, _ABSENT))} now but the model in "
            f"{_show(dest)}/model.pt was learned with {_shown(then.get(key, _ABSENT))}; `{command}` uses the learned "
            "model: run `latticedft train` (or `run`) to learn the edited case, or undo the edit"
        )


_ABSENT = object()


def _shown(value: Any) -> str:
    return "unset" if value is _ABSENT else json.dumps(value)


def refuse_existing(dest: Path, args: argparse.Namespace) -> None:
    if dest.exists() and not getattr(args, "overwrite", False):
        raise InputError(f"{_show(dest)}/ exists; use --overwrite to replace it")


def require_results(dest: Path, what: str) -> None:
    path = dest / what
    if path.is_file():
        return
    if os.path.lexists(path) and (path.exists() or not os.path.islink(path)):
        raise InputError(
            f"{_show(dest)}/{what}: is {not_a_regular_file(path)}; run `latticedft run` (or `train`) to write it again"
        )
    raise InputError(f"{_show(dest)}/{what}: not found; run `latticedft run` (or `train`) first")


def _show(p: Path) -> str:
    try:
        return os.path.relpath(p)
    except ValueError:  # pragma: no cover - other drive on Windows
        return str(p)


def set_threads(case: Case) -> None:
    """Bound torch's threads and the BLAS/OpenMP pools to ``[run] threads`` for the rest of the run."""
    from .._threads import limit_threads

    limit_threads(case.run.threads)
    log.debug("torch and BLAS/OpenMP threads: %d", case.run.threads)


def run_device(case: Case) -> Case:
    """The case with ``[run] device`` resolved: a CUDA request this machine cannot honour becomes ``"cpu"``
    with one warning (console and run.log); the device is logged."""
    from .._device import DeviceWarning, device_label, resolve_device

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DeviceWarning)
        where = resolve_device(case.run.device, key="run.device")
    for w in caught:
        log.warning("%s", w.message)
    log.debug("device: %s", device_label(where))
    if where.type == "cpu" and case.run.device != "cpu":
        return dataclasses.replace(case, run=dataclasses.replace(case.run, device="cpu"))
    return case


def summary_head(case: Case, argv: list[str], stage: str) -> dict[str, Any]:
    from .._results import versions

    return {
        "case": case.name,
        "case_path": str(case.root),
        "stage": stage,
        "command": command_line(argv),
        "versions": versions(),
        "overrides": list(case.overrides),
        "config": case.raw,
        "device": case.run.device,
        "finished": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
    }
