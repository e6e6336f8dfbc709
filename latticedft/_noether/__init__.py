"""Symmetries and Noether charges of discrete Lagrangians (see docs/symmetries.md).

* :func:`symmetries`: invariance residuals of ``L_d`` under built-in or given symmetries, over data;
* :func:`discover_symmetries`: the generators ``M psi + w`` of affine internal symmetries, fitted;
* :func:`noether_charge`, :func:`discrete_energy`, :func:`noether_charges`: the discrete momentum maps
  and the discrete energy along a (served) field, as DataArrays over time.
"""

from __future__ import annotations

from ._charges import discrete_energy, noether_charge, noether_charges, relative_drift
from ._discovery import DiscoveryReport, discover_symmetries
from ._group import Symmetry
from ._invariance import SymmetryReport, builtin_symmetries, symmetries

__all__ = [
    "DiscoveryReport",
    "Symmetry",
    "SymmetryReport",
    "builtin_symmetries",
    "discover_symmetries",
    "discrete_energy",
    "noether_charge",
    "noether_charges",
    "relative_drift",
    "symmetries",
]
