"""The gauge fixes: each written once, in the three forms the learner needs.

``L_d`` is only defined up to a factor (and null Lagrangians): the DEL loss alone is minimised by
``L_d = const``. A gauge fixes the factor by a condition on the mean over the training cells of the mixed
time Hessian ``M = d^2 L_d / dpsi_x dpsi_{x+e_0}``. Each gauge gives

- :meth:`Gauge.residual`: how far a model is from the condition (``gauge_residual`` of reports);
- :meth:`Gauge.penalty`: the same as a differentiable penalty (neural training);
- :meth:`Gauge.constraint`: the condition as linear equations on the coefficients of a linear model
  (the exact solve).
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
import torch

from .._contract import GaugeName
from .._errors import InputError

__all__ = ["Gauge", "UnitMass", "Trace", "NoGauge", "GAUGES", "AUTO", "AUTO_CANDIDATES", "gauge_named"]


class Gauge:
    """A condition on ``mbar``, the mean mixed time Hessian ``(m, m)`` over the training cells."""

    name: ClassVar[str]
    #: False for ``none``: no condition (no penalty, no constraint rows).
    fixes: ClassVar[bool] = True

    def residual(self, mbar: torch.Tensor, h0: float) -> float:
        """How far ``mbar`` is from the condition (0 when it holds)."""
        raise NotImplementedError

    def penalty(self, mbar: torch.Tensor, h0: float) -> torch.Tensor | None:
        """A differentiable penalty, zero where the condition holds; ``None`` where nothing is fixed."""
        raise NotImplementedError

    def constraint(self, mean: np.ndarray, h0: float) -> tuple[np.ndarray, np.ndarray] | None:
        """Rows ``G coef = g`` of the condition for ``mbar = sum_c coef[c] mean[c]`` (``mean``: ``(C, m, m)``,
        one mean mixed Hessian per basis function); ``None`` where nothing is fixed."""
        raise NotImplementedError


class UnitMass(Gauge):
    """``h_0^2 mbar = -I``: every entry, the unit mass of a kinetic term ``|g_0|^2 / (2 h_0^2)``."""

    name = GaugeName.UNIT_MASS.value

    def _defect(self, mbar: torch.Tensor, h0: float) -> torch.Tensor:
        return h0**2 * mbar + torch.eye(mbar.shape[0], dtype=mbar.dtype)

    def residual(self, mbar: torch.Tensor, h0: float) -> float:
        """``||h_0^2 mbar + I||_F / sqrt(m)``."""
        return float(torch.linalg.norm(self._defect(mbar, h0)) / math.sqrt(mbar.shape[0]))

    def penalty(self, mbar: torch.Tensor, h0: float) -> torch.Tensor:
        return (self._defect(mbar, h0) ** 2).sum() / mbar.shape[0]

    def constraint(self, mean: np.ndarray, h0: float) -> tuple[np.ndarray, np.ndarray]:
        c, m = mean.shape[0], mean.shape[1]
        return mean.reshape(c, m * m).T * h0**2, -np.eye(m).reshape(-1)


class Trace(Gauge):
    """``h_0^2 tr(mbar) / m = -1``: only the trace, for components of unequal masses."""

    name = GaugeName.TRACE.value

    def _defect(self, mbar: torch.Tensor, h0: float) -> torch.Tensor:
        return h0**2 * torch.trace(mbar) / mbar.shape[0] + 1

    def residual(self, mbar: torch.Tensor, h0: float) -> float:
        """``|h_0^2 tr(mbar) / m + 1|``."""
        return abs(float(self._defect(mbar, h0)))

    def penalty(self, mbar: torch.Tensor, h0: float) -> torch.Tensor:
        return self._defect(mbar, h0) ** 2

    def constraint(self, mean: np.ndarray, h0: float) -> tuple[np.ndarray, np.ndarray]:
        return np.trace(mean, axis1=1, axis2=2)[None, :] * h0**2, np.array([-float(mean.shape[1])])


class NoGauge(Gauge):
    """No fix: the learner drifts towards ``L_d = const``. Reports measure it against the unit mass (the
    collapse shows as a residual near 1)."""

    name = GaugeName.NONE.value
    fixes = False

    def residual(self, mbar: torch.Tensor, h0: float) -> float:
        return UnitMass().residual(mbar, h0)

    def penalty(self, mbar: torch.Tensor, h0: float) -> None:
        return None

    def constraint(self, mean: np.ndarray, h0: float) -> None:
        return None


_BY_NAME: dict[str, Gauge] = {g.name: g for g in (UnitMass(), Trace(), NoGauge())}

#: The choice of :func:`latticedft.learn` that is a rule, not a gauge: fit the candidates
#: (:data:`AUTO_CANDIDATES`) and keep one (see ``latticedft._learn._api.AUTO_RULE``).
AUTO = "auto"
#: The gauges ``auto`` chooses from, in order of preference.
AUTO_CANDIDATES = (UnitMass.name, Trace.name)

#: Gauge choices of :func:`latticedft.learn`: ``unit-mass`` (mean mixed Hessian = -I/h0^2, every entry),
#: ``trace`` (only its trace, for unequal masses or velocity-linear terms such as a magnetic field),
#: ``none`` (no fix: collapses) and ``auto`` (the better of unit-mass and trace, by the training residual).
GAUGES = (*_BY_NAME, AUTO)


def gauge_named(name: str) -> Gauge:
    """The gauge called ``name`` (one of :data:`GAUGES` but ``auto``, which is a rule of ``learn``)."""
    if name == AUTO:
        raise InputError.at(
            "gauge", "'auto' chooses a gauge while learning; measure a learned model with its report's gauge"
        )
    if name not in _BY_NAME:
        raise InputError.at("gauge", f"expected one of {list(GAUGES)}, got {name!r}")
    return _BY_NAME[name]
