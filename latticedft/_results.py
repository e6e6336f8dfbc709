"""Results of a run: the staging folder, model files, task files, exports, summary.

Everything is first written into a temporary folder beside the destination
(``CASE/results.tmp-XXXXXXXXXX``) that replaces ``CASE/results/`` in one atomic
step only when the stage succeeded, so a failed, interrupted or killed run
never leaves a half-written ``results/`` and never loses the previous one.
:func:`staged_results` is the one place that stages and publishes; every
command uses it, inside :func:`hold_results`.

Guarantees (docs/guarantees.md):

- A run writes only its results folder ``DEST`` and staging folders beside it
  named ``DEST.tmp-<10 hex digits>`` (and, where the atomic swap is not
  available, ``DEST.tmp-old-<10 hex digits>`` for a moment).
- Publishing swaps the staging folder and ``DEST`` with one
  ``renameat2(RENAME_EXCHANGE)`` (Linux); elsewhere ``DEST`` is renamed aside
  and the staging folder renamed in its place. A crash at any point leaves
  the old results or the new ones at ``DEST`` (with the two-rename fallback:
  or the old ones parked beside it, which the next run puts back).
- One run per results folder's parent at a time: :func:`hold_results` takes a
  non-blocking ``flock`` on the parent folder itself (no lock file), and,
  once it holds it, removes the staging folders of killed runs and restores
  parked results (one warning line).
- SIGINT and SIGTERM during the publishing step are deferred until it is done.

Test hook: the environment variable ``LATTICEDFT_FAULT`` (read only here, for
the fault-injection tests; never set it otherwise) lists comma-separated
``ACTION:POINT`` items: ACTION is ``kill`` (SIGKILL), ``term`` (SIGTERM),
``int`` (SIGINT), ``stop`` (SIGSTOP), ``enospc`` or ``eacces`` (raise that
OSError), POINT one of :data:`FAULT_POINTS`; the item ``no-exchange`` forces
the two-rename fallback of the publishing step.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import hashlib
import json
import logging
import math
import os
import platform
import re
import shutil
import signal
import stat
import sys
import threading
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from ._errors import InputError, LatticeDFTError, ModelFileError

__all__ = [
    "FAULT_ENV",
    "FAULT_POINTS",
    "read_task_series",
    "RUN_LOG",
    "ResultsError",
    "Staging",
    "check_destination",
    "export_task",
    "hold_results",
    "json_safe",
    "leftovers",
    "load_verified_model",
    "published",
    "read_summary",
    "read_task",
    "staged_results",
    "versions",
    "write_model",
    "write_summary",
    "write_task",
]

log = logging.getLogger("latticedft")
RUN_LOG = "run.log"
FAULT_ENV = "LATTICEDFT_FAULT"
#: Named points of the fault hook: ``lock`` (the lock is held), ``stage`` (the staging folder exists),
#: ``write`` (each model, task or JSON file written into it), ``after-stage`` (the stage's work is done, not
#: yet published), ``mid-publish`` (between the two renames of the fallback, or after the swap before the
#: old results are deleted).
FAULT_POINTS = ("lock", "stage", "write", "after-stage", "mid-publish")
_MARKER = "summary.json"  # every published results folder holds one

#: The results folders this process published, in order (the command line says whether an interrupted
#: command had already published).
published: list[Path] = []


class ResultsError(LatticeDFTError):
    """The results folder cannot be written, is held by another run, or is not a place for results."""


# -- the fault hook (tests only) -----------------------------------------------------------------------------
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


# -- small file-system helpers -------------------------------------------------------------------------------
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


# -- where results may go --------------------------------------------------------------------------------------
def check_destination(
    dest: str | os.PathLike[str], *, inputs: Sequence[Path] = (), root: Path | None = None, what: str = "results folder"
) -> Path:
    """The real path of ``dest`` (a symlinked ``dest`` is followed), after checking that results may go there.

    Refused (:class:`ResultsError`): a ``dest`` that is an existing non-folder, that is or contains the case
    folder ``root``, or that is, contains or lies inside one of ``inputs`` (files and folders the case
    reads). A ``dest`` inside ``root`` (``CASE/results``, ``CASE/results2``) is fine.
    """
    real = Path(os.path.realpath(dest))
    shown = f"{what} {_show(dest)}" + (f" (a link to {_show(real)})" if os.path.islink(dest) else "")
    why = "; results replace their folder as a whole, so they must go elsewhere (the default is CASE/results)"
    if root is not None:
        r = Path(os.path.realpath(root))
        if real == r or r.is_relative_to(real):
            verb = "is" if real == r else "contains"
            raise ResultsError(f"{shown}: {verb} the case folder {_show(root)}{why}")
    real_inputs = [(p, Path(os.path.realpath(p))) for p in inputs]
    matches = (
        [("is", p, r) for p, r in real_inputs if real == r]  # the most telling relation first
        + sorted(
            [("lies inside", p, r) for p, r in real_inputs if real.is_relative_to(r) and real != r],
            key=lambda m: -len(m[2].parts),
        )
        + [("contains", p, r) for p, r in real_inputs if r.is_relative_to(real) and real != r]
    )
    if matches:
        verb, p, r = matches[0]
        kind = "input folder" if r.is_dir() else "input file"
        raise ResultsError(f"{shown}: {verb} the case's {kind} {_show(p)}{why}")
    if real.exists() and not real.is_dir():
        raise ResultsError(f"{shown}: exists and is not a folder; results go into a folder of their own")
    return real


def _staging_re(name: str) -> re.Pattern[str]:
    return re.compile(rf"^{re.escape(name)}\.tmp-(old-)?[0-9a-f]{{10}}$")


def leftovers(dest: str | os.PathLike[str]) -> list[Path]:
    """Staging folders of ``dest`` left beside it (by runs that were killed, or by a run in progress)."""
    dest = Path(os.path.realpath(dest))
    if not dest.parent.is_dir():
        return []
    pattern = _staging_re(dest.name)
    return sorted(p for p in dest.parent.iterdir() if pattern.match(p.name))


def _recover(dest: Path) -> None:
    """With the lock held: put parked results back when ``dest`` is missing, delete dead staging folders."""
    left = leftovers(dest)
    if not left:
        return
    parked = [p for p in left if ".tmp-old-" in p.name and p.is_dir()]
    restored = None
    with _signals_deferred():
        if parked and not os.path.lexists(dest):
            restored = max(parked, key=lambda p: p.stat().st_mtime)
            os.rename(restored, dest)
            _fsync_dir(dest.parent)
    for p in left:
        if p != restored:
            _rmtree(p)
    names = ", ".join(p.name for p in left)
    if restored is not None:
        log.warning(
            "an interrupted run left %s beside %s: restored the earlier results from %s and removed the rest",
            names,
            _show(dest),
            restored.name,
        )
    else:
        log.warning(
            "an interrupted run left %s beside %s: removed (%s is as the last completed run left it)",
            names,
            _show(dest),
            _show(dest),
        )


# -- the lock ------------------------------------------------------------------------------------------------
_held: dict[str, list[int]] = {}  # real path of a locked parent folder -> [fd, depth]


def _make_parents(folder: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; the folders created, innermost first."""
    created: list[Path] = []
    p = folder
    while not p.exists() and p != p.parent:
        created.append(p)
        p = p.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ResultsError(f"cannot create the folder {_show(folder)}: {exc.strerror or exc}") from None
    return created


@contextmanager
def hold_results(dest: str | os.PathLike[str]) -> Iterator[Path]:
    """Hold the results folder ``dest`` for one command: the lock, then recovery from killed runs.

    Takes a non-blocking ``flock`` on ``dest``'s parent folder (a folder file descriptor: nothing is
    created beside the results) and keeps it until the block ends; another process holding it gives a
    :class:`ResultsError` ("another latticedft run holds ..."). Then staging folders left by killed runs are
    removed and, when ``dest`` is missing, results parked by an interrupted publishing step are put back (one
    warning). Yields the real path of ``dest``. Re-entrant within a process.
    """
    dest = Path(os.path.realpath(dest))
    parent = dest.parent
    key = str(parent)
    if key in _held:
        _held[key][1] += 1
        try:
            yield dest
        finally:
            _held[key][1] -= 1
        return
    created = _make_parents(parent)
    n_published = len(published)
    fd = _lock(parent)
    _held[key] = [fd, 1]
    try:
        _fault("lock", dest)
        _recover(dest)
        yield dest
    finally:
        del _held[key]
        if fd >= 0:
            os.close(fd)  # releases the lock
        if len(published) == n_published:
            for p in created:  # folders made for a --out that got nothing
                try:
                    p.rmdir()
                except OSError:
                    break


def _lock(parent: Path) -> int:
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX: no lock
        return -1
    try:
        fd = os.open(parent, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError as exc:
        raise ResultsError(f"cannot open the folder {_show(parent)}: {exc.strerror or exc}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise ResultsError(
            f"another latticedft run holds {_show(parent)}; wait for it to finish (one run per "
            "results folder at a time) and run again"
        ) from None
    except OSError as exc:  # a file system without flock (some network file systems): go on unlocked
        log.debug("no lock on %s (%s)", parent, exc)
    return fd


# -- staging and publishing ----------------------------------------------------------------------------------
class Staging:
    """A temporary folder beside ``dest`` that replaces ``dest`` on :meth:`publish`.

    ``copy_existing=True`` starts from a copy of an existing ``dest`` (stages
    that update results: ``serve``, ``export``). Use it through
    :func:`staged_results`.
    """

    def __init__(self, dest: Path, *, copy_existing: bool = False):
        self.dest = Path(dest)
        self.dest.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = self.dest.parent / f"{self.dest.name}.tmp-{uuid.uuid4().hex[:10]}"
        self.published = False
        try:
            if copy_existing and self.dest.is_dir():
                shutil.copytree(self.dest, self.tmp, symlinks=True)
                for root, dirs, _ in os.walk(self.tmp):  # a read-only results folder: its copy is writable
                    for d in [root, *(os.path.join(root, x) for x in dirs)]:
                        os.chmod(d, os.stat(d).st_mode | stat.S_IRWXU)
            else:
                self.tmp.mkdir()
        except BaseException:
            _rmtree(self.tmp)
            raise

    def publish(self) -> Path:
        """Put the staging folder at ``dest`` in one atomic step (see the module docstring)."""
        _fsync_tree(self.tmp)
        old: Path | None = None
        try:
            with _signals_deferred():  # a signal in here is delivered once the new results are in place
                if os.path.lexists(self.dest):
                    if _exchange(self.tmp, self.dest):
                        old = self.tmp  # now holds the previous results
                        self._published()
                        _fault("mid-publish", self.dest)
                    else:
                        old = self.dest.parent / f"{self.dest.name}.tmp-old-{uuid.uuid4().hex[:10]}"
                        os.rename(self.dest, old)
                        _fault("mid-publish", self.dest)
                        try:
                            os.rename(self.tmp, self.dest)
                        except BaseException:
                            os.rename(old, self.dest)
                            raise
                        self._published()
                else:
                    os.rename(self.tmp, self.dest)
                    self._published()
                _fsync_dir(self.dest.parent)
        finally:
            if old is not None and self.published:
                _rmtree(old)
        return self.dest

    def _published(self) -> None:
        self.published = True
        published.append(self.dest)

    def discard(self) -> None:
        if not self.published:
            _rmtree(self.tmp)


def _is_results_folder(folder: Path) -> bool:
    return (folder / _MARKER).is_file() or not any(folder.iterdir())


@contextmanager
def staged_results(
    dest: str | os.PathLike[str], *, copy_existing: bool = False, run_log: bool = True, replace_foreign: bool = True
) -> Iterator[Path]:
    """Write a stage's results into a temporary folder; publish it as ``dest`` when the block succeeds.

    ``with staged_results(dest) as folder:`` yields the temporary folder beside
    ``dest`` (a copy of ``dest`` with ``copy_existing=True``). With ``run_log``
    the ``latticedft`` logger also writes DEBUG lines, with times, to
    ``folder/run.log`` during the block. When the block ends normally the log is
    closed and the folder swapped in for ``dest`` (an existing ``dest`` is replaced)
    in one atomic step; when it raises (an error, KeyboardInterrupt, a signal)
    the folder is deleted and ``dest`` is left as it was. The lock of
    :func:`hold_results` is taken for the block unless this process holds it.

    ``replace_foreign=False`` refuses to replace an existing non-empty ``dest``
    that is not a results folder (no ``summary.json``): the command line never
    deletes a folder of files it did not write. An :class:`OSError` (disk full,
    a read-only folder) becomes a one-line :class:`ResultsError` naming the path.
    """
    with hold_results(dest) as real:
        if not replace_foreign and not copy_existing and real.is_dir() and not _is_results_folder(real):
            raise ResultsError(
                f"{_show(dest)}: holds files that latticedft did not write (no {_MARKER}); "
                "refusing to replace it: choose another --out or remove the folder"
            )
        staging: Staging | None = None
        handler: _RunLog | None = None
        try:
            staging = Staging(real, copy_existing=copy_existing)
            _fault("stage", staging.tmp)
            if run_log:
                handler = _RunLog(staging.tmp / RUN_LOG, encoding="utf-8")
                handler.setLevel(logging.DEBUG)
                handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
                log.addHandler(handler)
            yield staging.tmp
            if handler is not None and handler.failed is not None:
                raise handler.failed
            _close(handler)
            handler = None
            _fault("after-stage", staging.tmp)
            staging.publish()
        except OSError as exc:
            raise ResultsError(_os_error_line(exc, staging.tmp if staging else None, real)) from None
        finally:
            with contextlib.suppress(OSError):  # the stage failed already; its log goes with it
                _close(handler)
            if staging is not None:
                staging.discard()


class _RunLog(logging.FileHandler):
    """``run.log``: a failed write (a full disk) is kept in :attr:`failed`, not printed as a traceback."""

    failed: OSError | None = None

    def handleError(self, record: logging.LogRecord) -> None:
        exc = sys.exc_info()[1]
        if self.failed is None:
            self.failed = exc if isinstance(exc, OSError) else OSError(errno.EIO, str(exc), self.baseFilename)
            if not self.failed.filename:
                self.failed.filename = self.baseFilename


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


def versions() -> dict[str, str]:
    import torch

    from . import __version__

    return {
        "latticedft": __version__,
        "torch": torch.__version__,
        "numpy": np.__version__,
        "xarray": xr.__version__,
        "python": platform.python_version(),
    }


def json_safe(obj: Any) -> Any:
    """Recursively turn numpy scalars/arrays, paths and non-finite floats into JSON values (nan/inf -> None)."""
    if isinstance(obj, Mapping):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    if obj is None or isinstance(obj, str):
        return obj
    return str(obj)


def _write_json(path: Path, data: Any) -> None:
    text = json.dumps(json_safe(data), indent=2, allow_nan=False) + "\n"
    tmp = path.with_name(f".{path.name}.tmp")
    with _writing(path):
        try:
            tmp.write_text(text, encoding="utf-8")
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def write_model(folder: Path, model: Any, report: Any, meta: Mapping[str, Any]) -> dict[str, Any]:
    """``model.pt`` (:func:`latticedft.save_model`) and ``model.json`` (same record, no tensors)."""
    from ._modelfile import model_record, save_model

    with _writing(folder / "model.pt"):
        pt = save_model(model, folder / "model.pt", gauge=report.gauge if report is not None else None)
    record = model_record(model, report.gauge if report is not None else "unit-mass")
    record["n_parameters"] = model.n_parameters()
    record["training"] = report.to_dict() if report is not None else None
    record["sha256"] = sha256(pt)
    record["file"] = pt.name
    record.update(meta)
    _write_json(folder / "model.json", record)
    log.debug("wrote %s (sha256 %s) and model.json", pt.name, record["sha256"])
    return record


def load_verified_model(folder: str | os.PathLike[str]) -> Any:
    """Load ``folder/model.pt`` after checking it against ``folder/model.json``; refuse non-finite weights.

    The sha256 that ``model.json`` records must match the file (a mismatch is a
    :class:`latticedft.ModelFileError`: the file was changed or damaged after
    training); without a recorded sha256 a warning says the file is unverified.
    A model whose parameters or buffers hold NaN or inf is refused.
    """
    from ._modelfile import load_model

    folder = Path(folder)
    pt, meta = folder / "model.pt", folder / "model.json"
    if not pt.is_file():
        raise ModelFileError(f"{_show(pt)}: model file not found; run `latticedft run` (or `train`) first")
    model = load_model(pt)  # a file that is not a model file at all says so first
    expected = None
    if meta.is_file():
        try:
            record = json.loads(meta.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise ModelFileError(f"{_show(meta)}: not a readable model record ({type(exc).__name__})") from None
        expected = record.get("sha256") if isinstance(record, dict) else None
    if isinstance(expected, str) and expected:
        actual = sha256(pt)
        if actual != expected:
            raise ModelFileError(
                f"{_show(pt)}: sha256 {actual[:16]}... differs from the {expected[:16]}... "
                f"recorded in model.json: the file was changed or damaged after training; "
                "run `latticedft train` again"
            )
    else:
        log.warning("%s: no sha256 recorded in model.json; the model file is not verified", _show(pt))
    for name, tensor in model.state_dict().items():
        if tensor.is_floating_point() and not bool(tensor.isfinite().all()):
            bad = int((~tensor.isfinite()).sum())
            raise ModelFileError(
                f"{_show(pt)}: {bad} non-finite weight(s) (NaN or inf) in {name!r}; run `latticedft train` again"
            )
    return model


def _config_attr(config: Mapping[str, Any]) -> str:
    return json.dumps(json_safe(config), sort_keys=True)


def align_reference(pred: xr.DataArray, ref: xr.DataArray | None) -> xr.DataArray | None:
    """``ref`` on ``pred``'s slices (truncated to them), or None when it is shorter or on another lattice."""
    if ref is None:
        return None
    tdim = pred.dims[0]
    n = pred.sizes[tdim]
    if ref.sizes.get(tdim, 0) < n or ref.shape[1:] != pred.shape[1:]:
        return None
    return pred.copy(data=np.asarray(ref.values[:n], dtype=np.float64))


def write_task(
    folder: Path,
    name: str,
    variable: str,
    pred: xr.DataArray,
    ref: xr.DataArray | None,
    invariant: xr.DataArray | None,
    *,
    attrs: Mapping[str, Any],
    history: str,
    baseline: xr.DataArray | None = None,
    steps: int | None = None,
    charges: xr.Dataset | None = None,
    extra: Mapping[str, xr.DataArray] | None = None,
) -> Path:
    """``<name>.nc``: the served field, ``<var>_ref`` and ``<var>_err`` when a reference covers it, the
    ``invariant`` and the task's ``charges`` (``charge_<name>(t)``, ``energy(t)``) when given, and the
    variables of ``extra`` (e.g. ``extrapolation(t, feature)``).

    With a ``baseline`` (another scheme's field, scored against the same
    reference) the file also holds ``baseline_err_max(t)`` and
    ``baseline_err_rms(t)``: the baseline's max and RMS error per served slice
    (NaN where the baseline holds no slice), so that the figures of a later
    ``export`` need the file alone. ``steps`` (the slices the task asked for)
    is written as the global attribute ``latticedft_steps``.
    """
    pred = pred.rename(variable)
    quantity = str(pred.attrs.get("long_name") or variable)
    units = pred.attrs.get("units")
    unit_attrs = {"units": units} if units is not None else {}
    pred.attrs = {**pred.attrs, "long_name": quantity, "comment": "served by the learned discrete Lagrangian"}
    fields: dict[str, xr.DataArray] = {variable: pred}
    ref_al = align_reference(pred, ref)
    if ref_al is not None:
        ref_al.attrs = {**ref_al.attrs, "comment": "reference"}
        fields[f"{variable}_ref"] = ref_al
        err = (pred - ref_al).assign_attrs(long_name=f"{variable} - {variable}_ref", **unit_attrs)
        fields[f"{variable}_err"] = err
        if baseline is not None:
            fields.update(_baseline_errors(pred, ref_al, baseline, unit_attrs))
    if invariant is not None:
        fields["invariant"] = invariant.rename("invariant")
    if charges is not None:
        fields.update({str(k): v.rename(str(k)) for k, v in charges.data_vars.items()})
    fields.update({k: v.rename(k) for k, v in (extra or {}).items()})
    all_attrs = dict(attrs)
    if steps is not None:
        all_attrs["latticedft_steps"] = int(steps)
    with _writing(folder / f"{name}.nc"):
        return write_field(folder / f"{name}.nc", fields, attrs=all_attrs, history=history)


def _baseline_errors(
    pred: xr.DataArray, ref: xr.DataArray, baseline: xr.DataArray, unit_attrs: Mapping[str, Any]
) -> dict[str, xr.DataArray]:
    """The baseline's max and RMS error against ``ref`` per slice of ``pred`` (position by position)."""
    tdim = pred.dims[0]
    nt = pred.sizes[tdim]
    base = baseline.transpose(*pred.dims) if set(baseline.dims) == set(pred.dims) else baseline
    if base.shape[1:] != pred.shape[1:]:
        return {}
    n = min(nt, base.sizes[tdim])
    diff = np.full(pred.shape, np.nan)
    diff[:n] = np.asarray(base.values[:n], dtype=np.float64) - np.asarray(ref.values[:n], dtype=np.float64)
    flat = diff.reshape(nt, -1)
    with np.errstate(invalid="ignore"):
        worst = np.abs(flat).max(axis=1) if flat.shape[1] else np.full(nt, np.nan)
        rms = np.sqrt(np.mean(flat**2, axis=1)) if flat.shape[1] else np.full(nt, np.nan)
    label = str(baseline.attrs.get("long_name") or "baseline")
    coords = {tdim: pred.coords[tdim]} if tdim in pred.coords else None
    common = {"baseline": label, **unit_attrs}
    return {
        "baseline_err_max": xr.DataArray(
            worst, dims=(tdim,), coords=coords, attrs={"long_name": "max |baseline - reference| per slice", **common}
        ),
        "baseline_err_rms": xr.DataArray(
            rms, dims=(tdim,), coords=coords, attrs={"long_name": "rms of (baseline - reference) per slice", **common}
        ),
    }


def write_field(path: Path, fields: Mapping[str, xr.DataArray], *, attrs: Mapping[str, Any], history: str) -> Path:
    from .io.fields import write_field as _write

    return _write(path, fields, attrs=dict(attrs), history=history)


def read_task(path: Path, variable: str) -> tuple[xr.DataArray, xr.DataArray | None, xr.DataArray | None]:
    """Reload ``<name>.nc``: (served field, reference or None, error or None)."""
    from .io.fields import read_field

    if not path.is_file():
        raise InputError(f"{path}: file not found; run `latticedft serve` first")
    with xr.open_dataset(path, engine="netcdf4", decode_times=False) as ds:
        names = {str(v) for v in ds.data_vars}
    pred = read_field(path, variable, allow_nan=True)
    ref = read_field(path, f"{variable}_ref") if f"{variable}_ref" in names else None
    err = read_field(path, f"{variable}_err", allow_nan=True) if f"{variable}_err" in names else None
    return pred, ref, err


def export_task(
    folder: Path,
    name: str,
    variable: str,
    pred: xr.DataArray,
    ref: xr.DataArray | None,
    err: xr.DataArray | None,
    *,
    formats: Sequence[str],
    max_frames: int | None,
    train: Sequence[xr.DataArray] | None = None,
    title: str | None = None,
) -> list[Path]:
    """Write task ``name`` in each export format of ``formats``; the files written.

    Formats are the names of :data:`latticedft.io.exporters.EXPORTERS`
    (``"paraview"``, ``"figures"``, ``"xdmf"``). When ``folder/<name>.nc``
    exists, its global attributes and its series over time (``invariant``,
    ``energy``, ``charge_*``, ``baseline_err_*`` ...) go to the exporters too
    (:func:`read_task_series`).
    """
    from .io.exporters import ExportTask, export_formats

    attrs, series = read_task_series(Path(folder) / f"{name}.nc", variable)
    task = ExportTask(
        folder=Path(folder),
        name=name,
        field=pred.rename(variable),
        reference=ref,
        error=err,
        max_frames=max_frames,
        train=tuple(train) if train is not None else None,
        title=title or name,
        attrs=attrs,
        series=series,
    )
    with _writing(Path(folder) / f"{name}.*"):
        return export_formats(task, formats)


def read_task_series(path: Path, variable: str) -> tuple[dict[str, Any], dict[str, xr.DataArray]]:
    """Global attributes and the series over time of a task file (both empty when there is no file).

    A series is a data variable whose only dim is the field's time dim, other
    than the field itself, ``<var>_ref`` and ``<var>_err`` (1D fields).
    """
    if not Path(path).is_file():
        return {}, {}
    with xr.open_dataset(path, engine="netcdf4", decode_times=False) as ds:
        attrs = dict(ds.attrs)
        if variable not in ds.data_vars:
            return attrs, {}
        tdim = ds[variable].dims[0]
        skip = {variable, f"{variable}_ref", f"{variable}_err"}
        series = {str(k): v.load() for k, v in ds.data_vars.items() if v.dims == (tdim,) and str(k) not in skip}
    return attrs, series


def write_summary(folder: Path, summary: Mapping[str, Any]) -> Path:
    path = folder / "summary.json"
    _write_json(path, summary)
    return path


def read_summary(folder: Path) -> dict[str, Any] | None:
    path = folder / "summary.json"
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a readable summary ({type(exc).__name__})") from None
    return data if isinstance(data, dict) else None


def config_attrs(config: Mapping[str, Any], overrides: tuple[str, ...], command: str) -> dict[str, Any]:
    """Global attributes of a task file."""
    from . import __version__

    return {
        "source": f"latticedft {__version__}",
        "latticedft_config": _config_attr(config),
        "latticedft_overrides": json.dumps(list(overrides)),
        "latticedft_command": command,
    }
