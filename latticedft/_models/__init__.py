"""Models of the discrete Lagrangian density, behind one abstract interface.

A new model kind is one class (a subclass of :class:`AbstractLagrangian`, or of :class:`LinearLagrangian`
when ``L_d`` is linear in its parameters) plus one line in :data:`MODELS` (``MODELS[kind] = TheClass``).
A kind from another package needs no line: ``[model] kind = "mypkg.models:MyLagrangian"`` or the name of
its entry point in group ``latticedft.models`` (see :mod:`latticedft._plugins`).
"""

from __future__ import annotations

from .._contract import AbstractLagrangian
from ._analytic import AnalyticLagrangian
from ._ensemble import EnsembleLagrangian
from ._features import FeatureLagrangian
from ._library import Library
from ._linear import LinearLagrangian
from ._mlp import (
    PRESETS,
    FreeMLPLagrangian,
    KineticPotentialMLPLagrangian,
    MLPLagrangian,
    mlp_lagrangian,
)
from ._polynomial import PolynomialLagrangian
from ._registry import MODELS, ModelKind, ModelRegistry
from ._sparse import SparseLagrangian

MODELS["polynomial"] = PolynomialLagrangian
MODELS["mlp"] = ModelKind("mlp", mlp_lagrangian, MLPLagrangian)  # the form option picks the class
MODELS["features"] = FeatureLagrangian
MODELS["sparse"] = SparseLagrangian

__all__ = [
    "AbstractLagrangian",
    "AnalyticLagrangian",
    "EnsembleLagrangian",
    "FeatureLagrangian",
    "FreeMLPLagrangian",
    "KineticPotentialMLPLagrangian",
    "Library",
    "LinearLagrangian",
    "MLPLagrangian",
    "PolynomialLagrangian",
    "SparseLagrangian",
    "MODELS",
    "ModelKind",
    "ModelRegistry",
    "PRESETS",
]
