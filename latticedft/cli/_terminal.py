"""The terminal: log lines that do not break a progress bar (written through ``tqdm.write``), and a first line
at once while the engine loads."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from typing import Any

__all__ = ["TqdmHandler", "loading_note"]


class TqdmHandler(logging.StreamHandler):
    """A stream handler whose lines go through ``tqdm.write``: an active bar on the same stream is cleared,
    the line written, and the bar drawn again below it (without a bar it is a plain stream handler)."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            msg = self.format(record)
            from tqdm.std import tqdm

            tqdm.write(msg, file=self.stream)
            self.flush()
        except RecursionError:  # pragma: no cover - as logging.StreamHandler
            raise
        except Exception:
            self.handleError(record)


@contextlib.contextmanager
def loading_note(stream: Any, show: bool) -> Iterator[None]:
    """On a terminal, the first line at once: ``latticedft: loading torch and xarray ...`` while the engine is
    imported (seconds), erased when the import is done, so the run's own lines (or one error line) follow.
    Elsewhere (a file, a pipe, ``-q``) nothing is written."""
    live = show and _isatty(stream)
    if live:
        stream.write("latticedft: loading torch and xarray ...")
        stream.flush()
    try:
        yield
    finally:
        if live:
            stream.write("\r\x1b[K")  # back to the line start, erase the line
            stream.flush()


def _isatty(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False
