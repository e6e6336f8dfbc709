"""Type checks of model options, read from the constructors' annotations.

A model's options are its constructor's keyword arguments (``stencil`` aside): ``case.toml`` ``[model]``
tables and model files pass them by name. Their types are declared once, as the constructor's annotations;
:func:`option_checks` turns each annotation into a check of a TOML value, so a new model class needs no
separate option table. Values (ranges, choices) are then checked by the constructor itself.

>>> def __init__(self, hidden: list[int], scale: bool = True, *, stencil=None): ...
>>> checks = option_checks_of(__init__)
>>> sorted(checks), checks["hidden"]([4, 4])
(['hidden', 'scale'], [4, 4])
>>> checks["scale"]("yes")
Traceback (most recent call last):
...
latticedft._modeloptions.OptionTypeError: true or false
"""

from __future__ import annotations

import collections.abc
import functools
import inspect
import math
import types
import typing
from collections.abc import Callable
from typing import Any

__all__ = ["OptionTypeError", "option_checks_of"]

#: Constructor arguments that are not options (passed by the library, not by case.toml).
NOT_OPTIONS = ("self", "stencil")


class OptionTypeError(Exception):
    """A value does not have its option's type; ``expected`` says what would (``"an integer"``)."""

    def __init__(self, expected: str):
        super().__init__(expected)
        self.expected = expected


class _Check:
    """A check with its description in the singular and the plural (``an integer`` / ``integers``)."""

    def __init__(
        self, ok: Callable[[Any], bool], expected: str, plural: str, convert: Callable[[Any], Any] | None = None
    ):
        self.ok, self.expected, self.plural = ok, expected, plural
        self.convert = convert or (lambda v: v)

    def __call__(self, value: Any) -> Any:
        if not self.ok(value):
            raise OptionTypeError(self.expected)
        return self.convert(value)


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


_SIMPLE = {
    bool: _Check(lambda v: isinstance(v, bool), "true or false", "booleans"),
    int: _Check(_is_int, "an integer", "integers", int),
    float: _Check(_is_number, "a number", "numbers", float),
    str: _Check(lambda v: isinstance(v, str), "a string", "strings"),
}
_SEQUENCES = (list, tuple, collections.abc.Sequence)


def _sequence(item: _Check | None, length: int | None) -> _Check:
    """A TOML array (a list or tuple in Python) of ``length`` items (any number when ``None``)."""

    def ok(v: Any) -> bool:
        return (
            isinstance(v, (list, tuple))
            and (length is None or len(v) == length)
            and (item is None or all(item.ok(i) for i in v))
        )

    what = "a list" + (f" of {length}" if length is not None else "")
    expected = f"{what} of {item.plural}" if item is not None else what
    return _Check(ok, expected, "lists", lambda v: [item.convert(i) if item else i for i in v])


def _union(checks: list[_Check], none: bool) -> _Check:
    expected = " or ".join(dict.fromkeys(c.expected for c in checks))

    def ok(v: Any) -> bool:
        return (none and v is None) or any(c.ok(v) for c in checks)

    def convert(v: Any) -> Any:
        return v if v is None else next(c for c in checks if c.ok(v)).convert(v)

    return _Check(ok, expected, "values", convert)


def _check_of(annotation: Any) -> _Check | None:
    """The check an annotation stands for; ``None`` where it says nothing checkable (any value passes)."""
    if annotation in _SIMPLE:
        return _SIMPLE[annotation]
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Literal:
        return _Check(lambda v: v in args, " or ".join(repr(a) for a in args), "values")
    if origin in _SEQUENCES:
        if origin is tuple and args and args[-1] is not Ellipsis:
            items = {_check_of(a) for a in args}
            return _sequence(items.pop() if len(items) == 1 else None, len(args))
        return _sequence(_check_of(args[0]) if args else None, None)
    if origin in (typing.Union, types.UnionType):
        maybe = [_check_of(a) for a in args if a is not type(None)]
        checks = [c for c in maybe if c is not None]
        if len(checks) < len(maybe):
            return None
        return _union(checks, type(None) in args)
    return None


@functools.cache
def option_checks_of(init: Callable[..., Any]) -> dict[str, Callable[[Any], Any]]:
    """Option name -> check, from a constructor's signature and annotations (unannotated options: any value).

    A check returns the value (integers, numbers and lists normalised) or raises :class:`OptionTypeError`.
    """
    # an annotation that does not resolve checks nothing rather than refusing the class
    try:
        hints = typing.get_type_hints(init)
    except (NameError, TypeError, AttributeError, SyntaxError):
        hints = {}
    out: dict[str, Callable[[Any], Any]] = {}
    for name, p in inspect.signature(init).parameters.items():
        if name in NOT_OPTIONS or p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
            continue
        out[name] = _check_of(hints.get(name)) or _any
    return out


def _any(value: Any) -> Any:
    return value
