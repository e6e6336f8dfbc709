"""Log lines on a terminal that do not break a progress bar: written through ``tqdm.write``."""

from __future__ import annotations

import logging

__all__ = ["TqdmHandler"]


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
