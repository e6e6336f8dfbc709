"""The test-only fault hook: the environment variable ``LATTICEDFT_FAULT`` makes a command fail at a named point.

Read only by :func:`_fault` and :func:`_fault_flag`, called where results are written (``latticedft._results``)
and where a cadenced task appends its kept slices (``latticedft._task_stream``); never set it otherwise.
"""

from __future__ import annotations

import errno
import os
import signal
from pathlib import Path

__all__ = ["FAULT_ENV", "FAULT_POINTS"]


FAULT_ENV = "LATTICEDFT_FAULT"


#: Named points of the fault hook: ``lock`` (the lock is held), ``stage`` (the staging folder exists),
#: ``write`` (each model, task or JSON file written into it), ``after-stage`` (the stage's work is done, not
#: yet published), ``mid-publish`` (between the two renames of the fallback, or after the swap before the
#: old results are deleted), ``slice`` (each kept slice appended to a task's part file, ``[[serve]] every``).
FAULT_POINTS = ("lock", "stage", "write", "after-stage", "mid-publish", "slice")


def _fault(point: str, path: Path | None = None) -> None:
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


def _fault_flag(flag: str) -> bool:
    return flag in [s.strip() for s in os.environ.get(FAULT_ENV, "").split(",")]
