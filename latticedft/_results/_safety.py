"""Keeping a user's files safe while results are written.

One-line write errors, fsync, the atomic exchange of two folders, deferred signals and the
test-only fault hook.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import logging
import os
import shutil
import signal
import stat
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from .._atomic import FAULT_ENV as FAULT_ENV
from .._atomic import FAULT_POINTS as FAULT_POINTS
from .._atomic import fault as _fault
from .._atomic import fault_flag as _fault_flag
from .._errors import LatticeDFTError

log = logging.getLogger("latticedft")


class ResultsError(LatticeDFTError):
    """The results folder cannot be written, is held by another run, or is not a place for results."""


def _show(p: str | os.PathLike[str]) -> str:
    try:
        rel = os.path.relpath(p)
    except ValueError:  # pragma: no cover - another drive on Windows
        return str(p)
    return rel if not rel.startswith(".." + os.sep + ".." + os.sep) else str(p)


def _rmtree(path: Path) -> None:
    """Delete ``path`` (a folder, a file or a link), making read-only folders writable on the way."""

    def retry(func: Callable[..., Any], p: str, _exc: Any) -> None:
        try:
            os.chmod(os.path.dirname(p), stat.S_IRWXU)
            if os.path.isdir(p) and not os.path.islink(p):
                os.chmod(p, stat.S_IRWXU)
            func(p)
        except OSError:
            pass

    if os.path.islink(path) or os.path.isfile(path):
        with contextlib.suppress(OSError):
            os.unlink(path)
    elif os.path.isdir(path):
        shutil.rmtree(path, onerror=retry)  # onerror: Python 3.11 (onexc from 3.12)


def _fsync_tree(folder: Path) -> None:
    """Flush every file under ``folder`` and the folders themselves to disk before they are published."""
    for root, _dirs, files in os.walk(folder):
        for name in files:
            try:
                fd = os.open(os.path.join(root, name), os.O_RDONLY)
            except OSError:
                continue
            try:
                os.fsync(fd)
            except OSError:
                pass
            finally:
                os.close(fd)
        _fsync_dir(Path(root))


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


_RENAME_EXCHANGE = 2


_AT_FDCWD = -100


_renameat2: Any = None


def _exchange(a: Path, b: Path) -> bool:
    """Swap ``a`` and ``b`` atomically (Linux ``renameat2(RENAME_EXCHANGE)``); False where unavailable."""
    global _renameat2
    if _fault_flag("no-exchange") or not sys.platform.startswith("linux"):
        return False
    if _renameat2 is None:
        try:
            fn = ctypes.CDLL(None, use_errno=True).renameat2
            fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
            fn.restype = ctypes.c_int
            _renameat2 = fn
        except (AttributeError, OSError):  # glibc < 2.28, musl, ...
            _renameat2 = False
    if _renameat2 is False:
        return False
    if _renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOTSUP):  # not on this file system
        return False
    raise OSError(code, os.strerror(code), str(b))


@contextmanager
def _signals_deferred() -> Iterator[None]:
    """SIGINT/SIGTERM arriving in the block are delivered when it ends (the block is never cut in two)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    sigs = [s for s in (signal.SIGINT, signal.SIGTERM) if s is not None]
    old = {s: signal.getsignal(s) for s in sigs}
    for s in sigs:
        signal.signal(s, lambda signum, _frame: pending.append(signum))
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)
        for signum in dict.fromkeys(pending):
            signal.raise_signal(signum)


@contextmanager
def _writing(path: Path) -> Iterator[None]:
    """Writing the file ``path``: a library's failure (netCDF/HDF5, torch's zip writer, VTK ...) becomes an
    OSError naming it; the library's own input errors pass unchanged."""
    _fault("write", path)
    try:
        yield
    except LatticeDFTError:
        raise
    except OSError as exc:
        if not exc.filename:
            raise OSError(exc.errno, exc.strerror or " ".join(str(exc).split())[:160], str(path)) from exc
        raise
    except Exception as exc:
        reason = f"{type(exc).__name__}: {' '.join(str(exc).split())[:160]}"
        raise OSError(errno.EIO, reason, str(path)) from exc


def _os_error_line(exc: BaseException, tmp: Path | None, dest: Path) -> str:
    """One line naming the path (as it would be in ``dest``) and the reason; notes a full disk."""
    path = getattr(exc, "filename", None)
    shown = _show(dest)
    if path:
        text = str(path)
        if tmp is not None and text.startswith(str(tmp)):
            text = str(dest) + text[len(str(tmp)) :]
        shown = _show(text)
    reason = getattr(exc, "strerror", None) or " ".join(str(exc).split())[:160] or type(exc).__name__
    if isinstance(exc, shutil.Error):  # copytree: a list of (source, target, reason)
        first = exc.args[0][0] if exc.args and isinstance(exc.args[0], list) and exc.args[0] else None
        reason = str(first[2]) if first else reason
    line = f"cannot write {shown}: {reason}"
    try:
        free = shutil.disk_usage(dest.parent).free
        if getattr(exc, "errno", None) not in (errno.EACCES, errno.EPERM, errno.EROFS) or free < 2**20:
            line += f" ({_size(free)} free on that disk)"
    except OSError:
        pass
    return line + f"; nothing was published, {_show(dest)} is as it was"


def _size(n: float) -> str:
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} bytes"


def _close(handler: logging.Handler | None) -> None:
    if handler is not None:
        log.removeHandler(handler)
        handler.close()
