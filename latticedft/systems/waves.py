"""The wave equation, exact: standing waves of a string (1+1D) and a membrane (2+1D).

:func:`wave_string` samples the d'Alembert standing-mode solution of
``psi_tt = c^2 psi_xx`` with fixed ends; :func:`wave_membrane` the modes of
``psi_tt = c^2 (psi_xx + psi_yy)`` on a rectangle with a fixed frame (the
separation-of-variables solutions). Their discrete energy is
:func:`latticedft.systems.wave_energy`; :func:`latticedft.systems.leapfrog`
steps the same equations numerically.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
import xarray as xr

from latticedft._errors import InputError
from latticedft.systems._fields import (
    _check_count,
    _check_finite,
    _check_positive,
    make_field,
)

__all__ = ["wave_membrane", "wave_string"]


def _parse_modes(
    modes: Iterable[Sequence[float]], nidx: int, arg: str = "modes"
) -> list[tuple[tuple[int, ...], float, float]]:
    """Check ``(k[, l], amplitude[, phase])`` tuples: ``(mode numbers, amplitude, phase)`` per mode."""
    out = []
    shape = "(k, amplitude[, phase])" if nidx == 1 else "(k, l, amplitude[, phase])"
    try:
        entries = list(modes)
    except TypeError:
        raise InputError(f"{arg}: expected a list of {shape} tuples") from None
    if not entries:
        raise InputError(f"{arg}: expected at least one {shape} tuple")
    for m in entries:
        m = tuple(m)
        if len(m) not in (nidx + 1, nidx + 2):
            raise InputError(f"{arg}: expected {shape} tuples, got {m!r}")
        idx = m[:nidx]
        if not all(isinstance(k, (int, np.integer)) and not isinstance(k, bool) and k >= 1 for k in idx):
            raise InputError(f"{arg}: mode numbers must be integers >= 1, got {m!r}")
        amp = _check_finite(m[nidx], arg)
        phase = _check_finite(m[nidx + 1], arg) if len(m) == nidx + 2 else 0.0
        out.append((tuple(int(k) for k in idx), amp, phase))
    return out


def wave_string(
    modes: Iterable[Sequence[float]],
    c: float = 1.0,
    length: float = 1.0,
    nx: int = 41,
    nt: int = 81,
    dt: float | None = None,
    *,
    t0: float = 0.0,
) -> xr.DataArray:
    r"""Exact standing-wave solution of ``psi_tt = c^2 psi_xx`` with fixed ends on ``[0, length]``.

    .. math:: \psi(t, x) = \sum_k A_k \sin\frac{k\pi x}{L}\cos(\omega_k t + \phi_k),
              \qquad \omega_k = \frac{c k \pi}{L}

    sampled at ``x_j = j*dx``, ``dx = L/(nx-1)`` (both end points included;
    their values are exactly 0) and ``t_i = t0 + i*dt``.

    Parameters
    ----------
    modes
        ``(k, A_k)`` or ``(k, A_k, phi_k)`` tuples, ``k >= 1`` an integer.
    c, length
        Wave speed and string length.
    nx, nt
        Number of sites in x (>= 3) and in t (>= 2).
    dt
        Time step; default ``0.5 * dx / c`` (Courant number 1/2).
    t0
        First time.

    Examples
    --------
    >>> psi = wave_string([(1, 1.0), (3, 0.2, 0.5)], nx=11, nt=5)
    >>> psi.dims, psi.shape, float(abs(psi[:, [0, -1]]).max())
    (('t', 'x'), (5, 11), 0.0)
    """
    parsed = _parse_modes(modes, 1)
    c = _check_positive(c, "c")
    length = _check_positive(length, "length")
    nx = _check_count(nx, "nx", 3)
    nt = _check_count(nt, "nt", 2)
    t0 = _check_finite(t0, "t0")
    dx = length / (nx - 1)
    dt = 0.5 * dx / c if dt is None else _check_positive(dt, "dt")
    x = dx * np.arange(nx, dtype=np.float64)
    t = t0 + dt * np.arange(nt, dtype=np.float64)
    psi = np.zeros((nt, nx))
    for (k,), amp, phase in parsed:
        psi += amp * np.outer(np.cos(c * k * np.pi / length * t + phase), np.sin(k * np.pi * x / length))
    psi[:, 0] = 0.0
    psi[:, -1] = 0.0
    return make_field(
        psi,
        ("t", "x"),
        spacing=(dt, dx),
        origin=(t0, 0.0),
        attrs={
            "long_name": "string displacement",
            "units": "1",
            "source": f"latticedft.systems.wave_string: exact standing modes "
            f"{[(k[0], a, p) for k, a, p in parsed]}, c={c!r}, length={length!r}",
        },
    )


def wave_membrane(
    modes: Iterable[Sequence[float]],
    c: float = 1.0,
    length_x: float = 1.0,
    length_y: float = 1.0,
    nx: int = 21,
    ny: int = 21,
    nt: int = 41,
    dt: float | None = None,
    *,
    t0: float = 0.0,
) -> xr.DataArray:
    r"""Exact solution of ``psi_tt = c^2 (psi_xx + psi_yy)`` on a rectangle with a fixed frame.

    .. math:: \psi(t, y, x) = \sum_{k,l} A_{kl}\sin\frac{k\pi x}{L_x}\sin\frac{l\pi y}{L_y}
              \cos(\omega_{kl} t + \phi_{kl}),\qquad
              \omega_{kl} = c\pi\sqrt{(k/L_x)^2 + (l/L_y)^2}

    sampled at ``x_j = j*dx`` (``dx = L_x/(nx-1)``), ``y_m = m*dy``
    (``dy = L_y/(ny-1)``) and ``t_i = t0 + i*dt``; the frame is exactly 0.

    Parameters
    ----------
    modes
        ``(k, l, A)`` or ``(k, l, A, phi)`` tuples; `k` counts half waves in
        x, `l` in y.
    dt
        Time step; default ``0.5 * min(dx, dy) / c``.

    Examples
    --------
    >>> psi = wave_membrane([(1, 2, 1.0)], nx=5, ny=4, nt=3)
    >>> psi.dims, psi.shape
    (('t', 'y', 'x'), (3, 4, 5))
    """
    parsed = _parse_modes(modes, 2)
    c = _check_positive(c, "c")
    length_x = _check_positive(length_x, "length_x")
    length_y = _check_positive(length_y, "length_y")
    nx = _check_count(nx, "nx", 3)
    ny = _check_count(ny, "ny", 3)
    nt = _check_count(nt, "nt", 2)
    t0 = _check_finite(t0, "t0")
    dx = length_x / (nx - 1)
    dy = length_y / (ny - 1)
    dt = 0.5 * min(dx, dy) / c if dt is None else _check_positive(dt, "dt")
    x = dx * np.arange(nx, dtype=np.float64)
    y = dy * np.arange(ny, dtype=np.float64)
    t = t0 + dt * np.arange(nt, dtype=np.float64)
    psi = np.zeros((nt, ny, nx))
    for (k, ky), amp, phase in parsed:
        omega = c * np.pi * math.hypot(k / length_x, ky / length_y)
        shape = np.outer(np.sin(ky * np.pi * y / length_y), np.sin(k * np.pi * x / length_x))
        psi += amp * np.cos(omega * t + phase)[:, None, None] * shape[None]
    psi[:, 0, :] = psi[:, -1, :] = 0.0
    psi[:, :, 0] = psi[:, :, -1] = 0.0
    return make_field(
        psi,
        ("t", "y", "x"),
        spacing=(dt, dy, dx),
        origin=(t0, 0.0, 0.0),
        attrs={
            "long_name": "membrane displacement",
            "units": "1",
            "source": f"latticedft.systems.wave_membrane: exact modes "
            f"{[(*k, a, p) for k, a, p in parsed]}, c={c!r}, "
            f"length_x={length_x!r}, length_y={length_y!r}",
        },
    )
