"""Writing a file so that it is either complete or absent: a temporary file beside it, then a rename."""

from __future__ import annotations

import os
import uuid
from pathlib import Path

__all__ = ["write_text_atomic"]


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
