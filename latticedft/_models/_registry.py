"""The registry of model kinds: ``[model] kind = ...`` in case.toml and model files name its entries.

An entry (:class:`ModelKind`) pairs a kind's name with the factory that builds a model from its options and
the class whose constructor declares those options and whose class methods answer for the kind before any
model exists (the option checks and defaults, the memory check's parameter bound). A class is its own factory;
the ``mlp`` kind's factory picks one of two classes by the ``form`` option.

>>> registry = ModelRegistry()
>>> from latticedft import PolynomialLagrangian
>>> registry["polynomial"] = PolynomialLagrangian  # a class: its own factory
>>> registry["polynomial"](orders=(2, 2)).options()["orders"]
[2, 2]
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, MutableMapping
from dataclasses import dataclass
from typing import Any, Protocol

from .._contract import AbstractLagrangian

__all__ = ["KindClass", "ModelKind", "ModelRegistry"]


class KindClass(Protocol):
    """What the registry reads of a kind's class before any model is built: its constructor's signature and
    these class methods of :class:`AbstractLagrangian` (an abstract class, such as ``MLPLagrangian``, will do)."""

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
        return self._kinds[name]

    def __setitem__(self, name: str, entry: ModelKind | type[AbstractLagrangian]) -> None:
        if not isinstance(entry, ModelKind):
            if not (isinstance(entry, type) and issubclass(entry, AbstractLagrangian)):
                raise TypeError(
                    f"MODELS[{name!r}]: expected a subclass of latticedft.AbstractLagrangian, got {entry!r}"
                )
            entry = ModelKind(name, entry, entry)
        self._kinds[name] = entry

    def __delitem__(self, name: str) -> None:
        del self._kinds[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._kinds)

    def __len__(self) -> int:
        return len(self._kinds)

    def __repr__(self) -> str:
        return f"ModelRegistry({sorted(self._kinds)})"
