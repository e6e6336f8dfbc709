"""The ``latticedft`` command line (stdlib argparse; one module per subcommand).

``main(argv)`` returns the exit status: 0 when every stage and task
completed, 1 for bad input or results that cannot be written (a one-line
message on stderr, nothing published), 2 for a usage error (argparse: an
unknown command or option), 3 when a serving task stopped part-way (its
partial field is still written and the results are published), 130 on
SIGINT (Ctrl-C) and 143 on SIGTERM (one line; nothing published unless the
signal came after the publishing step).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading
from pathlib import Path

from .._atomic import fault
from .._errors import LatticeDFTError
from . import check as _check
from . import export as _export
from . import info as _info
from . import new as _new
from . import run as _run
from . import serve as _serve
from . import train as _train
from ._common import BAD_INPUT, INTERRUPTED, TERMINATED, Terminated, _show, detach, setup_logging
from ._terminal import loading_note

__all__ = ["main", "build_parser"]

SUBCOMMANDS = {
    "run": _run,
    "check": _check,
    "train": _train,
    "serve": _serve,
    "export": _export,
    "info": _info,
    "new": _new,
}

#: The exit statuses, for ``--help``.
EXIT_STATUSES = (
    "exit status: 0 every stage and task completed; 1 bad input (one line names the key or file; nothing "
    "written); 2 a usage error (an unknown command or option); 3 a serving task stopped part-way (its "
    "partial field is written); 4 with --strict ([run] strict): a warning (poor fit, extrapolation, an "
    "inaccurate task ...), results published; 130 interrupted (Ctrl-C, SIGINT) and 143 terminated (SIGTERM): nothing "
    "published."
)


def _plain(text: str | None) -> str | None:
    """Help text without reStructuredText markup: ``code`` -> code."""
    return None if text is None else text.replace("``", "")


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__

    parser = argparse.ArgumentParser(
        prog="latticedft",
        description="Learn a discrete field theory from lattice data and serve it (H. Qin, Sci. Rep. 10, "
        "19329, 2020). Runs case folders: CASE/case.toml, CASE/data/ -> CASE/results/. "
        "Start with: latticedft new NAME; latticedft run NAME.",
        epilog=EXIT_STATUSES,
    )
    parser.add_argument("--version", action="version", version=f"latticedft {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for mod in SUBCOMMANDS.values():
        mod.add_parser(sub)
    for p in sub.choices.values():  # module docstrings as descriptions: no markup in --help
        p.description = _plain(p.description)
        p.epilog = p.epilog or EXIT_STATUSES
        for action in p._actions:
            action.help = _plain(action.help)
    for choice in sub._choices_actions:
        choice.help = _plain(choice.help)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (the process's own command line, run in a process group,
    ends the process here: :func:`latticedft.cli._workers.end_process`)."""
    entry = argv is None  # the process's own command line: its outcome is final once main returns
    status = _main(argv)
    if entry:
        from . import _workers

        return _workers.end_process(status)
    return status


def _error(text: str) -> None:
    """The one-line error on stderr; in a rank that ``--workers`` started, also into the file it names
    (``latticedft.cli._workers.ERROR_FILE``), so that the launcher says an error all ranks met once."""
    line = f"latticedft: error: {text}"
    print(line, file=sys.stderr)
    path = os.environ.get("LATTICEDFT_ERROR_FILE")
    if path:
        with contextlib.suppress(OSError):
            Path(path).write_text(line + "\n")


def _main(argv: list[str] | None) -> int:
    """The command line's work and its exit status; errors, interrupts and signals answered as documented."""
    entry = argv is None  # the process's own command line: its outcome is final once main returns
    argv = list(sys.argv[1:] if argv is None else argv)
    previous = _on_sigterm()  # first of all: a signal while the engine loads is answered like any other
    handler = None
    published: list[Path] = []
    n_published = 0
    try:
        parser = build_parser()
        try:
            args = parser.parse_args(argv)
        except SystemExit as exc:  # --help, --version, usage errors
            return int(exc.code or 0) if not isinstance(exc.code, str) else 2
        handler = setup_logging(args)
        # the engine is imported only now (--help and usage errors answer without it); on a terminal a first
        # line shows at once while it loads
        with loading_note(sys.stderr, show=args.command != "new" and not getattr(args, "quiet", False)):
            fault("loading")
            from .. import _results

            if args.command != "new":
                from .. import _case  # noqa: F401  (torch)
        published = _results.published
        n_published = len(published)
        return int(SUBCOMMANDS[args.command].main(args, argv))
    except LatticeDFTError as exc:
        _error(" ".join(str(exc).split()))
        return BAD_INPUT
    except OSError as exc:  # reading or writing outside a staged stage: the path and the reason
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        _error(f"{where}{exc.strerror or ' '.join(str(exc).split())}")
        return BAD_INPUT
    except BrokenPipeError:  # e.g. `latticedft info CASE | head`: stop quietly
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    except (KeyboardInterrupt, Terminated) as exc:
        what = "interrupted" if isinstance(exc, KeyboardInterrupt) else "terminated (SIGTERM)"
        done = published[n_published:]
        print(
            f"latticedft: {what}; "
            + (f"after publishing {', '.join(_show(p) for p in done)}" if done else "nothing was published"),
            file=sys.stderr,
        )
        return INTERRUPTED if isinstance(exc, KeyboardInterrupt) else TERMINATED
    finally:
        if entry:  # the outcome is decided and said: a late Ctrl-C or SIGTERM no longer changes it
            _ignore_signals()
            fault("exit")
        elif previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if handler is not None:
            detach(handler)


def _ignore_signals() -> None:
    if threading.current_thread() is threading.main_thread():
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, signal.SIG_IGN)


def _raise_terminated(signum: int, frame: object) -> None:
    raise Terminated()


def _on_sigterm() -> signal._HANDLER:
    """SIGTERM raises :class:`Terminated` in the main thread, so a stage is cleaned up as on Ctrl-C; returns
    the previous handler (None when not in the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    previous = signal.getsignal(signal.SIGTERM)
    signal.signal(signal.SIGTERM, _raise_terminated)
    return previous if previous is not None else signal.SIG_DFL


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
