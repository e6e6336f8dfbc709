"""Serving options as values: :class:`ServeOptions` (how to serve) and :class:`Cadence` (which slices to keep).

``serve(model, init, rtol=..., every=...)`` gathers its keywords into one frozen :class:`ServeOptions`;
the drivers, the case pipeline and ``case.toml`` pass that value, never the loose keywords. The options'
defaults are written here only. A field whose metadata says ``case=True`` (see :func:`option`) is also a
key of ``case.toml``'s ``[[serve]]`` tables: the schema reads the key, its check of a TOML value and its
default from the fields (:meth:`ServeOptions.case_keys`), so a new serving key is one field here and one
row of the docs' table.

>>> opts = ServeOptions(rtol=1e-8, every=4)
>>> opts.max_newton, opts.cadence.thins, opts.cadence.kept(10).tolist()
(30, True, [0, 4, 8, 9])
>>> sorted(ServeOptions.case_keys())
['boundary_value', 'box', 'checkpoint', 'every', 'max_newton', 'mode', 'rtol', 'solver']
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._errors import InputError
from .._modeloptions import OptionTypeError
from ._solvers import SOLVERS

__all__ = ["MODES", "Cadence", "ServeOptions", "kept_slices", "option"]

#: ``mode``: whole-slice Newton, or the paper's site-by-site sweep.
MODES = ("newton", "sweep")

#: A check of a ``case.toml`` value: returns it (converted) or raises :class:`OptionTypeError` saying what
#: was expected, in the words of the other ``case.toml`` checks ("a positive integer").
TomlCheck = Callable[[Any], Any]


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def positive_int(v: Any) -> int:
    """A TOML integer >= 1."""
    if not _is_int(v) or v < 1:
        raise OptionTypeError("a positive integer")
    return int(v)


def positive_number(v: Any) -> float:
    """A finite TOML number > 0."""
    if not _is_number(v) or v <= 0:
        raise OptionTypeError("a positive number")
    return float(v)


def unit_number(v: Any) -> float:
    """A TOML number strictly between 0 and 1."""
    if not _is_number(v) or not 0 < v < 1:
        raise OptionTypeError("a number between 0 and 1 (exclusive)")
    return float(v)


def number_or_function(v: Any) -> float | str:
    """A finite TOML number, or a ``"module:function"`` string."""
    if _is_number(v):
        return float(v)
    if isinstance(v, str) and _FUNCTION.fullmatch(v):
        return v
    raise OptionTypeError('a number or "module:function", e.g. 0.0 or "mycase_edges:left_drive"')


_FUNCTION = re.compile(r"[A-Za-z_][\w.]*:[A-Za-z_]\w*")


def choice(*names: str) -> TomlCheck:
    """One of the strings ``names``."""

    def check(v: Any) -> str:
        if v not in names:
            raise OptionTypeError(" or ".join(repr(c) for c in names))
        return str(v)

    return check


def option(default: Any, toml: TomlCheck | None = None) -> Any:
    """A field of :class:`ServeOptions` with its default; ``toml`` (a check of a TOML value) makes it a
    ``[[serve]]`` key of ``case.toml`` too."""
    return field(default=default, metadata={"toml": toml})


def kept_slices(slices: int, every: int) -> np.ndarray:
    """The slices kept of ``slices`` served: ``0, every, 2 every, ...`` and the last one.

    >>> kept_slices(10, 4).tolist()
    [0, 4, 8, 9]
    """
    idx = np.arange(0, slices, every, dtype=np.int64)
    if slices and idx[-1] != slices - 1:
        idx = np.append(idx, slices - 1)
    return idx


@dataclass(frozen=True)
class Cadence:
    """The output cadence: of the slices served, keep ``0, every, 2 every, ...`` and the last one.

    ``every = 1`` keeps every slice. Every decision that depends on the cadence is a member here.
    """

    every: int = 1

    def __post_init__(self) -> None:
        every = self.every
        if not _is_int(every) or every < 1:
            raise InputError.at("every", f"expected an integer >= 1 (keep every k-th time slice), got {every!r}")

    @property
    def thins(self) -> bool:
        """True when some slices are dropped (``every > 1``)."""
        return self.every > 1

    def streams(self, on_slice: Any = None) -> bool:
        """Whether an n-D field is served through a rolling window: when slices are dropped, or when each
        kept slice is handed to an ``on_slice`` callback as it is served."""
        return self.thins or on_slice is not None

    def kept(self, slices: int) -> np.ndarray:
        """The indices of the slices kept of ``slices`` served."""
        return kept_slices(slices, self.every)

    def kept_count(self, slices: int) -> int:
        """How many of ``slices`` served are kept (the length of the thinned field)."""
        return slices if not self.thins else len(self.kept(slices))

    def describe(self) -> str:
        """``", every k"`` for a thinning cadence, else empty (for log lines)."""
        return f", every {self.every}" if self.thins else ""


@dataclass(frozen=True)
class ServeOptions:
    """How :func:`latticedft.serve` serves: every keyword of ``serve`` that is an option rather than data.

    Attributes
    ----------
    mode : "newton" or "sweep"
        Whole-slice Newton (fast) or the paper's site-by-site sweep (reference).
    rtol : float
        Newton stops when the residual is below ``rtol`` times the size of the kinetic terms.
    max_newton : int
        Newton iterations per slice (per site in sweep mode) before giving up.
    box : float, optional
        1D only: a trajectory stops (completed) once ``|psi| > box``.
    solver : "auto", "sitewise", "krylov" or "lu"
        n-D ``mode="newton"`` only: the linear solve of each Newton step (see :func:`latticedft.serve`).
    every : int
        Output cadence (:class:`Cadence`): keep only the time slices ``0, every, 2 every, ...`` and the last.
    affine : bool
        n-D ``mode="newton"`` only: serve the affine recurrence when the DEL is affine.
    progress : bool, optional
        Progress bar; ``None`` shows it only on a terminal.
    device : "cpu", "cuda", "cuda:N" or "auto", optional
        Where the model is evaluated (default the CPU).
    boundary_value : float, function or "module:function", optional
        n-D only: the Dirichlet strips on the slices beyond those ``init`` holds, a number or a function
        ``value(t, *coords)`` of the slice's time and the spatial coordinates (arrays on the lattice, in the
        field's dim order) returning the field's values there (the strips are taken from them), so that a
        field served past the end of its data needs no file of boundary values. Default: none, the strips
        must be in ``init`` on every slice served.
    checkpoint : int, optional
        n-D only: the rolling window (``every > 1`` or ``on_slice``) holds at most this many new slices, and
        after every ``checkpoint`` slices served its state is handed to the ``checkpointer`` of ``on_slice``
        when it has one (the case pipeline's resumable tasks, ``[[serve]] checkpoint``). Default: none.

    The fields given a TOML check (:func:`option`) are also ``[[serve]]`` keys of ``case.toml``.
    """

    mode: str = option("newton", choice(*MODES))
    rtol: float = option(1e-10, unit_number)
    box: float | None = option(None, positive_number)
    max_newton: int = option(30, positive_int)
    solver: str = option("auto", choice(*SOLVERS))
    every: int = option(1, positive_int)
    affine: bool = option(True)
    progress: bool | None = option(None)
    device: str | None = option(None)
    boundary_value: float | str | Callable[..., Any] | None = option(None, number_or_function)
    checkpoint: int | None = option(None, positive_int)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise InputError.at("mode", f"expected one of {list(MODES)}, got {self.mode!r}")
        if not (isinstance(self.rtol, float) and 0 < self.rtol < 1):
            raise InputError.at("rtol", f"expected a float in (0, 1), got {self.rtol!r}")
        if self.box is not None and not (_is_number(self.box) and self.box > 0):
            raise InputError.at("box", f"expected a positive number, got {self.box!r}")
        if not _is_int(self.max_newton) or self.max_newton < 1:
            raise InputError.at(
                "max_newton", f"expected a positive integer (Newton iterations per slice), got {self.max_newton!r}"
            )
        if self.solver not in SOLVERS:
            raise InputError.at("solver", f"expected one of {list(SOLVERS)}, got {self.solver!r}")
        if not isinstance(self.affine, bool):
            raise InputError.at("affine", f"expected True or False, got {self.affine!r}")
        if self.progress is not None and not isinstance(self.progress, bool):
            raise InputError.at("progress", f"expected True, False or None, got {self.progress!r}")
        Cadence(self.every)  # checks ``every``
        if self.checkpoint is not None and (not _is_int(self.checkpoint) or self.checkpoint < 1):
            raise InputError.at(
                "checkpoint", f"expected a positive integer (slices between checkpoints), got {self.checkpoint!r}"
            )
        value = self.boundary_value
        if not (value is None or callable(value) or _is_number(value) or isinstance(value, str)):
            raise InputError.at(
                "boundary_value", f"expected a number, a function value(t, *coords) or None, got {value!r}"
            )

    @property
    def cadence(self) -> Cadence:
        """The output cadence of ``every``."""
        return Cadence(self.every)

    def replace(self, **changes: Any) -> ServeOptions:
        """A copy with ``changes`` (checked as the constructor checks them)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_keywords(cls, base: ServeOptions | None = None, **keywords: Any) -> ServeOptions:
        """``base`` (default: the defaults) with the options given as keywords; a TypeError names an unknown
        keyword, as Python's would."""
        if base is not None and not isinstance(base, ServeOptions):
            raise InputError.at("options", f"expected a ServeOptions, got {type(base).__name__}")
        names = [f.name for f in dataclasses.fields(cls if base is None else type(base))]
        for key in keywords:
            if key not in names:
                near = difflib.get_close_matches(key, names, n=1, cutoff=0.6)
                hint = f"; did you mean {near[0]!r}?" if near else ""
                raise TypeError(f"serve() got an unexpected keyword argument {key!r}{hint}")
        if base is None:
            return cls(**keywords)
        return dataclasses.replace(base, **keywords) if keywords else base

    @classmethod
    def case_keys(cls) -> dict[str, tuple[TomlCheck, Any]]:
        """The ``[[serve]]`` keys of ``case.toml`` among the fields: name -> (TOML check, default)."""
        return {f.name: (f.metadata["toml"], f.default) for f in dataclasses.fields(cls) if f.metadata.get("toml")}
