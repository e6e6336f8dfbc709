"""The Kepler problem: planetary orbits in the Sun's gravity (Qin 2020, Section 4).

Newton's equations ``r'' = -GM r / |r|^3`` with ``GM = 1`` in units of 1 au and
58.14 days (:data:`KEPLER_TIME_UNIT_DAYS`, :data:`GM_SUN_KEPLER_UNITS`):
:func:`kepler_orbit` (any launch), :func:`planet_orbit` and
:func:`planet_aphelion` (the paper's training bodies, :data:`PLANETS`), and the
orbit invariants :func:`kepler_energy`, :func:`kepler_angular_momentum`,
:func:`kepler_period` and :func:`escape_speed`.

References: H. Qin, "Machine learning and serving of discrete field theories",
Sci. Rep. 10, 19329 (2020); orbital elements from JPL, "Keplerian elements for
approximate positions of the major planets" and the JPL small-body database.
Solutions are DOP853 solves with ``rtol = atol = 1e-12`` sampled at the lattice
times (see :mod:`latticedft.systems._fields`).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

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
    _time_attrs,
    make_field,
)

__all__ = [
    "GM_SUN_KEPLER_UNITS",
    "KEPLER_TIME_UNIT_DAYS",
    "PLANETS",
    "Planet",
    "escape_speed",
    "kepler_angular_momentum",
    "kepler_energy",
    "kepler_orbit",
    "kepler_period",
    "planet_aphelion",
    "planet_orbit",
]

#: Time unit of the Kepler data in days (Qin 2020, Sec. 4). Length unit: 1 au.
KEPLER_TIME_UNIT_DAYS = 58.14
#: GM of the Sun in units au^3 / (58.14 d)^2, from Kepler's third law
#: ``GM = 4 pi^2 au^3 / yr^2`` with the sidereal year 365.256363 d: 1.00024.
#: (58.14 d is, to 4 digits, 1/k with k = 0.01720209895 the Gaussian
#: gravitational constant.) The functions below use ``GM = 1`` exactly.
GM_SUN_KEPLER_UNITS = 4.0 * math.pi**2 * (KEPLER_TIME_UNIT_DAYS / 365.256363) ** 2


class Planet(NamedTuple):
    """Orbital elements: semi-major axis `a` [au] and eccentricity `e`."""

    a: float
    e: float


#: The six training bodies of Qin 2020, Sec. 4 (J2000 mean elements: JPL
#: "Keplerian elements for approximate positions of the major planets"; Ceres
#: from the JPL small-body database).
PLANETS: dict[str, Planet] = {
    "Mercury": Planet(0.38709927, 0.20563593),
    "Venus": Planet(0.72333566, 0.00677672),
    "Earth": Planet(1.00000261, 0.01671123),
    "Mars": Planet(1.52371034, 0.09339410),
    "Ceres": Planet(2.7691651, 0.0760090),
    "Jupiter": Planet(5.20288700, 0.04838624),
}


def kepler_period(a: ArrayLike) -> Any:
    """Orbital period ``T = 2 pi a^{3/2}`` (GM = 1) of an orbit with semi-major axis `a`.

    Examples
    --------
    >>> round(float(kepler_period(1.0)) * KEPLER_TIME_UNIT_DAYS, 1)  # days
    365.3
    """
    return 2.0 * np.pi * np.power(a, 1.5)


def escape_speed(r: ArrayLike) -> Any:
    """Escape speed ``sqrt(2 GM / r)`` (GM = 1) at distance `r` from the Sun.

    Examples
    --------
    >>> round(float(escape_speed(1.0167)), 4)
    1.4026
    """
    return np.sqrt(2.0 / np.asarray(r, dtype=np.float64))


def _state_arrays(position: ArrayLike, velocity: ArrayLike) -> tuple[_FloatArray, _FloatArray]:
    r = np.asarray(position, dtype=np.float64)
    v = np.asarray(velocity, dtype=np.float64)
    if r.shape != v.shape or r.ndim == 0 or r.shape[-1] != 2:
        raise InputError(f"position, velocity: expected equal shapes (..., 2), got {r.shape} and {v.shape}")
    return r, v


def _like_leading(values: _FloatArray, template: Any) -> Any:
    """Wrap `values` as a DataArray over the template's leading dims when it is one."""
    if isinstance(template, xr.DataArray):
        lead = template.dims[:-1]
        return xr.DataArray(values, dims=lead, coords={d: template.coords[d] for d in lead if d in template.coords})
    return values


def kepler_energy(position: ArrayLike, velocity: ArrayLike) -> Any:
    """Specific orbital energy ``E = |v|^2 / 2 - 1 / |r|`` (GM = 1).

    `position` and `velocity` have shape ``(..., 2)`` (last axis x, y), e.g.
    the pair returned by ``kepler_orbit(..., return_velocity=True)``; the result
    has the leading shape (a DataArray over ``t`` for DataArray input).

    Examples
    --------
    >>> float(kepler_energy([1.0, 0.0], [0.0, 1.0]))
    -0.5
    """
    r, v = _state_arrays(position, velocity)
    return _like_leading(0.5 * np.sum(v * v, axis=-1) - 1.0 / np.hypot(r[..., 0], r[..., 1]), position)


def kepler_angular_momentum(position: ArrayLike, velocity: ArrayLike) -> Any:
    """Specific angular momentum ``l = x v_y - y v_x``; arguments as in :func:`kepler_energy`.

    Examples
    --------
    >>> float(kepler_angular_momentum([1.0, 0.0], [0.0, 1.0]))
    1.0
    """
    r, v = _state_arrays(position, velocity)
    return _like_leading(r[..., 0] * v[..., 1] - r[..., 1] * v[..., 0], position)


def _kepler_rhs(t: float, y: _FloatArray) -> list[float]:
    x, yy, vx, vy = y
    r3 = (x * x + yy * yy) ** 1.5
    return [vx, vy, -x / r3, -yy / r3]


def _orbit_length(r0: float, v0: float, dt: float, n: int | None, t_end: float | None) -> int:
    """Number of slices of :func:`kepler_orbit`: `n`, the lattice times ``<= t_end``, or one period."""
    if n is not None and t_end is not None:
        raise InputError("n, t_end: give at most one of them")
    energy = 0.5 * v0 * v0 - 1.0 / r0
    if n is None and t_end is None:
        if energy >= 0:
            raise InputError(
                f"n: required (or t_end) for an unbound orbit (v0={v0!r} >= escape speed {math.sqrt(2.0 / r0):.6g})"
            )
        n = int(round(float(kepler_period(-0.5 / energy)) / dt)) + 1
    elif t_end is not None:
        t_end = _check_finite(t_end, "t_end")
        if t_end < dt:
            raise InputError(f"t_end: expected at least one step dt={dt!r}, got {t_end!r}")
        n = int(math.floor(t_end / dt + 1e-9)) + 1
    _check_lattice_1d(n, dt)  # type: ignore[arg-type]
    return n  # type: ignore[return-value]


def _leave_disc(r_max: float) -> Any:
    """A terminal solve_ivp event: the orbit crosses ``|r| = r_max`` outwards."""

    def leave(t: float, y: _FloatArray) -> float:
        return math.hypot(y[0], y[1]) - r_max

    leave.terminal = True  # type: ignore[attr-defined]
    leave.direction = 1.0  # type: ignore[attr-defined]
    return leave


def kepler_orbit(
    r0: float,
    v0: float,
    dt: float = 0.05,
    n: int | None = None,
    t_end: float | None = None,
    r_max: float | None = None,
    *,
    return_velocity: bool = False,
) -> xr.DataArray | tuple[xr.DataArray, xr.DataArray]:
    r"""An orbit in the Sun's gravity (Qin 2020, Sec. 4), Newton's equations.

    .. math:: \ddot{\mathbf r} = -\frac{GM\,\mathbf r}{|\mathbf r|^3},\qquad GM = 1

    in units of 1 au and 58.14 days (see :data:`GM_SUN_KEPLER_UNITS`),
    started at position ``(r0, 0)`` with velocity ``(0, v0)`` (counter-clockwise
    for ``v0 > 0``), solved with DOP853 (``rtol = atol = 1e-12``) and sampled at
    ``t = i*dt``.

    Parameters
    ----------
    r0, v0
        Launch distance (> 0) and speed. ``v0 < escape_speed(r0)`` is bound.
    dt
        Time step of the data (the paper uses 0.05).
    n, t_end
        Length: `n` slices, or every lattice time ``<= t_end`` (give at most
        one). With neither, a bound orbit gets one period (the lattice time
        nearest ``2 pi a^{3/2}`` is the last slice); an unbound one is an error.
    r_max
        Stop before the orbit first leaves the disc ``|r| <= r_max``: only the
        slices before that crossing are returned (so fewer than `n`).
    return_velocity
        Also return the velocity, a DataArray named ``"velocity"`` of the
        same layout.

    Returns
    -------
    xarray.DataArray
        ``psi(t, component)`` with ``component = ["x", "y"]`` in au.

    Examples
    --------
    >>> orbit = kepler_orbit(1.0, 1.0, dt=0.05, n=11)
    >>> orbit.dims, orbit.shape, orbit["component"].values.tolist()
    (('t', 'component'), (11, 2), ['x', 'y'])
    >>> escaping = kepler_orbit(1.0, 1.5, t_end=100.0, r_max=3.0)
    >>> bool(np.hypot(*escaping.values[-1]) <= 3.0), escaping.sizes["t"] < 2001
    (True, True)
    """
    r0 = _check_finite(r0, "r0")
    v0 = _check_finite(v0, "v0")
    if r0 <= 0:
        raise InputError(f"r0: expected a positive distance, got {r0!r}")
    if not (isinstance(dt, (int, float, np.floating)) and math.isfinite(dt) and dt > 0):
        raise InputError(f"dt: expected a positive finite number, got {dt!r}")
    n = _orbit_length(r0, v0, dt, n, t_end)
    events = None
    if r_max is not None:
        r_max = _check_finite(r_max, "r_max")
        if r_max <= r0:
            raise InputError(f"r_max: expected more than r0={r0!r}, got {r_max!r}")
        events = _leave_disc(r_max)
    t = dt * np.arange(n, dtype=np.float64)
    sol = _solve(_kepler_rhs, [r0, 0.0, 0.0, v0], t, events=events, what="kepler_orbit")
    if sol.y.shape[1] < 2:
        raise InputError(f"r_max: the orbit leaves r <= {r_max!r} within the first step")
    src = (
        f"latticedft.systems.kepler_orbit: r''=-r/|r|^3 (GM=1, units 1 au, {KEPLER_TIME_UNIT_DAYS} d), "
        f"r0={r0!r}, v0={v0!r}, r_max={r_max!r}; solve_ivp DOP853 rtol={ODE_RTOL:g} atol={ODE_ATOL:g}"
    )
    common: dict[str, Any] = dict(
        spacing=dt, components=["x", "y"], coord_attrs={"t": _time_attrs(f"{KEPLER_TIME_UNIT_DAYS} days")}
    )
    attrs = {"units": "au", "source": src, "r0": r0, "v0": v0, "GM": 1.0}
    psi = make_field(sol.y[:2].T, ("t",), attrs={"long_name": "position", **attrs}, **common)
    if not return_velocity:
        return psi
    vel = make_field(
        sol.y[2:].T,
        ("t",),
        name="velocity",
        attrs={"long_name": "velocity", **attrs, "units": f"au / ({KEPLER_TIME_UNIT_DAYS} days)"},
        **common,
    )
    return psi, vel


def _planet(name: str) -> tuple[str, Planet]:
    for key, p in PLANETS.items():
        if isinstance(name, str) and key.lower() == name.lower():
            return key, p
    raise InputError(f"name: unknown planet {name!r}; expected one of {sorted(PLANETS)}")


def planet_aphelion(name: str) -> tuple[float, float]:
    """Aphelion distance ``a(1+e)`` and speed ``sqrt((1-e)/(a(1+e)))`` (GM = 1) of a planet.

    Examples
    --------
    >>> [round(v, 4) for v in planet_aphelion("Earth")]
    [1.0167, 0.9834]
    >>> [round(v, 4) for v in planet_aphelion("mercury")]
    [0.4667, 1.3046]
    """
    _, p = _planet(name)
    r = p.a * (1.0 + p.e)
    return r, math.sqrt((1.0 - p.e) / r)


def planet_orbit(name: str, dt: float = 0.05, periods: float = 1.0) -> xr.DataArray:
    """Orbit of one of :data:`PLANETS` launched from its aphelion (Qin 2020, Sec. 4).

    Starts at ``(a(1+e), 0)`` with velocity ``(0, sqrt((1-e)/(a(1+e))))``
    (Earth: ``r = 1.0167``, ``v = 0.983``; Mercury: ``r = 0.4667``,
    ``v = 1.305``) and runs `periods` orbital periods ``2 pi a^{3/2}``: the
    lattice time nearest ``periods * T`` is the last slice. The name is
    case-insensitive; the DataArray's attrs carry ``planet``, ``a`` and ``e``.

    Examples
    --------
    >>> earth = planet_orbit("Earth")
    >>> earth.sizes["t"], earth.attrs["planet"]
    (127, 'Earth')
    """
    key, p = _planet(name)
    periods = _check_finite(periods, "periods")
    if periods <= 0:
        raise InputError(f"periods: expected a positive number, got {periods!r}")
    if not (isinstance(dt, (int, float, np.floating)) and math.isfinite(dt) and dt > 0):
        raise InputError(f"dt: expected a positive finite number, got {dt!r}")
    r0, v0 = planet_aphelion(key)
    n = int(round(periods * float(kepler_period(p.a)) / dt)) + 1
    psi = kepler_orbit(r0, v0, dt=dt, n=max(n, 2))
    assert isinstance(psi, xr.DataArray)
    psi.attrs.update({"long_name": f"position of {key}", "planet": key, "a": p.a, "e": p.e})
    psi.attrs["source"] = (
        f"latticedft.systems.planet_orbit({key!r}, periods={periods!r}) from aphelion; " + psi.attrs["source"]
    )
    return psi
