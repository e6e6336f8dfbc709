"""Models of the discrete Lagrangian density, behind one abstract interface."""

from __future__ import annotations

from ._analytic import AnalyticLagrangian
from ._base import AbstractLagrangian
from ._mlp import PRESETS, MLPLagrangian
from ._polynomial import PolynomialLagrangian

#: ``[model] kind = ...`` in case.toml and model files name these classes.
MODELS: dict[str, type[AbstractLagrangian]] = {
    "polynomial": PolynomialLagrangian,
    "mlp": MLPLagrangian,
}

__all__ = ["AbstractLagrangian", "AnalyticLagrangian", "MLPLagrangian", "PolynomialLagrangian", "MODELS", "PRESETS"]
