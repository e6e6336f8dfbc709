"""Tuning knobs: the sizes of the blocks, windows and chunks the package works in, set for a while or for good.

``latticedft.set_options(serve_window_bytes=2**20)`` sets knobs for the rest of the session; used as a context
manager (``with latticedft.set_options(...):``) it sets them for the block only, and restores the values they
had when it ends. ``latticedft.get_options()`` returns the values in effect. The knobs trade memory for
speed: none changes what is computed beyond round-off, and at their defaults the outputs are those of
every release (docs/api.md lists them).

The values are global to the process (not to a thread), as xarray's options are; code reads one with
:func:`option` at the moment it sizes a block.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Any

from ._errors import InputError

__all__ = ["OPTIONS", "get_options", "option", "set_options"]


@dataclass(frozen=True)
class _Knob:
    default: Any
    check: Callable[[Any], bool]
    expects: str  # what a valid value is, for the error message
    meaning: str


def _positive_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 1


def _non_negative_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


_POSITIVE = "a positive integer"

#: Every knob: its default, its check and what it sizes.
OPTIONS: dict[str, _Knob] = {
    "scan_bytes": _Knob(
        64 * 2**20,
        _positive_int,
        _POSITIVE,
        "bytes of values read at a time when a lazily opened field is scanned for NaN/inf",
    ),
    "serve_window_bytes": _Knob(
        32 * 2**20,
        _positive_int,
        _POSITIVE,
        "bytes of the rolling window of new slices while a field is served (at least 4 slices)",
    ),
    "task_block_bytes": _Knob(
        32 * 2**20,
        _positive_int,
        _POSITIVE,
        "bytes of each of the two fields read at a time when a task's error is measured",
    ),
    "range_sites_per_pass": _Knob(
        250_000,
        _positive_int,
        _POSITIVE,
        "cells gathered per pass when a served field is checked against the training range",
    ),
    "poly_chunk_elements": _Knob(
        1 << 22,
        _positive_int,
        _POSITIVE,
        "elements (cells x terms x derivatives) of the polynomial's closed forms above which cells go in chunks",
    ),
    "folded_max_powers": _Knob(
        1 << 13,
        _non_negative_int,
        "a non-negative integer",
        "most monomials for which the polynomial's numpy forms fold the coefficients onto them (0: never)",
    ),
    "folded_chunk": _Knob(
        1 << 21, _positive_int, _POSITIVE, "monomial values per chunk of cells in the folded numpy forms"
    ),
    "compiled_kernels": _Knob(
        True,
        lambda v: isinstance(v, bool),
        "True or False",
        "serve closed-form L_d on compiled kernels (numba): the DEL kernel, folded polynomials, kinetic-potential MLPs "
        "(False: torch/autograd and numpy forms)",
    ),
    "compiled_numpy_models": _Knob(
        False,
        lambda v: isinstance(v, bool),
        "True or False",
        "also compile one 0+1D trajectory of an L_d with numpy closed forms (a polynomial): a build per model",
    ),
    "affine_check_every": _Knob(
        1,
        _positive_int,
        _POSITIVE,
        "slices between the DEL checks of the affine recurrence's slices (1: every slice; k: every k-th and the last)",
    ),
    "learn_linear_budget": _Knob(
        2**21,
        _positive_int,
        _POSITIVE,
        "basis-function derivatives (doubles) per streamed chunk of a linear model's training: sites x m x terms",
    ),
    "learn_neural_chunk": _Knob(
        2**16,
        _positive_int,
        _POSITIVE,
        "sites per chunk of iterative training (its autograd graph holds a few KiB per site)",
    ),
    "learn_share": _Knob(
        "chunks",
        lambda v: v in ("chunks", "fields"),
        "'chunks' or 'fields'",
        "what a process of several reads in training: chunk i ('chunks') or every chunk of field i ('fields') "
        "goes to rank i mod N",
    ),
    "selection_served_bytes": _Knob(
        256 * 2**20,
        _non_negative_int,
        "a non-negative integer",
        "bytes of the candidates' served fields that model selection keeps for the calibration (beyond: served again)",
    ),
}

_values: dict[str, Any] = {name: knob.default for name, knob in OPTIONS.items()}


def option(name: str) -> Any:
    """The value of knob ``name`` in effect now."""
    return _values[name]


def get_options() -> dict[str, Any]:
    """The knobs and their values in effect now (a copy: change them with :class:`set_options`)."""
    return dict(_values)


class set_options:  # noqa: N801  (a function to its users, as xarray's)
    """Set tuning knobs: for good when called, for the block when used in a ``with`` statement.

    >>> import latticedft as ldft
    >>> with ldft.set_options(serve_window_bytes=2**20):
    ...     ldft.get_options()["serve_window_bytes"]
    1048576
    >>> ldft.get_options()["serve_window_bytes"] == 32 * 2**20
    True
    """

    def __init__(self, **knobs: Any) -> None:
        for name, value in knobs.items():
            if name not in OPTIONS:
                raise InputError.at(name, f"no such tuning knob; set_options knows {', '.join(OPTIONS)}")
            if not OPTIONS[name].check(value):
                raise InputError.at(name, f"expected {OPTIONS[name].expects}, got {value!r}")
        self._previous = {name: _values[name] for name in knobs}
        _values.update(knobs)

    def __enter__(self) -> set_options:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        _values.update(self._previous)
