"""Paper oscillators: the two one-degree-of-freedom examples of Qin 2020.

* Example 1 (Eq. ex1ODE), a nonlinear oscillator with position-dependent
  mass: :func:`oscillator_sin` and its energy :func:`oscillator_sin_energy`.
* Example 2 (Eq. ex2ODE), oscillation in a potential with wells:
  :func:`oscillator_wells`, :func:`wells_potential` and
  :func:`oscillator_wells_energy`.

Reference: H. Qin, "Machine learning and serving of discrete field theories",
Sci. Rep. 10, 19329 (2020). Solutions are DOP853 solves with
``rtol = atol = 1e-12`` sampled at the lattice times (see
:mod:`latticedft.systems._fields`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import xarray as xr
from numpy.typing import ArrayLike

from latticedft._errors import InputError
from latticedft.systems._fields import (
    ODE_ATOL,
    ODE_RTOL,
    _check_finite,
    _check_lattice_1d,
    _FloatArray,
    _solve,
    make_field,
)

__all__ = [
    "oscillator_sin",
    "oscillator_sin_energy",
    "oscillator_wells",
    "oscillator_wells_energy",
    "wells_potential",
]

# ----------------------------------------------------------------------------
# Paper Example 1
# ----------------------------------------------------------------------------

_SIN_K = math.pi**2 / 400.0  # potential coefficient: L = (1 + sin psi) psi'^2 - K psi^2


def _ode_fields(
    rhs: Callable[[float, _FloatArray], list[float]],
    start: tuple[float, float],
    n: int,
    dt: float,
    t0: float,
    what: str,
    equation: str,
    long_name: str,
    return_velocity: bool,
) -> xr.DataArray | tuple[xr.DataArray, xr.DataArray]:
    """A one-degree-of-freedom ODE ``(psi, psi')' = rhs`` solved from ``start`` and sampled at
    ``t0 + i dt``: ``psi`` (and ``psi'`` with ``return_velocity``) as fields whose ``source`` names the
    function ``what``, its ``equation`` and the solver."""
    t = t0 + dt * np.arange(n, dtype=np.float64)
    sol = _solve(rhs, list(start), t, what=what)
    src = (
        f"latticedft.systems.{what}: {equation}, psi0={start[0]!r}, dpsi0={start[1]!r}; "
        f"solve_ivp DOP853 rtol={ODE_RTOL:g} atol={ODE_ATOL:g}"
    )
    psi = make_field(
        sol.y[0], ("t",), spacing=dt, origin=t0, attrs={"long_name": long_name, "units": "1", "source": src}
    )
    if not return_velocity:
        return psi
    vel = make_field(
        sol.y[1],
        ("t",),
        spacing=dt,
        origin=t0,
        name="dpsi",
        attrs={"long_name": "d psi / d t", "units": "1", "source": src},
    )
    return psi, vel


def _sin_rhs(t: float, y: _FloatArray) -> list[float]:
    psi, dpsi = y
    return [dpsi, -(dpsi * dpsi * math.cos(psi) + 2.0 * _SIN_K * psi) / (2.0 * (math.sin(psi) + 1.0))]


def oscillator_sin_energy(psi: ArrayLike, dpsi: ArrayLike) -> Any:
    """Energy of paper Example 1: ``E = (1 + sin psi) psi'^2 + pi^2/400 psi^2``.

    ``E = psi' dL/dpsi' - L`` for ``L = (1 + sin psi) psi'^2 - pi^2/400 psi^2``;
    conserved by :func:`oscillator_sin`. Works elementwise on numbers, arrays
    and DataArrays.

    Examples
    --------
    >>> round(float(oscillator_sin_energy(1.2, 0.0)), 8)
    0.03553058
    """
    return (1.0 + np.sin(psi)) * np.square(dpsi) + _SIN_K * np.square(psi)


def oscillator_sin(
    psi0: float,
    dpsi0: float = 0.0,
    n: int = 51,
    dt: float = 1.0,
    *,
    t0: float = 0.0,
    return_velocity: bool = False,
) -> xr.DataArray | tuple[xr.DataArray, xr.DataArray]:
    r"""Paper Example 1 (Qin 2020, Eq. ex1ODE): a nonlinear oscillator.

    .. math:: 2(\sin\psi + 1)\,\psi'' + \psi'^2\cos\psi + \frac{\pi^2}{200}\psi = 0,

    the Euler–Lagrange equation of
    :math:`L = (1 + \sin\psi)\psi'^2 - \frac{\pi^2}{400}\psi^2`. The paper
    trains on ``psi0 = 1.2`` and tests ``psi0 = -0.6`` and ``0.1``, all with
    ``dpsi0 = 0``, ``n = 51``, ``dt = 1``.

    Solved with DOP853 (``rtol = atol = 1e-12``) and sampled at
    ``t = t0 + i*dt``, ``i = 0 .. n-1``.

    Parameters
    ----------
    psi0, dpsi0
        Initial value and derivative at ``t0``.
    n
        Number of time slices (>= 2).
    dt
        Time step of the lattice.
    t0
        First time.
    return_velocity
        Also return ``psi'`` at the same times (as a second DataArray).

    Raises
    ------
    InputError
        If the energy reaches the singular mass point: the motion then hits
        ``psi = -pi/2`` where ``1 + sin psi = 0`` (needs
        ``E < pi^4/1600``).

    Examples
    --------
    >>> psi = oscillator_sin(1.2)
    >>> psi.dims, psi.shape, float(psi[0]), float(psi["t"][-1])
    (('t',), (51,), 1.2, 50.0)
    """
    psi0 = _check_finite(psi0, "psi0")
    dpsi0 = _check_finite(dpsi0, "dpsi0")
    t0 = _check_finite(t0, "t0")
    _check_lattice_1d(n, dt)
    energy = float(oscillator_sin_energy(psi0, dpsi0))
    if not (-0.5 * math.pi < psi0 < 0.5 * math.pi) or energy >= _SIN_K * (0.5 * math.pi) ** 2:
        raise InputError(
            f"psi0, dpsi0: energy {energy:.4g} reaches the singular point psi = -pi/2 "
            f"(need |psi| < pi/2 throughout, i.e. E < {_SIN_K * (0.5 * math.pi) ** 2:.4g})"
        )
    return _ode_fields(
        _sin_rhs,
        (psi0, dpsi0),
        n,
        dt,
        t0,
        "oscillator_sin",
        "2(sin psi+1)psi''+psi'^2 cos psi+pi^2/200 psi=0",
        "oscillator displacement (Qin 2020 Example 1)",
        return_velocity,
    )


# ----------------------------------------------------------------------------
# Paper Example 2
# ----------------------------------------------------------------------------


def wells_potential(psi: ArrayLike) -> Any:
    """Potential of paper Example 2: ``V(psi) = -0.015 [cos(psi^2 - 1) + 0.2 psi]``.

    The equation of motion :func:`oscillator_wells` solves,
    ``psi'' - 0.03 [sin(1 - psi^2) psi + 0.1] = 0``, is exactly
    ``psi'' = -V'(psi)``: ``V'(psi) = 0.03 sin(psi^2 - 1) psi - 0.003``
    (checked numerically in the tests). A large well spans ``|psi| < 1.6``
    with two secondary wells, ``(-1.3, -0.1)`` and ``(-0.1, 1.5)``.

    Examples
    --------
    >>> round(float(wells_potential(0.0)), 8)
    -0.00810453
    """
    if not isinstance(psi, xr.DataArray):
        psi = np.asarray(psi, dtype=np.float64)
    return -0.015 * (np.cos(np.square(psi) - 1.0) + 0.2 * psi)


def _wells_rhs(t: float, y: _FloatArray) -> list[float]:
    psi, dpsi = y
    return [dpsi, 0.03 * (math.sin(1.0 - psi * psi) * psi + 0.1)]


def oscillator_wells_energy(psi: ArrayLike, dpsi: ArrayLike) -> Any:
    """Energy of paper Example 2: ``E = psi'^2 / 2 + V(psi)``, see :func:`wells_potential`.

    Examples
    --------
    >>> round(float(oscillator_wells_energy(1.7, 0.0)), 8)
    -0.00039284
    """
    return 0.5 * np.square(dpsi) + wells_potential(psi)


def oscillator_wells(
    psi0: float,
    dpsi0: float = 0.0,
    n: int = 51,
    dt: float = 1.0,
    *,
    t0: float = 0.0,
    return_velocity: bool = False,
) -> xr.DataArray | tuple[xr.DataArray, xr.DataArray]:
    r"""Paper Example 2 (Qin 2020, Eq. ex2ODE): oscillation in a potential with wells.

    .. math:: \psi'' - 0.03\,[\sin(1 - \psi^2)\,\psi + 0.1] = 0,

    i.e. :math:`\psi'' = -V'(\psi)` with
    :math:`V = -0.015[\cos(\psi^2 - 1) + 0.2\psi]` (:func:`wells_potential`),
    the Euler–Lagrange equation of :math:`L = \psi'^2/2 - V(\psi)`. The paper
    trains on ``psi0 = 1.7`` (the large well) with ``dpsi0 = 0``, ``n = 51``,
    ``dt = 1``, and tests oscillations in the two small wells.

    Solved with DOP853 (``rtol = atol = 1e-12``) and sampled at
    ``t = t0 + i*dt``, ``i = 0 .. n-1``. Arguments as in
    :func:`oscillator_sin`.

    Examples
    --------
    >>> psi, dpsi = oscillator_wells(1.7, return_velocity=True)
    >>> psi.shape, float(psi[0]), float(dpsi[0])
    ((51,), 1.7, 0.0)
    """
    psi0 = _check_finite(psi0, "psi0")
    dpsi0 = _check_finite(dpsi0, "dpsi0")
    t0 = _check_finite(t0, "t0")
    _check_lattice_1d(n, dt)
    return _ode_fields(
        _wells_rhs,
        (psi0, dpsi0),
        n,
        dt,
        t0,
        "oscillator_wells",
        "psi''-0.03[sin(1-psi^2)psi+0.1]=0",
        "oscillator displacement (Qin 2020 Example 2)",
        return_velocity,
    )
