"""Exceptions raised by latticedft.

Every error a user can cause carries a one-line message that names the file,
key or argument at fault and says what was expected.
"""

from __future__ import annotations

from typing import Any

__all__ = ["LatticeDFTError", "InputError", "ConfigError", "ServeError", "ModelFileError"]


class LatticeDFTError(Exception):
    """Base class of every error latticedft raises on purpose."""


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

    def __init__(self, message: str, *, result: Any = None, slice: int | None = None,
                 site: tuple[int, ...] | None = None, residual: float | None = None):
        super().__init__(message)
        self.result = result
        self.slice = slice
        self.site = site
        self.residual = residual
