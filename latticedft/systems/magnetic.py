"""A charged particle in a uniform magnetic field: a Lagrangian linear in the velocity.

.. math:: L = \\tfrac12 |\\dot{\\mathbf q}|^2 + \\tfrac{B}{2}\\,(x \\dot y - y \\dot x)

(unit mass and charge, ``B`` along ``z``, symmetric gauge of the vector potential ``A = B (-y, x) / 2``).
The Euler–Lagrange equations are the Lorentz force ``x'' = B y'``, ``y'' = -B x'``: uniform circular
motion with the cyclotron frequency ``B`` (clockwise for ``B > 0``), radius ``|v| / |B|`` and centre
``q_0 + (v_y, -v_x) / B``. :func:`charged_particle` samples that closed form on the lattice times.

The magnetic term makes the mixed time Hessian of a discrete ``L_d`` non-symmetric (an antisymmetric
``B``-part beside the unit-mass ``-I / h^2``): the ``unit-mass`` gauge of :func:`latticedft.learn`
(every entry of the mean mixed Hessian fixed) cannot describe it, the ``trace`` gauge (and ``auto``)
can.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import xarray as xr
from numpy.typing import ArrayLike

from latticedft._errors import InputError
from latticedft.systems._fields import _check_finite, make_field

__all__ = ["charged_particle", "cyclotron_energy"]


def _pair(v: Sequence[float], name: str) -> tuple[float, float]:
    try:
        a, b = (float(x) for x in v)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected two numbers (x, y), got {v!r}") from None
    if not (math.isfinite(a) and math.isfinite(b)):
        raise InputError(f"{name}: expected finite numbers, got {v!r}")
    return a, b


def charged_particle(
    q0: Sequence[float] = (0.0, 0.0),
    v0: Sequence[float] = (1.0, 0.0),
    B: float = 1.0,
    n: int = 101,
    dt: float = 0.1,
    *,
    t0: float = 0.0,
    return_velocity: bool = False,
) -> xr.DataArray | tuple[xr.DataArray, xr.DataArray]:
    r"""The exact orbit of a charged particle in a uniform magnetic field ``B`` (along z).

    .. math::

        x(t) = x_0 + \frac{v_x \sin Bt + v_y (1 - \cos Bt)}{B},\qquad
        y(t) = y_0 + \frac{v_y \sin Bt - v_x (1 - \cos Bt)}{B}

    (``t`` counted from ``t0``), the solution of ``x'' = B y'``, ``y'' = -B x'`` — the Euler–Lagrange
    equations of ``L = |v|^2/2 + (B/2)(x v_y - y v_x)``. ``B = 0`` gives the straight line.

    Parameters
    ----------
    q0, v0
        Position and velocity ``(x, y)`` at ``t0``.
    B
        Field strength (the cyclotron frequency; the period is ``2 pi / |B|``).
    n, dt
        Number of time slices and time step.
    t0
        First time.
    return_velocity
        Also return the velocity (a DataArray named ``"velocity"``).

    Returns
    -------
    xarray.DataArray
        ``psi(t, component)`` with ``component = ["x", "y"]``.

    Examples
    --------
    >>> orbit = charged_particle((0.0, 0.0), (1.0, 0.0), B=2.0, n=5, dt=0.1)
    >>> orbit.dims, orbit.shape
    (('t', 'component'), (5, 2))
    >>> centre = np.array([0.0, -0.5])  # q0 + (v_y, -v_x) / B
    >>> bool(np.allclose(np.hypot(*(orbit.values - centre).T), 0.5))  # radius |v| / B
    True
    """
    x0, y0 = _pair(q0, "q0")
    vx, vy = _pair(v0, "v0")
    B = _check_finite(B, "B")
    if not (isinstance(n, int) and not isinstance(n, bool) and n >= 2):
        raise InputError(f"n: expected an integer >= 2, got {n!r}")
    if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
        raise InputError(f"dt: expected a positive number, got {dt!r}")
    t0 = _check_finite(t0, "t0")
    s = dt * np.arange(n, dtype=np.float64)
    if B == 0.0:
        sin_b, one_minus_cos = s, np.zeros_like(s)  # (sin Bs)/B -> s, (1 - cos Bs)/B -> 0
        cos, sin = np.ones_like(s), np.zeros_like(s)
    else:
        sin, cos = np.sin(B * s), np.cos(B * s)
        sin_b, one_minus_cos = sin / B, (1.0 - cos) / B
    x = x0 + vx * sin_b + vy * one_minus_cos
    y = y0 + vy * sin_b - vx * one_minus_cos
    src = (
        f"latticedft.systems.charged_particle: exact circular motion x''=B y', y''=-B x' "
        f"(L = |v|^2/2 + B/2 (x v_y - y v_x)), q0={[x0, y0]!r}, v0={[vx, vy]!r}, B={B!r}"
    )
    attrs: dict[str, Any] = {"units": "1", "source": src, "B": B}
    common: dict[str, Any] = {"spacing": dt, "origin": t0, "components": ["x", "y"]}
    psi = make_field(np.stack([x, y], -1), ("t",), attrs={"long_name": "position", **attrs}, **common)
    if not return_velocity:
        return psi
    vel = np.stack([vx * cos + vy * sin, vy * cos - vx * sin], -1)
    return psi, make_field(vel, ("t",), name="velocity", attrs={"long_name": "velocity", **attrs}, **common)


def cyclotron_energy(velocity: ArrayLike) -> Any:
    """The conserved energy ``|v|^2 / 2`` (the magnetic force does no work), elementwise over the last axis.

    >>> float(cyclotron_energy([3.0, 4.0]))
    12.5
    """
    v = np.asarray(velocity, dtype=np.float64)
    return 0.5 * np.sum(v * v, axis=-1)
