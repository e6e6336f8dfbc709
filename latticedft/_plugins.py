"""Extensions from other packages: an object named by an import path or by an entry point.

The registries of model kinds (:data:`latticedft.MODELS`) and of export formats
(:data:`latticedft.io.exporters.EXPORTERS`) look a name up here only when they hold no entry of that name,
so a case that uses only what latticedft holds never scans the installed packages. A name is either

- an import path ``"package.module:Name"`` (as ``invariant = "module:function"`` in case.toml), imported
  as it stands; or
- the name of an entry point of the registry's group (:data:`MODEL_GROUP`, :data:`EXPORTER_GROUP`), which
  a package declares in its ``pyproject.toml``, as xarray's backends do::

      [project.entry-points."latticedft.models"]
      my-kind = "mypkg.models:MyLagrangian"

A name that is neither gives ``None`` (the registry reports it as unknown); a name whose import fails gives
a one-line :class:`InputError` that names it, its group and the cause.

>>> load("no-such-name", MODEL_GROUP, "model.kind") is None
True
>>> load("no_such_module:Thing", MODEL_GROUP, "model.kind")  # doctest: +ELLIPSIS
Traceback (most recent call last):
...
latticedft._errors.InputError: model.kind: cannot import 'no_such_module:Thing' (ModuleNotFoundError: ...)
"""

from __future__ import annotations

import importlib
import re
from importlib.metadata import EntryPoint, entry_points

from ._errors import InputError

__all__ = ["MODEL_GROUP", "EXPORTER_GROUP", "is_import_path", "load", "entry_point_names", "describe"]

#: The entry-point group of model kinds: ``name = "module:Class"`` (an ``AbstractLagrangian`` subclass or a
#: ``ModelKind``).
MODEL_GROUP = "latticedft.models"
#: The entry-point group of export formats: ``name = "module:Class"`` (an ``Exporter`` subclass).
EXPORTER_GROUP = "latticedft.exporters"

_IMPORT_PATH = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)*:[A-Za-z_]\w*(\.[A-Za-z_]\w*)*$")


def is_import_path(name: str) -> bool:
    """True when ``name`` has the form ``package.module:Name``."""
    return bool(_IMPORT_PATH.match(name))


def _cause(exc: BaseException) -> str:
    """``ExceptionType: first line of its message`` (at most 160 characters)."""
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0][:160]}" if text else type(exc).__name__


def _import(path: str) -> object:
    """The object at ``package.module:Name`` (``Name`` may be dotted: an attribute of an attribute)."""
    module, _, attr = path.partition(":")
    obj: object = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def describe(obj: object) -> str:
    """What ``obj`` is, for a message about a plugin of the wrong type: ``the class mypkg.models.Thing``."""
    if isinstance(obj, type) or callable(obj):
        what = "class" if isinstance(obj, type) else type(obj).__name__
        return f"the {what} {getattr(obj, '__module__', '?')}.{getattr(obj, '__qualname__', repr(obj))}"
    return f"an object of type {type(obj).__name__}"


def _entry_point(name: str, group: str) -> EntryPoint | None:
    found = entry_points(group=group, name=name)
    return next(iter(found), None)


def entry_point_names(group: str) -> list[str]:
    """The names of the entry points of ``group`` in the installed packages (none loaded), sorted."""
    return sorted({ep.name for ep in entry_points(group=group)})


def load(name: str, group: str, key: str) -> object | None:
    """The object ``name`` stands for: an import path, else an entry point of ``group``; ``None`` when it is
    neither. A failing import is an :class:`InputError` about ``key`` naming ``name`` and the cause."""
    if is_import_path(name):
        try:
            return _import(name)
        except Exception as exc:
            raise InputError.at(key, f"cannot import {name!r} ({_cause(exc)})") from None
    ep = _entry_point(name, group)
    if ep is None:
        return None
    try:
        loaded: object = ep.load()
        return loaded
    except Exception as exc:
        raise InputError.at(
            key, f"the entry point {name!r} of group {group!r} ({ep.value}) failed to load ({_cause(exc)})"
        ) from None
