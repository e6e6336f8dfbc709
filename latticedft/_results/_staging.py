"""The results folder: where it may go, its lock, the staging folder, publishing, recovery.

Publishing is one atomic exchange of the staging folder and the results folder; a killed run's
leftovers are recovered by the next command.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import re
import shutil
import stat
import sys
import uuid
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from ._safety import (
    ResultsError,
    _close,
    _exchange,
    _fault,
    _fsync_dir,
    _fsync_tree,
    _os_error_line,
    _rmtree,
    _show,
    _signals_deferred,
    log,
)

RUN_LOG = "run.log"


#: Every results folder latticedft stages holds this file: a folder with it (or an empty one) may be replaced
#: by ``--overwrite``; any other folder is the user's and is never deleted.
MARKER = ".latticedft-results"
_MARKER_TEXT = "A results folder written by latticedft: its next run replaces the whole folder.\n"
_WRITTEN = frozenset({"model.pt", "model.json", "summary.json", "run.log", MARKER})


#: The results folders this process published, in order (the command line says whether an interrupted
#: command had already published).
published: list[Path] = []


def check_destination(
    dest: str | os.PathLike[str], *, inputs: Sequence[Path] = (), root: Path | None = None, what: str = "results folder"
) -> Path:
    """The real path of ``dest`` (a symlinked ``dest`` is followed), after checking that results may go there.

    Refused (:class:`ResultsError`): a ``dest`` that is an existing non-folder, that is or contains the case
    folder ``root``, or that is, contains or lies inside one of ``inputs`` (files and folders the case
    reads). A ``dest`` inside ``root`` (``CASE/results``, ``CASE/results2``) is fine.
    """
    if os.path.islink(dest):
        try:
            os.stat(dest)
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                raise ResultsError(f"{what} {_show(dest)}: is a link that loops (to itself); remove it") from None
    real = Path(os.path.realpath(dest))
    shown = f"{what} {_show(dest)}" + (f" (a link to {_show(real)})" if os.path.islink(dest) else "")
    why = "; results replace their folder as a whole, so they must go elsewhere (the default is CASE/results)"
    if root is not None:
        r = Path(os.path.realpath(root))
        if real == r or r.is_relative_to(real):
            verb = "is" if real == r else "contains"
            raise ResultsError(f"{shown}: {verb} the case folder {_show(root)}{why}")
    outer = _results_above(real, None if root is None else Path(os.path.realpath(root)) / "results")
    if outer is not None:
        raise ResultsError(
            f"{shown}: lies inside the results folder {_show(outer)}, which the next run replaces as a whole "
            "(with everything in it); choose a folder beside it"
        )
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


def _results_above(real: Path, default: Path | None) -> Path | None:
    """The nearest folder above ``real`` that is a results folder (the case's default one, or one holding the
    marker), or None."""
    for parent in real.parents:
        if parent == default or (parent / MARKER).is_file():
            return parent
    return None


def _staging_re(name: str) -> re.Pattern[str]:
    return re.compile(rf"^{re.escape(name)}\.tmp-(old-)?[0-9a-f]{{10}}$")


def leftovers(dest: str | os.PathLike[str]) -> list[Path]:
    """Staging folders of ``dest`` left beside it (by runs that were killed, or by a run in progress)."""
    dest = Path(os.path.realpath(dest))
    if not dest.parent.is_dir():
        return []
    pattern = _staging_re(dest.name)
    return sorted(p for p in dest.parent.iterdir() if pattern.match(p.name))


def _recover(dest: Path, keep: str | None = None) -> None:
    """With the lock held: put parked results back when ``dest`` is missing, delete dead staging folders (but
    those holding a file named ``keep``: a checkpointed run to resume)."""
    left = [p for p in leftovers(dest) if keep is None or not (p / keep).is_file()]
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
    stuck = [p for p in left if p != restored and os.path.lexists(p)]
    if stuck:  # an immutable file, a folder of another user: say so instead of claiming it was removed
        log.warning(
            "could not remove %s beside %s (a file there cannot be deleted: immutable, or not yours); "
            "remove it by hand",
            ", ".join(p.name for p in stuck),
            _show(dest),
        )
        left = [p for p in left if p not in stuck]
        if not left:
            return
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
def hold_results(dest: str | os.PathLike[str], keep: str | None = None) -> Iterator[Path]:
    """Hold the results folder ``dest`` for one command: the lock, then recovery from killed runs.

    Takes a non-blocking ``flock`` on ``dest``'s parent folder (a folder file descriptor: nothing is
    created beside the results) and keeps it until the block ends; another process holding it gives a
    :class:`ResultsError` ("another latticedft run holds ..."). Then staging folders left by killed runs are
    removed and, when ``dest`` is missing, results parked by an interrupted publishing step are put back (one
    warning); with ``keep``, staging folders holding a file of that name are left for the command to take up
    (:func:`staged_results`'s ``adopt``). Yields the real path of ``dest``. Re-entrant within a process.
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
        _recover(dest, keep)
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


def held_by_another(dest: str | os.PathLike[str]) -> bool:
    """True when another process holds the lock of ``dest`` (a run in progress); takes nothing."""
    parent = Path(os.path.realpath(dest)).parent
    if str(parent) in _held or not parent.is_dir():
        return False
    try:
        fd = _flocked(parent)
    except BlockingIOError:
        return True
    except OSError:
        return False
    if fd >= 0:
        os.close(fd)  # releases the lock taken to look
    return False


def _lock(parent: Path) -> int:
    try:
        return _flocked(parent)
    except BlockingIOError:
        raise ResultsError(
            f"another latticedft run holds {_show(parent)}; wait for it to finish (one run per "
            "results folder at a time) and run again"
        ) from None
    except OSError as exc:
        raise ResultsError(f"cannot open the folder {_show(parent)}: {exc.strerror or exc}") from None


def _flocked(parent: Path) -> int:
    """A descriptor of the folder ``parent`` holding its non-blocking exclusive ``flock`` (-1 where the system
    has no flock; unlocked on a file system without flock). BlockingIOError when another process holds the
    lock; OSError when the folder cannot be opened."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX: no lock
        return -1
    fd = os.open(parent, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise
    except OSError as exc:  # a file system without flock (some network file systems): go on unlocked
        log.debug("no lock on %s (%s)", parent, exc)
    return fd


class Staging:
    """A temporary folder beside ``dest`` that replaces ``dest`` on :meth:`publish`.

    ``copy_existing=True`` starts from a copy of an existing ``dest`` (stages
    that update results: ``serve``, ``export``); ``adopt`` takes up the
    staging folder of a killed run instead (``--resume``). Use it through
    :func:`staged_results`.
    """

    def __init__(self, dest: Path, *, copy_existing: bool = False, adopt: Path | None = None):
        self.dest = Path(dest)
        self.dest.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = adopt or self.dest.parent / f"{self.dest.name}.tmp-{uuid.uuid4().hex[:10]}"
        self.published = False
        if adopt is not None:  # a killed run's staging folder, taken up again (``--resume``)
            return
        try:
            if copy_existing and self.dest.is_dir():
                shutil.copytree(self.dest, self.tmp, symlinks=True)
                for root, dirs, _ in os.walk(self.tmp):  # a read-only results folder: its copy is writable
                    for d in [root, *(os.path.join(root, x) for x in dirs)]:
                        os.chmod(d, os.stat(d).st_mode | stat.S_IRWXU)
                _replace_links(self.tmp, self.dest)
            else:
                self.tmp.mkdir()
            (self.tmp / MARKER).write_text(_MARKER_TEXT, encoding="utf-8")
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


def _replace_links(tmp: Path, dest: Path) -> None:
    """Nothing inside a results folder is followed as a link when written: in the staging copy ``tmp`` of
    ``dest``, a link to a regular file becomes a copy of that file, and any other link (to a folder, a device,
    nothing) is left out; each with a warning naming it."""
    for root, dirs, files in os.walk(tmp):
        for name in [*dirs, *files]:
            link = Path(root, name)
            if not link.is_symlink():
                continue
            shown = _show(dest / link.relative_to(tmp))
            target = os.readlink(link)
            try:
                regular = stat.S_ISREG(os.stat(link).st_mode)
            except OSError:
                regular = False
            if regular:
                copy = link.with_name(f"{name}.tmp-link-{uuid.uuid4().hex[:10]}")
                shutil.copyfile(link, copy)
                os.replace(copy, link)
                log.warning("%s was a link to %s: the updated results hold a copy of that file instead", shown, target)
            else:
                link.unlink()
                log.warning("%s was a link to %s (not a regular file): left out of the updated results", shown, target)
        dirs[:] = [d for d in dirs if not Path(root, d).is_symlink() and Path(root, d).is_dir()]


def _is_results_folder(folder: Path) -> bool:
    """True for a folder latticedft wrote (it holds the marker, or is a results folder written before the
    marker existed) and for an empty one."""
    return (folder / MARKER).is_file() or not any(folder.iterdir()) or _earlier_results(folder)


def _earlier_results(folder: Path) -> bool:
    """A results folder of a version without the marker: a latticedft ``summary.json``, and only the files a run
    writes (the fixed names, and files named after the tasks it lists)."""
    try:
        summary = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    if not isinstance(summary, dict) or "latticedft" not in (summary.get("versions") or {}):
        return False
    tasks = [str(t) for t in (summary.get("tasks") or {})]
    return all(
        p.name in _WRITTEN or any(p.name.startswith((f"{t}.", f"{t}_")) for t in tasks) for p in folder.iterdir()
    )


@contextmanager
def staged_results(
    dest: str | os.PathLike[str],
    *,
    copy_existing: bool = False,
    run_log: bool = True,
    replace_foreign: bool = True,
    adopt: Path | None = None,
    keep: str | None = None,
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
    that latticedft did not write (no marker file :data:`MARKER`): the command line never
    deletes a folder of files it did not write. An :class:`OSError` (disk full,
    a read-only folder) becomes a one-line :class:`ResultsError` naming the path.
    ``adopt`` (a staging folder of ``dest`` that a killed run left) is taken
    up instead of a new one: ``run.log`` goes on, and the folder is published
    or, when the block fails, deleted as a new one would be; but a stage
    holding a file named ``keep`` (a checkpointed run's journal) is left for
    ``--resume`` when the command is interrupted (SIGINT, SIGTERM).
    """
    with hold_results(dest) as real:
        if not replace_foreign and not copy_existing and not adopt and real.is_dir() and not _is_results_folder(real):
            raise ResultsError(
                f"{_show(dest)}: holds files that latticedft did not write (no {MARKER}); "
                "refusing to replace it: choose another --out or remove the folder"
            )
        staging: Staging | None = None
        handler: _RunLog | None = None
        try:
            staging = Staging(real, copy_existing=copy_existing, adopt=adopt)
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
        except (KeyboardInterrupt, SystemExit) as exc:
            staging = _kept_for_resume(staging, keep, exc)
            raise
        except BaseException as exc:  # the command line's Terminated (SIGTERM)
            staging = _kept_for_resume(staging, keep, exc if not isinstance(exc, Exception) else None)
            raise
        finally:
            with contextlib.suppress(OSError):  # the stage failed already; its log goes with it
                _close(handler)
            if staging is not None:
                staging.discard()


def _kept_for_resume(staging: Staging | None, keep: str | None, exc: BaseException | None) -> Staging | None:
    """None (nothing to discard) when the interrupted stage ``staging`` holds the file ``keep``: it is left for
    ``--resume``, with a warning; else ``staging``."""
    if staging is None or keep is None or exc is None or not (staging.tmp / keep).is_file():
        return staging
    log.warning("interrupted: the checkpoints are kept in %s; `--resume` continues the run", _show(staging.tmp))
    return None


class _RunLog(logging.FileHandler):
    """``run.log``: a failed write (a full disk) is kept in :attr:`failed`, not printed as a traceback."""

    failed: OSError | None = None

    def handleError(self, record: logging.LogRecord) -> None:
        exc = sys.exc_info()[1]
        if self.failed is None:
            self.failed = exc if isinstance(exc, OSError) else OSError(errno.EIO, str(exc), self.baseFilename)
            if not self.failed.filename:
                self.failed.filename = self.baseFilename
