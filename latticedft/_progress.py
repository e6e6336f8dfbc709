"""Progress bars of learning and serving: on a terminal, in Jupyter, and quiet elsewhere.

:func:`progress_bar` picks the bar class once: ``tqdm.notebook`` inside a Jupyter kernel *with* ipywidgets,
plain ``tqdm`` otherwise. (``tqdm.auto`` warns "IProgress not found" at import in a kernel without
ipywidgets, so latticedft never imports it.) ``progress=None`` shows the bar when stderr is a terminal
and in a Jupyter kernel, and nowhere else. Where the bar cannot redraw in place (a notebook without
ipywidgets, a file), every refresh is a new line, so it refreshes at most every :data:`PLAIN_INTERVAL`
seconds and keeps its last line; on a terminal or as a widget it refreshes every :data:`LIVE_INTERVAL`
seconds and disappears when done.
"""

from __future__ import annotations

import functools
import importlib.util
import sys
from typing import Any

__all__ = ["progress_bar", "in_jupyter", "LIVE_INTERVAL", "PLAIN_INTERVAL"]

#: Seconds between refreshes of a bar that redraws in place (a terminal, a notebook widget).
LIVE_INTERVAL = 0.5
#: Seconds between refreshes of a bar that prints a new line each time (a notebook without ipywidgets).
PLAIN_INTERVAL = 10.0


def in_jupyter() -> bool:
    """True inside a Jupyter kernel (the test of ``tqdm.autonotebook``: its shell module is loaded)."""
    return "ipykernel.zmqshell" in sys.modules


@functools.cache
def _widgets() -> bool:
    return importlib.util.find_spec("ipywidgets") is not None


def _isatty(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def progress_bar(total: int, desc: str, progress: bool | None) -> Any:
    """A bar over ``total`` steps; ``progress``: True, False, or None (on a terminal and in Jupyter only)."""
    tty = _isatty(sys.stderr)
    show = (tty or in_jupyter()) if progress is None else bool(progress)
    if show and not tty and in_jupyter() and _widgets():
        from tqdm.notebook import tqdm as notebook_tqdm

        return notebook_tqdm(total=total, desc=desc, leave=False, mininterval=LIVE_INTERVAL)
    from tqdm.std import tqdm

    return tqdm(
        total=total,
        desc=desc,
        leave=not tty,  # a bar that cannot redraw keeps its last line instead of a blank one
        disable=not show,
        file=sys.stderr,
        mininterval=LIVE_INTERVAL if tty else PLAIN_INTERVAL,
    )
