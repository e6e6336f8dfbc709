"""Energies of wave-type fields: the invariants of served wave, membrane and Klein–Gordon fields.

:func:`field_energy` is the discrete energy of ``psi_tt = c^2 Laplacian(psi) -
m^2 psi`` that the explicit leapfrog scheme (:func:`latticedft.systems.leapfrog`)
conserves exactly; :func:`wave_energy` (``c = 1``, ``m = 0``) and
:func:`klein_gordon_energy` (``c = 1``, ``m = 1``) are its forms named by the
``invariant`` keys of the wave and Klein–Gordon cases. The sine-Gordon energy is
:func:`latticedft.systems.sine_gordon_energy`.
"""

from __future__ import annotations

import math

import numpy as np
import xarray as xr

from latticedft._errors import InputError
from latticedft._layout import axis_periodic
from latticedft.systems._fields import _as_real_array, _check_finite, _uniform_spacing

__all__ = ["field_energy", "klein_gordon_energy", "wave_energy"]


def field_energy(psi: xr.DataArray, c: float = 1.0, mass: float = 0.0) -> xr.DataArray:
    r"""Discrete energy of a field ``psi(t, x)`` or ``psi(t, y, x)``, slice by slice.

    For ``psi_tt = c^2 Laplacian(psi) - m^2 psi`` (the wave equation for
    ``m = 0``, Klein–Gordon otherwise) the energy of the slice pair
    ``(i, i+1)``, at ``t_i + dt/2``, is

    .. math:: E_{i+1/2} = \sum_j \Big[\frac{(\psi_{i+1,j} - \psi_{ij})^2}{2\Delta t^2}
              + \frac{m^2}{2}\psi_{ij}\psi_{i+1,j}
              + \sum_k \frac{c^2}{2 h_k^2}(\psi_{i,j+e_k} - \psi_{ij})(\psi_{i+1,j+e_k} - \psi_{i+1,j})\Big]
              \prod_k h_k,

    summed over all sites and every link along each spatial axis (links wrap
    around along axes whose coordinate is marked ``periodic = "true"``). The
    explicit leapfrog scheme (:func:`leapfrog`) conserves it exactly (to
    round-off) with periodic axes or a fixed frame; for a smooth solution it
    is the continuum energy to ``O(dt^2 + h^2)``. The value at slice ``i`` is
    the mean of ``E_{i-1/2}`` and ``E_{i+1/2}`` (the one that exists at the
    first and last slice), so a conserved ``E`` stays constant.

    Returns
    -------
    xarray.DataArray
        ``energy(t)`` on the slices of `psi` (at least 2).

    Examples
    --------
    >>> from latticedft.systems import wave_string
    >>> psi = wave_string([(1, 1.0)], nx=401, nt=5)
    >>> bool(abs(float(field_energy(psi)[2]) - np.pi**2 / 4) < 1e-4)  # exact: (k pi)^2 A^2 / 4
    True
    """
    if not isinstance(psi, xr.DataArray) or psi.ndim not in (2, 3) or psi.dims[0] != "t":
        raise InputError(
            f"psi: expected a DataArray psi(t, x) or psi(t, y, x), got "
            f"{psi.dims if isinstance(psi, xr.DataArray) else type(psi).__name__}"
        )
    c = _check_finite(c, "c")
    mass = _check_finite(mass, "mass")
    for d in psi.dims:
        if d not in psi.coords:
            raise InputError(f"psi: needs a {d!r} coordinate to read the spacing")
    h = [_uniform_spacing(psi[d].values, str(d)) for d in psi.dims]
    u = _as_real_array(psi, "psi")
    if u.shape[0] < 2:
        raise InputError(f"psi: needs at least 2 time slices, got {u.shape[0]}")
    a, b = u[:-1], u[1:]
    axes = tuple(range(1, u.ndim))
    e = ((b - a) ** 2 / (2.0 * h[0] ** 2) + 0.5 * mass * mass * a * b).sum(axis=axes)
    for k in axes:
        if axis_periodic(psi, str(psi.dims[k]), "psi"):
            da, db = np.roll(a, -1, axis=k) - a, np.roll(b, -1, axis=k) - b
        else:
            da, db = np.diff(a, axis=k), np.diff(b, axis=k)
        e = e + (c * c / (2.0 * h[k] ** 2)) * (da * db).sum(axis=axes)
    e = e * math.prod(h[1:])
    out = np.concatenate([e[:1], 0.5 * (e[:-1] + e[1:]), e[-1:]])
    return xr.DataArray(
        out,
        dims=("t",),
        coords={"t": psi["t"]},
        name="energy",
        attrs={"long_name": "discrete field energy", "units": "1"},
    )


def wave_energy(psi: xr.DataArray) -> xr.DataArray:
    """Energy of the wave equation ``psi_tt = Laplacian(psi)`` (``c = 1``): :func:`field_energy`.

    For the ``invariant = "latticedft.systems:wave_energy"`` key of a case
    (string or membrane).
    """
    return field_energy(psi, c=1.0, mass=0.0)


def klein_gordon_energy(psi: xr.DataArray) -> xr.DataArray:
    """Energy of ``u_tt = u_xx - u`` (the Klein–Gordon benchmark): :func:`field_energy` with ``mass = 1``."""
    return field_energy(psi, c=1.0, mass=1.0)
