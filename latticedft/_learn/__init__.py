"""Learning ``L_d`` from observed fields with an explicit gauge fix.

The loss ``F = mean over interior sites of |EL_y|^2`` (Qin 2020, Eq. 7) is
ill-posed: ``L_d = const`` gives ``F = 0``. The gauge is fixed by the
unit-mass normalisation of the mixed time Hessian,
``mean over training cells of d^2 L_d / dpsi_x dpsi_{x+e_0} = -I / h_0^2``
(:mod:`._gauge`). Models linear in their parameters are then an
equality-constrained linear least-squares problem, solved exactly
(:mod:`._exact`); neural models are trained by L-BFGS or Adam with the
normalisation as a penalty, or by construction (:mod:`._neural`).
:mod:`._report` measures the result, :mod:`._api` is :func:`learn` itself.
"""

from __future__ import annotations

from ._api import OPTIMIZERS, learn
from ._data import check_model_lattice
from ._gauge import GAUGES
from ._noise import NoiseEstimate, denoise, estimate_noise
from ._report import LearnReport, diagnose

__all__ = ["learn", "LearnReport", "diagnose", "GAUGES", "OPTIMIZERS", "check_model_lattice"]
__all__ += ["NoiseEstimate", "denoise", "estimate_noise"]
