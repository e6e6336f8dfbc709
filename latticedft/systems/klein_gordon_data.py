"""The periodic Klein–Gordon benchmark (Offen & Ober-Blöbaum's setup): data from the explicit scheme.

``u_tt = u_xx - u`` on a periodic interval, the Euler–Lagrange equation of
``L = u_t^2/2 - u_x^2/2 - u^2/2``. The data are the explicit leapfrog scheme
(:func:`latticedft.systems.leapfrog`, ``force = -u``, periodic) to round-off:
:func:`klein_gordon` from two given slices, :func:`klein_gordon_training_set`
(random smooth initial data, reproducible from a seed) and
:func:`klein_gordon_test_field` (the benchmark's test data). Their discrete
energy is :func:`latticedft.systems.klein_gordon_energy`.
"""

from __future__ import annotations

import numpy as np
import xarray as xr
from numpy.typing import ArrayLike

from latticedft._errors import InputError
from latticedft._layout import PERIODIC_ATTR, periodic_attr
from latticedft.systems._fields import (
    _as_real_array,
    _check_count,
    _check_finite,
    _check_positive,
    _FloatArray,
    make_field,
)
from latticedft.systems.leapfrog_scheme import leapfrog

__all__ = ["klein_gordon", "klein_gordon_test_field", "klein_gordon_training_set"]


def _kg_force(u: _FloatArray) -> _FloatArray:
    return -u


def klein_gordon(
    u0: ArrayLike,
    u1: ArrayLike,
    steps: int,
    dt: float = 0.025,
    dx: float = 0.05,
) -> xr.DataArray:
    r"""Periodic Klein–Gordon data from the explicit scheme (Offen & Ober-Blöbaum benchmark).

    Continuous theory :math:`L = u_t^2/2 - u_x^2/2 - u^2/2`,
    :math:`u_{tt} = u_{xx} - u`, on ``x in [0, nx*dx)`` periodic. The data are
    *exactly* (to round-off) the explicit scheme

    .. math:: \frac{u_{i+1,j} - 2u_{ij} + u_{i-1,j}}{\Delta t^2}
              = \frac{u_{i,j+1} - 2u_{ij} + u_{i,j-1}}{\Delta x^2} - u_{ij},

    indices in j taken modulo ``nx`` (:func:`leapfrog` with
    ``force = -u``, ``boundary = "periodic"``).

    Parameters
    ----------
    u0, u1
        The first two slices, 1-D arrays of length ``nx`` on ``x_j = j*dx``
        (the benchmark: ``nx = 20``, ``dx = 0.05``, ``dt = 0.025``).
    steps
        Number of time steps; the result has ``steps + 1`` slices including
        `u0` and `u1`.

    Returns
    -------
    xarray.DataArray
        ``psi(t, x)``; the ``x`` coordinate has attrs ``periodic = "true"``
        and ``period = nx*dx`` (there is no duplicated end point).

    Examples
    --------
    >>> x = 0.05 * np.arange(20)
    >>> u = klein_gordon(np.sin(4 * np.pi * x), np.sin(4 * np.pi * x), steps=40)
    >>> u.shape, u["x"].attrs["periodic"], u["x"].attrs["period"]
    ((41, 20), 'true', 1.0)
    """
    a0 = _as_real_array(u0, "u0")
    a1 = _as_real_array(u1, "u1")
    if a0.ndim != 1 or a0.size < 3:
        raise InputError(f"u0: expected a 1-D array of at least 3 sites, got shape {a0.shape}")
    if a1.shape != a0.shape:
        raise InputError(f"u1: expected shape {a0.shape} like u0, got {a1.shape}")
    dt = _check_positive(dt, "dt")
    dx = _check_positive(dx, "dx")
    u = leapfrog(a0, a1, steps, dt, dx, force=_kg_force, boundary="periodic")
    assert isinstance(u, np.ndarray)
    nx = a0.size
    return make_field(
        u,
        ("t", "x"),
        spacing=(dt, dx),
        coord_attrs={"x": {PERIODIC_ATTR: periodic_attr(True), "period": nx * dx}},
        attrs={
            "long_name": "Klein-Gordon field u",
            "units": "1",
            "source": f"latticedft.systems.klein_gordon: explicit scheme of u_tt = u_xx - u, "
            f"periodic, nx={nx}, dx={dx!r}, dt={dt!r}",
        },
    )


def _smooth_periodic(rng: np.random.Generator, nx: int, decay: float) -> _FloatArray:
    """Random trigonometric polynomial on ``x_j = j/nx``, coefficients ``N(0,1) exp(-decay k^4)``."""
    k = np.arange(nx // 2 + 1, dtype=np.float64)
    weight = np.exp(-decay * k**4)
    a = rng.standard_normal(k.size) * weight
    b = rng.standard_normal(k.size) * weight
    x = np.arange(nx, dtype=np.float64) / nx
    phase = 2.0 * np.pi * np.outer(x, k)
    return np.cos(phase) @ a + np.sin(phase) @ b


def klein_gordon_training_set(
    n: int = 80,
    steps: int = 20,
    seed: int = 0,
    *,
    nx: int = 20,
    dt: float = 0.025,
    dx: float = 0.05,
    decay: float = 2.0,
) -> list[xr.DataArray]:
    r"""Random smooth periodic Klein–Gordon fields for training, see :func:`klein_gordon`.

    Each field starts from a random trigonometric polynomial on ``[0, L)``,
    ``L = nx*dx``,

    .. math:: u_0(x) = \sum_{k=0}^{nx/2} a_k\cos(2\pi k x/L) + b_k\sin(2\pi k x/L),
              \qquad a_k, b_k \sim N(0, 1)\,e^{-\mathrm{decay}\,k^4},

    and an initial velocity ``v_0`` drawn the same way (independently). The
    second slice is a second-order Taylor step with the scheme's own operator,
    ``u_1 = u_0 + dt v_0 + dt^2/2 (D_xx u_0 - u_0)`` (``D_xx`` the periodic
    three-point Laplacian). With the default ``decay = 2`` the modes
    ``k >= 2`` carry at most ``e^{-32}`` of the amplitude, i.e. the data are
    dominated by ``k = 0, 1``. The generator is
    ``numpy.random.default_rng(seed)``; fields are drawn in order.

    Returns
    -------
    list of xarray.DataArray
        `n` fields ``psi(t, x)`` of ``steps + 1`` slices each.

    Examples
    --------
    >>> data = klein_gordon_training_set(n=3, steps=5, seed=1)
    >>> len(data), data[0].shape
    (3, (6, 20))
    """
    n = _check_count(n, "n", 1)
    nx = _check_count(nx, "nx", 3)
    dt = _check_positive(dt, "dt")
    dx = _check_positive(dx, "dx")
    decay = _check_finite(decay, "decay")
    if decay < 0:
        raise InputError(f"decay: expected a number >= 0, got {decay!r}")
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool):
        raise InputError(f"seed: expected an integer, got {seed!r}")
    rng = np.random.default_rng(int(seed))
    fields = []
    for m in range(n):
        u0 = _smooth_periodic(rng, nx, decay)
        v0 = _smooth_periodic(rng, nx, decay)
        dxx = (np.roll(u0, -1) - 2.0 * u0 + np.roll(u0, 1)) / (dx * dx)
        u1 = u0 + dt * v0 + 0.5 * dt * dt * (dxx - u0)
        f = klein_gordon(u0, u1, steps, dt=dt, dx=dx)
        f.attrs["source"] += (
            f"; klein_gordon_training_set seed={int(seed)} member {m} of {n}, "
            f"Fourier amplitudes N(0,1) exp(-{decay:g} k^4), u1 = Taylor step from v0"
        )
        fields.append(f)
    return fields


def klein_gordon_test_field(steps: int = 80, *, nx: int = 20, dt: float = 0.025, dx: float = 0.05) -> xr.DataArray:
    """The Klein–Gordon test data: ``u0 = sin(4 pi x)``, ``u1 = u0``, see :func:`klein_gordon`.

    ``x_j = j*dx``; with the defaults the period is 1, so ``u0`` has two
    wavelengths and is at rest to first order.

    Examples
    --------
    >>> klein_gordon_test_field(steps=10).shape
    (11, 20)
    """
    nx = _check_count(nx, "nx", 3)
    dx = _check_positive(dx, "dx")
    x = dx * np.arange(nx, dtype=np.float64)
    u0 = np.sin(4.0 * np.pi * x)
    f = klein_gordon(u0, u0, steps, dt=dt, dx=dx)
    f.attrs["source"] += "; test data u0 = sin(4 pi x), u1 = u0"
    return f
