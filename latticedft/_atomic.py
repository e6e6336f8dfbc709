"""Writing a file so that it is either complete or absent: a temporary file beside it, then a rename; and the
test hook that injects faults (signals, kills, write errors) at named points of a command."""

from __future__ import annotations

import errno
import os
import signal
import uuid
from pathlib import Path

__all__ = ["FAULT_ENV", "FAULT_POINTS", "fault", "fault_flag", "write_bytes_atomic", "write_text_atomic"]

FAULT_ENV = "LATTICEDFT_FAULT"


#: Named points of the fault hook: ``loading`` (the command line loads the engine), ``lock`` (the lock is
#: held), ``stage`` (the staging folder exists), ``write`` (each model, task or JSON file written into it),
#: ``after-stage`` (the stage's work is done, not yet published), ``mid-publish`` (between the two renames of
#: the fallback, or after the swap before the old results are deleted), ``slice`` (each kept slice appended
#: to a task's part file, ``[[serve]] every``), ``checkpoint`` (each checkpoint of a task written, ``[[serve]]
#: checkpoint``), ``exit`` (the command's outcome is said, the process is about to exit).
FAULT_POINTS = ("loading", "lock", "stage", "write", "after-stage", "mid-publish", "slice", "checkpoint", "exit")


def fault(point: str, path: Path | None = None) -> None:
    """The test hook: ``LATTICEDFT_FAULT="action:point,..."`` does ``action`` (``kill``, ``term``, ``int``,
    ``stop``: that signal to this process; ``enospc``, ``eacces``: that OSError for ``path``) at ``point``."""
    spec = os.environ.get(FAULT_ENV)
    if not spec:
        return
    for item in spec.split(","):
        action, _, where = item.strip().partition(":")
        if where != point:
            continue
        if action == "kill":
            os.kill(os.getpid(), signal.SIGKILL)
        elif action in ("term", "int", "stop"):
            signal.raise_signal({"term": signal.SIGTERM, "int": signal.SIGINT, "stop": signal.SIGSTOP}[action])
        elif action in ("enospc", "eacces"):
            code = errno.ENOSPC if action == "enospc" else errno.EACCES
            raise OSError(code, os.strerror(code), str(path) if path is not None else None)


def fault_flag(flag: str) -> bool:
    """True when the test hook's ``LATTICEDFT_FAULT`` names ``flag`` (a switch, not a point)."""
    return flag in [s.strip() for s in os.environ.get(FAULT_ENV, "").split(",")]


def write_text_atomic(target: Path, text: str) -> Path:
    """Write ``text`` to ``target`` through ``.<name>.<12 hex>.tmp`` beside it and ``os.replace``.

    The temporary file is removed when writing fails (or is interrupted); ``target`` keeps its old
    content until the rename. Returns ``target``.
    """
    target = Path(target)
    tmp = target.parent / f".{target.name}.{uuid.uuid4().hex[:12]}.tmp"
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return target


def write_bytes_atomic(target: Path, data: bytes) -> Path:
    """Write ``data`` to ``target`` as :func:`write_text_atomic` writes text, the temporary file synced to disk
    before the rename (a checkpoint survives a crash of the machine too). Returns ``target``."""
    target = Path(target)
    tmp = target.parent / f".{target.name}.{uuid.uuid4().hex[:12]}.tmp"
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return target
