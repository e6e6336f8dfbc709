"""Exceptions raised by latticedft.

Every error a user can cause carries a one-line message that names the file,
key or argument at fault and says what was expected. An error about one key
or argument also carries it as data: ``key`` (e.g. ``"boundary"``,
``"optimizer"``, ``"train.boundary"``) and ``problem``, the message without
the leading ``"<key>: "``, so that a caller can re-address it (the case run
turns ``InputError(key="boundary")`` into ``case.toml: train.boundary: ...``)
without reading the text.

>>> err = InputError.at("boundary", "unknown axis 'y'")
>>> str(err), err.key, err.problem
("boundary: unknown axis 'y'", 'boundary', "unknown axis 'y'")
"""

from __future__ import annotations

import os
from typing import Any, Self

__all__ = ["LatticeDFTError", "InputError", "ConfigError", "ServeError", "ModelFileError", "not_a_regular_file"]


def not_a_regular_file(path: str | os.PathLike[str]) -> str:
    """What stands at ``path``, which exists but is not a regular file, for a message: "a folder" or "not a
    regular file (a device, a pipe or a socket)", with " (a link to TARGET)" when ``path`` is a link."""
    what = "a folder" if os.path.isdir(path) else "not a regular file (a device, a pipe or a socket)"
    return what + (f" (a link to {os.readlink(path)})" if os.path.islink(path) else "")


class LatticeDFTError(Exception):
    """Base class of every error latticedft raises on purpose.

    ``key`` names the key or argument the error concerns (None when it
    concerns no single one); ``problem`` is what is wrong with it (the
    message itself unless given).
    """

    def __init__(self, message: str = "", *, key: str | None = None, problem: str | None = None):
        super().__init__(message)
        self.key = key
        self.problem = message if problem is None else problem

    @classmethod
    def at(cls, key: str, problem: str) -> Self:
        """The error ``"<key>: <problem>"`` about ``key``."""
        return cls(f"{key}: {problem}", key=key, problem=problem)


class InputError(LatticeDFTError, ValueError):
    """Bad input data: NaN, wrong shape, wrong dims, non-uniform coordinates ..."""


class ConfigError(LatticeDFTError, ValueError):
    """A bad ``case.toml`` key or ``--set`` override."""


class ModelFileError(LatticeDFTError, ValueError):
    """A model file that is corrupt, from another format version, or unsafe."""


class ServeError(LatticeDFTError, RuntimeError):
    """Newton's method failed while serving.

    ``result`` holds what was solved before the failure (a ``ServeResult``
    whose ``complete`` is False), ``slice`` the time index being solved,
    ``site`` the lattice index of the worst residual and ``residual`` its
    value.
    """

    def __init__(
        self,
        message: str,
        *,
        result: Any = None,
        slice: int | None = None,
        site: tuple[int, ...] | None = None,
        residual: float | None = None,
    ):
        super().__init__(message)
        self.result = result
        self.slice = slice
        self.site = site
        self.residual = residual
