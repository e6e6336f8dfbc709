"""The registry of model kinds: ``[model] kind = ...`` in case.toml and model files name its entries.

An entry (:class:`ModelKind`) pairs a kind's name with the factory that builds a model from its options and
the class whose constructor declares those options and whose class methods answer for the kind before any
model exists (the option checks and defaults, the memory check's parameter bound). A class is its own factory;
the ``mlp`` kind's factory picks one of two classes by the ``form`` option.

A name the registry does not hold may come from another package (:mod:`latticedft._plugins`): an import
path ``"mypkg.models:MyLagrangian"`` or the name of an entry point of group ``latticedft.models``. The
registry loads it on first use, keeps it under that name, and model files record that name
(:meth:`ModelRegistry.name_of`), so :func:`latticedft.load_model` finds the kind again.

>>> registry = ModelRegistry()
>>> from latticedft import PolynomialLagrangian
>>> registry["polynomial"] = PolynomialLagrangian  # a class: its own factory
>>> registry["polynomial"](orders=(2, 2)).options()["orders"]
[2, 2]
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, MutableMapping
from dataclasses import dataclass, replace
from typing import Any, Protocol

from .._contract import AbstractLagrangian
from .._errors import InputError
from .._plugins import MODEL_GROUP, describe, entry_point_names, load

__all__ = ["KindClass", "ModelKind", "ModelRegistry", "MODELS"]


class KindClass(Protocol):
    """What the registry reads of a kind's class before any model is built: its constructor's signature and
    these class methods of :class:`AbstractLagrangian` (an abstract class, such as ``MLPLagrangian``, will do)."""

    #: True when the kind's ``L_d`` is linear in its parameters (learned by the exact solve).
    linear: bool

    def option_checks(self) -> dict[str, Callable[[Any], Any]]: ...

    def option_defaults(self) -> dict[str, Any]: ...

    def parameter_lower_bound(self, options: Mapping[str, Any], n: int, m: int) -> tuple[int, str] | None: ...


@dataclass(frozen=True)
class ModelKind:
    """One model kind: ``kind(**options, stencil=...)`` builds a model of it.

    ``factory`` builds the model (a class, or a function choosing among classes); ``model_class`` is the
    class whose constructor's annotated keywords are the kind's options and whose class methods are its
    capabilities before a model is built (:meth:`AbstractLagrangian.option_checks`,
    :meth:`AbstractLagrangian.parameter_lower_bound`).
    """

    name: str
    factory: Callable[..., AbstractLagrangian]
    model_class: KindClass

    def __call__(self, *args: Any, **options: Any) -> AbstractLagrangian:
        return self.factory(*args, **options)

    def option_checks(self) -> dict[str, Callable[[Any], Any]]:
        """Option name -> type check of a ``case.toml`` value (see :meth:`AbstractLagrangian.option_checks`)."""
        return self.model_class.option_checks()

    def option_defaults(self) -> dict[str, Any]:
        """Option name -> its default (see :meth:`AbstractLagrangian.option_defaults`)."""
        return self.model_class.option_defaults()

    def parameter_lower_bound(self, options: Mapping[str, Any], n: int, m: int) -> tuple[int, str] | None:
        """See :meth:`AbstractLagrangian.parameter_lower_bound`."""
        return self.model_class.parameter_lower_bound(options, n, m)


class ModelRegistry(MutableMapping[str, ModelKind]):
    """Kind name -> :class:`ModelKind`. Assigning a model class registers it as its own factory:
    ``MODELS["my-kind"] = MyLagrangian`` is the one line a new kind needs."""

    def __init__(self) -> None:
        self._kinds: dict[str, ModelKind] = {}

    def __getitem__(self, name: str) -> ModelKind:
        """The kind ``name``: registered, else loaded from another package (``KeyError`` when none has it;
        a one-line :class:`InputError` about ``model.kind`` when loading it fails)."""
        entry = self._kinds.get(name)
        if entry is None:
            entry = self._plugin(name)
        return entry

    def __setitem__(self, name: str, entry: ModelKind | type[AbstractLagrangian]) -> None:
        checked = _entry(name, entry)
        if checked is None:
            raise TypeError(f"MODELS[{name!r}]: {_EXPECTED}, got {entry!r}")
        self._kinds[name] = checked

    def _plugin(self, name: str) -> ModelKind:
        """The kind ``name`` from an import path or an entry point, kept under ``name``; ``KeyError`` if none."""
        found = load(name, MODEL_GROUP, "model.kind") if isinstance(name, str) else None
        if found is None:
            raise KeyError(name)
        entry = _entry(name, found)
        if entry is None:
            raise InputError.at("model.kind", f"{name!r} gives {describe(found)}; {_EXPECTED}")
        self._kinds[name] = entry
        return entry

    def names(self) -> list[str]:
        """The kinds a case may name without an import path: those registered and the entry points of the
        installed packages (none loaded), sorted; for messages about an unknown kind."""
        return sorted({*self._kinds, *entry_point_names(MODEL_GROUP)})

    def name_of(self, model: AbstractLagrangian) -> str:
        """The name under which this registry builds ``model``'s kind: its ``kind``, unless the registry holds
        its very class under another name only (a kind from an import path); what model files record. A
        subclass of a registered class keeps its own ``kind``: it is never recorded as its base's."""
        if model.kind in self._kinds:
            return model.kind
        for name, entry in self._kinds.items():
            if entry.model_class is type(model):
                return name
        return model.kind

    def __delitem__(self, name: str) -> None:
        del self._kinds[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._kinds)

    def __len__(self) -> int:
        return len(self._kinds)

    def __repr__(self) -> str:
        return f"ModelRegistry({sorted(self._kinds)})"


def _entry(name: str, entry: object) -> ModelKind | None:
    """``entry`` as the registry's entry ``name``: a :class:`ModelKind` (renamed), or a model class as its own
    factory; ``None`` for anything else."""
    if isinstance(entry, ModelKind):
        return entry if entry.name == name else replace(entry, name=name)
    if isinstance(entry, type) and issubclass(entry, AbstractLagrangian):
        return ModelKind(name, entry, entry)
    return None


_EXPECTED = "expected a subclass of latticedft.AbstractLagrangian or a latticedft.ModelKind"


#: ``[model] kind = ...`` in case.toml and model files name these kinds (the key is the models' ``kind``);
#: :mod:`latticedft._models` registers the kinds latticedft holds.
MODELS = ModelRegistry()
