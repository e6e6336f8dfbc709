"""Models of the discrete Lagrangian density, behind one abstract interface.

A new model is one class (a subclass of :class:`AbstractLagrangian`, or of :class:`LinearLagrangian` when
``L_d`` is linear in its parameters) plus one line in :data:`MODELS`.
"""

from __future__ import annotations

from ._analytic import AnalyticLagrangian
from ._base import AbstractLagrangian
from ._ensemble import EnsembleLagrangian
from ._features import FeatureLagrangian
from ._linear import LinearLagrangian
from ._mlp import (
    PRESETS,
    FreeMLPLagrangian,
    KineticPotentialMLPLagrangian,
    MLPLagrangian,
)
from ._polynomial import PolynomialLagrangian

#: ``[model] kind = ...`` in case.toml and model files name these classes (the key is the class's ``kind``).
MODELS: dict[str, type[AbstractLagrangian]] = {
    "polynomial": PolynomialLagrangian,
    "mlp": MLPLagrangian,  # type: ignore[type-abstract]  # abstract, but its __new__ builds the concrete form class
    "features": FeatureLagrangian,
}

__all__ = [
    "AbstractLagrangian",
    "AnalyticLagrangian",
    "EnsembleLagrangian",
    "FeatureLagrangian",
    "FreeMLPLagrangian",
    "KineticPotentialMLPLagrangian",
    "LinearLagrangian",
    "MLPLagrangian",
    "PolynomialLagrangian",
    "MODELS",
    "PRESETS",
]
