"""Type checks of case.toml values: each returns the value (converted) or raises ``_Bad`` saying what was expected."""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable
from typing import Any

from .._boundary import boundary_kinds, kinds_text

_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_DEVICE_RE = re.compile(r"^(cpu|auto|cuda(:\d+)?)$")


# Each check returns the normalised value or raises _Bad(expected).
class _Bad(Exception):
    def __init__(self, expected: str):
        super().__init__(expected)
        self.expected = expected


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def t_str(v: Any) -> str:
    if not isinstance(v, str):
        raise _Bad("a string")
    return v


def t_bool(v: Any) -> bool:
    if not isinstance(v, bool):
        raise _Bad("true or false")
    return v


def t_pos_int(v: Any) -> int:
    if not _is_int(v) or v < 1:
        raise _Bad("a positive integer")
    return int(v)


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the system tells it)."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def t_threads(v: Any) -> int:
    cores = available_cores()
    if not _is_int(v) or not 1 <= v <= cores:
        raise _Bad(f"an integer from 1 to {cores} (the cores this machine gives the run)")
    return int(v)


def t_ensemble(v: Any) -> int:
    if not _is_int(v) or v < 2:
        raise _Bad("an integer >= 2 (ensemble members, the full-data model included)")
    return int(v)


def t_calibrate(v: Any) -> bool | str:
    if v != "auto" and not isinstance(v, bool):
        raise _Bad('true, false or "auto"')
    return v


def t_nonneg_int(v: Any) -> int:
    if not _is_int(v) or v < 0:
        raise _Bad("an integer >= 0")
    return int(v)


def t_float(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise _Bad("a number")
    return float(v)


def t_pos_float(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise _Bad("a positive number")
    return float(v)


def t_nonneg_float(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
        raise _Bad("a number >= 0")
    return float(v)


def t_ridge(v: Any) -> float | str:
    if v == "auto":
        return "auto"
    try:
        return t_nonneg_float(v)
    except _Bad:
        raise _Bad('a number >= 0 or "auto"') from None


def t_str_list(v: Any) -> list[str]:
    if isinstance(v, str):
        return [v]
    if not isinstance(v, list) or not all(isinstance(s, str) for s in v):
        raise _Bad("a string or a list of strings")
    return list(v)


def t_choice(*choices: str) -> Callable[[Any], str]:
    def check(v: Any) -> str:
        if v not in choices:
            raise _Bad(" or ".join(repr(c) for c in choices))
        return str(v)

    check.__name__ = f"t_choice{choices}"
    return check


def t_boundary(v: Any) -> str | dict[str, str]:
    """A boundary kind of :func:`latticedft._boundary.boundary_kinds`, or a table axis -> kind (the axes are
    checked against the data when they are read)."""
    if isinstance(v, str):
        if v not in boundary_kinds():
            raise _Bad(f"{kinds_text()}, or a table axis -> kind")
        return v
    if isinstance(v, dict):
        for axis, kind in v.items():
            if kind not in boundary_kinds():
                raise _Bad(f"a table axis -> kind with kinds {list(boundary_kinds())} (axis {axis!r} has {kind!r})")
        return {str(k): str(kind) for k, kind in v.items()}
    raise _Bad(f"{kinds_text()}, or a table axis -> kind")


def t_stencil(v: Any) -> str | list[list[int]]:
    if v in ("first-order", "full-cell"):
        return str(v)
    if isinstance(v, list) and v and all(isinstance(o, list) and o and all(_is_int(i) for i in o) for o in v):
        return [[int(i) for i in o] for o in v]
    raise _Bad('"first-order", "full-cell" or a list of integer offsets such as [[0, 0], [1, 0], [0, 1]]')


def t_invariant(v: Any) -> str:
    if not isinstance(v, str) or not re.fullmatch(r"[A-Za-z_][\w.]*:[A-Za-z_]\w*", v):
        raise _Bad('"module:function", e.g. "latticedft.systems:sine_gordon_energy"')
    return v


def t_name(v: Any) -> str:
    if not isinstance(v, str) or not _NAME_RE.match(v) or v in ("model", "summary", "run"):
        raise _Bad("a plain file-name stem (letters, digits, '_', '-', '.'; not 'model', 'summary' or 'run')")
    return v


def t_device(v: Any) -> str:
    if not isinstance(v, str) or not _DEVICE_RE.match(v):
        raise _Bad("'cpu', 'cuda', 'cuda:N' (N a GPU index) or 'auto'")
    return v


def t_any(v: Any) -> Any:
    return v
