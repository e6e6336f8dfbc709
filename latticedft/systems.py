"""Canonical systems: reference fields for training, tests and documentation.

Every generator returns its field as an :class:`xarray.DataArray` in the
layout of DESIGN.md §2 ("Field files"):

* name ``"psi"``; dims time first, then spatial dims with ``x`` last
  (``("t",)``, ``("t", "x")``, ``("t", "y", "x")``); vector fields add a
  trailing ``"component"`` dim with string labels (Kepler: ``["x", "y"]``);
* every lattice dim has a float64, uniformly spaced coordinate
  (``t = t0 + i*dt``) with attributes ``units``, ``long_name`` and ``axis``;
  periodic axes also carry ``periodic = "true"`` and ``period``;
* the values are float64 and C-contiguous; the DataArray carries
  ``long_name``, ``units`` and ``source`` (how it was made).

Systems
-------
* Paper (Qin 2020) Example 1, :func:`oscillator_sin`; Example 2,
  :func:`oscillator_wells`; Section 4, the Kepler problem
  (:data:`PLANETS`, :func:`kepler_orbit`, :func:`planet_orbit`).
* The wave equation, exact: :func:`wave_string` (1+1D) and
  :func:`wave_membrane` (2+1D).
* The explicit leapfrog scheme of ``psi_tt = c^2 Laplacian(psi) + f(psi)``,
  :func:`leapfrog` (baseline and numpy speed reference).
* The periodic Klein–Gordon benchmark: :func:`klein_gordon`,
  :func:`klein_gordon_training_set`, :func:`klein_gordon_test_field`.
* Sine-Gordon, exact: :func:`sine_gordon_breather`, :func:`kink_antikink`,
  and :func:`sine_gordon_energy`.
* Energies of served fields: :func:`field_energy`, :func:`wave_energy`
  (string and membrane) and :func:`klein_gordon_energy`.
* :func:`make_field` builds a DataArray in this layout from plain arrays.

Reference ODE solutions use :func:`scipy.integrate.solve_ivp` with the
8th-order Dormand–Prince method (DOP853), ``rtol = atol = 1e-12``, sampled at
the lattice times through ``t_eval`` (the method's dense output).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
import xarray as xr
from numpy.typing import ArrayLike, NDArray
from scipy.integrate import solve_ivp, trapezoid

from latticedft._errors import InputError

__all__ = [
    "ODE_RTOL",
    "ODE_ATOL",
    "KEPLER_TIME_UNIT_DAYS",
    "GM_SUN_KEPLER_UNITS",
    "Planet",
    "PLANETS",
    "make_field",
    "oscillator_sin",
    "oscillator_sin_energy",
    "oscillator_wells",
    "wells_potential",
    "oscillator_wells_energy",
    "kepler_orbit",
    "planet_orbit",
    "planet_aphelion",
    "kepler_energy",
    "kepler_angular_momentum",
    "kepler_period",
    "escape_speed",
    "wave_string",
    "wave_membrane",
    "leapfrog",
    "klein_gordon",
    "klein_gordon_training_set",
    "klein_gordon_test_field",
    "sine_gordon_breather",
    "kink_antikink",
    "sine_gordon_energy",
    "field_energy",
    "wave_energy",
    "klein_gordon_energy",
]

#: Relative tolerance of every reference ODE solve (DOP853).
ODE_RTOL = 1e-12
#: Absolute tolerance of every reference ODE solve (DOP853).
ODE_ATOL = 1e-12

_FloatArray = NDArray[np.float64]

# ----------------------------------------------------------------------------
# Field construction
# ----------------------------------------------------------------------------

_DIM_DEFAULTS: dict[str, tuple[str, str]] = {
    "t": ("time", "T"),
    "x": ("x", "X"),
    "y": ("y", "Y"),
    "z": ("z", "Z"),
}


def _per_dim(value: float | Sequence[float], ndim: int, arg: str) -> list[float]:
    """Broadcast a scalar or check a per-dim sequence of floats."""
    if np.ndim(value) == 0:
        out = [float(value)] * ndim  # type: ignore[arg-type]
    else:
        out = [float(v) for v in value]  # type: ignore[union-attr]
        if len(out) != ndim:
            raise InputError(f"{arg}: expected a number or {ndim} numbers (one per lattice dim), got {len(out)}")
    if not all(math.isfinite(v) for v in out):
        raise InputError(f"{arg}: expected finite numbers, got {out}")
    return out


def _uniform_spacing(coord: ArrayLike, dim: str) -> float:
    """Spacing of a uniformly spaced, increasing 1-D coordinate (InputError otherwise)."""
    c = np.asarray(coord, dtype=np.float64)
    if c.ndim != 1 or c.size < 2:
        raise InputError(f"coordinate {dim!r}: need a 1-D coordinate with at least 2 values to read a spacing")
    h = (c[-1] - c[0]) / (c.size - 1)
    if not np.isfinite(h) or h <= 0:
        raise InputError(f"coordinate {dim!r}: expected increasing finite values")
    dev = np.max(np.abs(c - (c[0] + h * np.arange(c.size))))
    if dev > 1e-9 * h + 8 * np.finfo(np.float64).eps * np.max(np.abs(c)):
        raise InputError(f"coordinate {dim!r}: not uniformly spaced (deviation {dev:.3g} for spacing {h:.6g})")
    return float(h)


def make_field(
    values: ArrayLike,
    dims: Sequence[str],
    *,
    spacing: float | Sequence[float] | None = None,
    origin: float | Sequence[float] = 0.0,
    coords: Mapping[str, ArrayLike] | None = None,
    components: Sequence[str] | None = None,
    name: str = "psi",
    attrs: Mapping[str, Any] | None = None,
    coord_attrs: Mapping[str, Mapping[str, Any]] | None = None,
) -> xr.DataArray:
    """Build a field DataArray in the DESIGN.md layout.

    Parameters
    ----------
    values
        Real array of shape ``lattice_shape`` (scalar field) or
        ``lattice_shape + (len(components),)`` (vector field).
    dims
        Names of the lattice dims, time first and ``x`` last, e.g.
        ``("t", "x")``. Do not list ``"component"``: it is added when
        `components` is given.
    spacing
        Lattice spacing, one number for every dim or one per dim; the
        coordinate of dim ``k`` is ``origin[k] + i * spacing[k]``.
    origin
        First coordinate value, one number or one per dim.
    coords
        Explicit coordinates ``{dim: 1-D array}``; each must be uniformly
        spaced and increasing. They take precedence over `spacing` for the
        dims they name; every other dim needs `spacing`.
    components
        String labels of the vector components (e.g. ``["x", "y"]``).
    name
        Variable name (default ``"psi"``).
    attrs
        Attributes of the DataArray (``long_name``, ``units``, ``source`` ...;
        strings or numbers). ``long_name`` defaults to `name`.
    coord_attrs
        Per-dim coordinate attributes, merged over the defaults
        (``units = "1"``, ``long_name`` "time"/"x"/"y", ``axis`` "T"/"X"/"Y").

    Returns
    -------
    xarray.DataArray
        float64, C-contiguous values with float64 coordinates.

    Raises
    ------
    InputError
        On a shape, dims, spacing or coordinate that does not fit.

    Examples
    --------
    >>> import numpy as np
    >>> f = make_field(np.zeros((3, 4)), ("t", "x"), spacing=(0.1, 0.25))
    >>> f.dims, f["x"].values.tolist(), f["t"].attrs["axis"]
    (('t', 'x'), [0.0, 0.25, 0.5, 0.75], 'T')
    >>> orbit = make_field(np.ones((5, 2)), ("t",), spacing=0.05, components=["x", "y"])
    >>> orbit.dims, orbit["component"].values.tolist()
    (('t', 'component'), ['x', 'y'])
    """
    dims = tuple(dims)
    if len(dims) == 0 or len(set(dims)) != len(dims) or not all(isinstance(d, str) for d in dims):
        raise InputError(f"dims: expected distinct dim names, got {dims!r}")
    if "component" in dims:
        raise InputError("dims: do not list 'component'; pass components=[...] instead")
    arr = np.asarray(values)
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr) or arr.dtype == np.bool_:
        raise InputError(f"values: expected real numbers, got dtype {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    ncomp = 0 if components is None else len(components)
    expected_ndim = len(dims) + (1 if components is not None else 0)
    if arr.ndim != expected_ndim:
        raise InputError(f"values: expected {expected_ndim} dims for dims={dims!r}"
                         f"{' plus component' if components is not None else ''}, got shape {arr.shape}")
    if components is not None:
        if ncomp == 0 or arr.shape[-1] != ncomp or not all(isinstance(s, str) for s in components):
            raise InputError(f"components: expected {arr.shape[-1]} string labels, got {list(components)!r}")
    if not np.all(np.isfinite(arr)):
        raise InputError("values: contains NaN or infinity")
    coords = dict(coords or {})
    unknown = set(coords) - set(dims)
    if unknown:
        raise InputError(f"coords: {sorted(unknown)} are not among dims {dims!r}")
    origins = _per_dim(origin, len(dims), "origin")
    spacings = None if spacing is None else _per_dim(spacing, len(dims), "spacing")
    if spacings is not None and any(h <= 0 for h in spacings):
        raise InputError(f"spacing: expected positive numbers, got {spacings}")
    coord_attrs = dict(coord_attrs or {})
    out_coords: dict[str, Any] = {}
    for k, d in enumerate(dims):
        n = arr.shape[k]
        if d in coords:
            c = np.asarray(coords[d], dtype=np.float64)
            if c.shape != (n,):
                raise InputError(f"coords[{d!r}]: expected {n} values, got shape {c.shape}")
            if n >= 2:
                _uniform_spacing(c, d)
        elif spacings is not None:
            c = origins[k] + spacings[k] * np.arange(n, dtype=np.float64)
        else:
            raise InputError(f"spacing: needed for dim {d!r} (or give coords[{d!r}])")
        long_name, axis = _DIM_DEFAULTS.get(d, (d, ""))
        ca: dict[str, Any] = {"units": "1", "long_name": long_name}
        if axis:
            ca["axis"] = axis
        ca.update(coord_attrs.get(d, {}))
        out_coords[d] = xr.Variable((d,), np.ascontiguousarray(c), attrs=ca)
    all_dims = dims
    if components is not None:
        all_dims = dims + ("component",)
        out_coords["component"] = xr.Variable(("component",), np.array(list(components), dtype=str),
                                              attrs={"long_name": "vector component"})
    da_attrs = {"long_name": name}
    da_attrs.update(attrs or {})
    return xr.DataArray(arr, dims=all_dims, coords=out_coords, name=name, attrs=da_attrs)


def _time_attrs(units: str = "1") -> dict[str, Any]:
    return {"units": units, "long_name": "time", "axis": "T"}


# ----------------------------------------------------------------------------
# ODE helpers
# ----------------------------------------------------------------------------


def _check_lattice_1d(n: int, dt: float, n_name: str = "n") -> None:
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 2:
        raise InputError(f"{n_name}: expected an integer >= 2, got {n!r}")
    if not (isinstance(dt, (int, float, np.floating)) and math.isfinite(dt) and dt > 0):
        raise InputError(f"dt: expected a positive finite number, got {dt!r}")


def _check_finite(value: float, arg: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{arg}: expected a number, got {value!r}") from None
    if not math.isfinite(v):
        raise InputError(f"{arg}: expected a finite number, got {value!r}")
    return v


def _solve(rhs: Callable[[float, _FloatArray], Any], y0: Sequence[float], t: _FloatArray,
           events: Any = None, what: str = "ODE") -> Any:
    sol = solve_ivp(rhs, (float(t[0]), float(t[-1])), np.asarray(y0, dtype=np.float64), method="DOP853",
                    t_eval=t, rtol=ODE_RTOL, atol=ODE_ATOL, events=events)
    if sol.status == -1:
        raise InputError(f"initial data: the {what} solve failed ({sol.message})")
    return sol


# ----------------------------------------------------------------------------
# Paper Example 1
# ----------------------------------------------------------------------------

_SIN_K = math.pi**2 / 400.0  # potential coefficient: L = (1 + sin psi) psi'^2 - K psi^2


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
        raise InputError(f"psi0, dpsi0: energy {energy:.4g} reaches the singular point psi = -pi/2 "
                         f"(need |psi| < pi/2 throughout, i.e. E < {_SIN_K * (0.5 * math.pi) ** 2:.4g})")
    t = t0 + dt * np.arange(n, dtype=np.float64)
    sol = _solve(_sin_rhs, [psi0, dpsi0], t, what="oscillator_sin")
    src = (f"latticedft.systems.oscillator_sin: 2(sin psi+1)psi''+psi'^2 cos psi+pi^2/200 psi=0, "
           f"psi0={psi0!r}, dpsi0={dpsi0!r}; solve_ivp DOP853 rtol={ODE_RTOL:g} atol={ODE_ATOL:g}")
    psi = make_field(sol.y[0], ("t",), spacing=dt, origin=t0,
                     attrs={"long_name": "oscillator displacement (Qin 2020 Example 1)", "units": "1",
                            "source": src})
    if not return_velocity:
        return psi
    vel = make_field(sol.y[1], ("t",), spacing=dt, origin=t0, name="dpsi",
                     attrs={"long_name": "d psi / d t", "units": "1", "source": src})
    return psi, vel


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
    t = t0 + dt * np.arange(n, dtype=np.float64)
    sol = _solve(_wells_rhs, [psi0, dpsi0], t, what="oscillator_wells")
    src = (f"latticedft.systems.oscillator_wells: psi''-0.03[sin(1-psi^2)psi+0.1]=0, "
           f"psi0={psi0!r}, dpsi0={dpsi0!r}; solve_ivp DOP853 rtol={ODE_RTOL:g} atol={ODE_ATOL:g}")
    psi = make_field(sol.y[0], ("t",), spacing=dt, origin=t0,
                     attrs={"long_name": "oscillator displacement (Qin 2020 Example 2)", "units": "1",
                            "source": src})
    if not return_velocity:
        return psi
    vel = make_field(sol.y[1], ("t",), spacing=dt, origin=t0, name="dpsi",
                     attrs={"long_name": "d psi / d t", "units": "1", "source": src})
    return psi, vel


# ----------------------------------------------------------------------------
# Kepler problem (paper Section 4)
# ----------------------------------------------------------------------------

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
    if n is not None and t_end is not None:
        raise InputError("n, t_end: give at most one of them")
    energy = 0.5 * v0 * v0 - 1.0 / r0
    if n is None and t_end is None:
        if energy >= 0:
            raise InputError(f"n: required (or t_end) for an unbound orbit (v0={v0!r} >= escape speed "
                             f"{math.sqrt(2.0 / r0):.6g})")
        n = int(round(float(kepler_period(-0.5 / energy)) / dt)) + 1
    elif t_end is not None:
        t_end = _check_finite(t_end, "t_end")
        if t_end < dt:
            raise InputError(f"t_end: expected at least one step dt={dt!r}, got {t_end!r}")
        n = int(math.floor(t_end / dt + 1e-9)) + 1
    _check_lattice_1d(n, dt)  # type: ignore[arg-type]
    events = None
    if r_max is not None:
        r_max = _check_finite(r_max, "r_max")
        if r_max <= r0:
            raise InputError(f"r_max: expected more than r0={r0!r}, got {r_max!r}")

        def leave(t: float, y: _FloatArray) -> float:
            return math.hypot(y[0], y[1]) - r_max  # type: ignore[operator]

        leave.terminal = True  # type: ignore[attr-defined]
        leave.direction = 1.0  # type: ignore[attr-defined]
        events = leave
    t = dt * np.arange(n, dtype=np.float64)  # type: ignore[arg-type]
    sol = _solve(_kepler_rhs, [r0, 0.0, 0.0, v0], t, events=events, what="kepler_orbit")
    if sol.y.shape[1] < 2:
        raise InputError(f"r_max: the orbit leaves r <= {r_max!r} within the first step")
    src = (f"latticedft.systems.kepler_orbit: r''=-r/|r|^3 (GM=1, units 1 au, {KEPLER_TIME_UNIT_DAYS} d), "
           f"r0={r0!r}, v0={v0!r}, r_max={r_max!r}; solve_ivp DOP853 rtol={ODE_RTOL:g} atol={ODE_ATOL:g}")
    common = dict(spacing=dt, components=["x", "y"], coord_attrs={"t": _time_attrs(f"{KEPLER_TIME_UNIT_DAYS} days")})
    attrs = {"units": "au", "source": src, "r0": r0, "v0": v0, "GM": 1.0}
    psi = make_field(sol.y[:2].T, ("t",), attrs={"long_name": "position", **attrs}, **common)  # type: ignore[arg-type]
    if not return_velocity:
        return psi
    vel = make_field(sol.y[2:].T, ("t",), name="velocity",  # type: ignore[arg-type]
                     attrs={"long_name": "velocity", **attrs, "units": f"au / ({KEPLER_TIME_UNIT_DAYS} days)"},
                     **common)
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
    psi.attrs["source"] = (f"latticedft.systems.planet_orbit({key!r}, periods={periods!r}) from aphelion; "
                           + psi.attrs["source"])
    return psi


# ----------------------------------------------------------------------------
# Wave equation, exact
# ----------------------------------------------------------------------------


def _parse_modes(modes: Iterable[Sequence[float]], nidx: int, arg: str = "modes") -> list[tuple[tuple[int, ...], float, float]]:
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


def _check_positive(value: float, arg: str) -> float:
    v = _check_finite(value, arg)
    if v <= 0:
        raise InputError(f"{arg}: expected a positive number, got {value!r}")
    return v


def _check_count(value: int, arg: str, minimum: int) -> int:
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < minimum:
        raise InputError(f"{arg}: expected an integer >= {minimum}, got {value!r}")
    return int(value)


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
    return make_field(psi, ("t", "x"), spacing=(dt, dx), origin=(t0, 0.0),
                      attrs={"long_name": "string displacement", "units": "1",
                             "source": f"latticedft.systems.wave_string: exact standing modes "
                                       f"{[(k[0], a, p) for k, a, p in parsed]}, c={c!r}, length={length!r}"})


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
    for (k, l), amp, phase in parsed:
        omega = c * np.pi * math.hypot(k / length_x, l / length_y)
        shape = np.outer(np.sin(l * np.pi * y / length_y), np.sin(k * np.pi * x / length_x))
        psi += amp * np.cos(omega * t + phase)[:, None, None] * shape[None]
    psi[:, 0, :] = psi[:, -1, :] = 0.0
    psi[:, :, 0] = psi[:, :, -1] = 0.0
    return make_field(psi, ("t", "y", "x"), spacing=(dt, dy, dx), origin=(t0, 0.0, 0.0),
                      attrs={"long_name": "membrane displacement", "units": "1",
                             "source": f"latticedft.systems.wave_membrane: exact modes "
                                       f"{[(*k, a, p) for k, a, p in parsed]}, c={c!r}, "
                                       f"length_x={length_x!r}, length_y={length_y!r}"})


# ----------------------------------------------------------------------------
# Explicit leapfrog of the true equations
# ----------------------------------------------------------------------------


def _laplacian_periodic(u: _FloatArray, h: Sequence[float]) -> _FloatArray:
    out = np.zeros_like(u)
    for ax, hk in enumerate(h):
        out += (np.roll(u, -1, axis=ax) - 2.0 * u + np.roll(u, 1, axis=ax)) / (hk * hk)
    return out


def _laplacian_interior(u: _FloatArray, h: Sequence[float]) -> _FloatArray:
    inner = (slice(1, -1),) * u.ndim
    out = np.zeros(tuple(s - 2 for s in u.shape))
    for ax, hk in enumerate(h):
        plus = list(inner)
        plus[ax] = slice(2, None)
        minus = list(inner)
        minus[ax] = slice(None, -2)
        out += (u[tuple(plus)] - 2.0 * u[inner] + u[tuple(minus)]) / (hk * hk)
    return out


def _as_real_array(a: ArrayLike, arg: str) -> _FloatArray:
    arr = np.asarray(a.values if isinstance(a, xr.DataArray) else a)
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr) or arr.dtype == np.bool_:
        raise InputError(f"{arg}: expected real numbers, got dtype {arr.dtype}")
    arr = np.asarray(arr, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{arg}: contains NaN or infinity")
    return arr


def leapfrog(
    psi0: ArrayLike | xr.DataArray,
    psi1: ArrayLike | xr.DataArray,
    steps: int,
    dt: float,
    spacing: float | Sequence[float] | None = None,
    *,
    c: float = 1.0,
    force: Callable[[_FloatArray], ArrayLike] | None = None,
    boundary: str = "dirichlet",
    boundary_values: ArrayLike | xr.DataArray | None = None,
) -> _FloatArray | xr.DataArray:
    r"""Explicit leapfrog scheme for ``psi_tt = c^2 Laplacian(psi) + force(psi)``, 1+1D or 2+1D.

    .. math:: \frac{\psi_{i+1} - 2\psi_i + \psi_{i-1}}{\Delta t^2}
              = c^2 \sum_k \frac{\psi_{i}[j + e_k] - 2\psi_i[j] + \psi_i[j - e_k]}{h_k^2}
              + f(\psi_i)[j]

    This is exactly the scheme served by the discrete wave Lagrangian of
    DESIGN.md (with ``f = 0``); it is stable for
    ``c dt sqrt(sum 1/h_k^2) <= 1``, and in 1+1D with ``c dt = dx`` it is exact
    for every solution of the continuous wave equation.

    Parameters
    ----------
    psi0, psi1
        The first two time slices (spatial shape ``(nx,)`` or ``(ny, nx)``):
        numpy arrays, or DataArrays with spatial dims only (a scalar ``t``
        coordinate is allowed and sets the first time).
    steps
        Number of time steps: the result has ``steps + 1`` slices,
        ``t0 .. t0 + steps*dt``, and *includes* ``psi0`` and ``psi1`` as
        slices 0 and 1 (``steps - 1`` slices are computed).
    dt
        Time step.
    spacing
        Grid spacing, one number or one per spatial axis (array axis order,
        ``(dy, dx)``). May be omitted for DataArray input: it is then read
        from the coordinates.
    c
        Wave speed.
    force
        Optional on-site term ``f``: called with a whole slice (ndarray), must
        return an array of the same shape (``lambda u: -np.sin(u)`` gives
        sine-Gordon, ``lambda u: -u`` Klein–Gordon).
    boundary
        ``"dirichlet"``: the outer layer of sites (first and last index along
        every spatial axis) is not stepped; on slices ``>= 2`` it takes its
        values from `boundary_values` when given, else from ``psi1``
        (constant in time). ``"periodic"``: every axis wraps around.
    boundary_values
        Dirichlet data, shape ``(steps + 1, *spatial_shape)`` (e.g. the exact
        solution); only its outer layer on slices ``>= 2`` is read.

    Returns
    -------
    numpy.ndarray or xarray.DataArray
        A ``(steps + 1, *spatial_shape)`` float64 array when `psi0` is a numpy
        array (or list); a DataArray with dims ``("t", *psi0.dims)``, ``psi0``'s
        spatial coordinates and attributes and a ``t`` coordinate when `psi0` is
        a DataArray. Periodic output coordinates are marked
        ``periodic = "true"``.

    Examples
    --------
    >>> x = np.linspace(0.0, 1.0, 11)
    >>> u0 = np.sin(np.pi * x)
    >>> u = leapfrog(u0, u0 * np.cos(np.pi * 0.1), steps=10, dt=0.1, spacing=0.1)
    >>> u.shape, bool(np.allclose(u[10], -u0, atol=1e-12))  # Courant 1: exact half period
    ((11, 11), True)
    """
    is_da = isinstance(psi0, xr.DataArray)
    u0 = _as_real_array(psi0, "psi0")
    u1 = _as_real_array(psi1, "psi1")
    if u0.ndim not in (1, 2):
        raise InputError(f"psi0: expected 1 or 2 spatial dims, got shape {u0.shape}")
    if u1.shape != u0.shape:
        raise InputError(f"psi1: expected shape {u0.shape} like psi0, got {u1.shape}")
    if is_da:
        assert isinstance(psi0, xr.DataArray)
        if "t" in psi0.dims or "component" in psi0.dims:
            raise InputError(f"psi0: expected spatial dims only (one time slice), got dims {psi0.dims}")
    steps = _check_count(steps, "steps", 1)
    dt = _check_positive(dt, "dt")
    c = _check_finite(c, "c")
    if boundary not in ("dirichlet", "periodic"):
        raise InputError(f"boundary: expected 'dirichlet' or 'periodic', got {boundary!r}")
    if spacing is None:
        if not is_da:
            raise InputError("spacing: required for numpy input (or pass DataArrays with coordinates)")
        assert isinstance(psi0, xr.DataArray)
        missing = [d for d in psi0.dims if d not in psi0.coords]
        if missing:
            raise InputError(f"spacing: not given and psi0 has no coordinate for {missing}")
        h = [_uniform_spacing(psi0[d].values, str(d)) for d in psi0.dims]
    else:
        h = _per_dim(spacing, u0.ndim, "spacing")
        if any(v <= 0 for v in h):
            raise InputError(f"spacing: expected positive numbers, got {h}")
    bvals = None
    if boundary_values is not None:
        if boundary != "dirichlet":
            raise InputError("boundary_values: only used with boundary='dirichlet'")
        bvals = _as_real_array(boundary_values, "boundary_values")
        if bvals.shape != (steps + 1, *u0.shape):
            raise InputError(f"boundary_values: expected shape {(steps + 1, *u0.shape)}, got {bvals.shape}")

    out = np.empty((steps + 1, *u0.shape), dtype=np.float64)
    out[0] = u0
    out[1] = u1
    c2 = c * c
    dt2 = dt * dt
    periodic = boundary == "periodic"
    inner = (slice(1, -1),) * u0.ndim
    edge = np.ones(u0.shape, dtype=bool)
    edge[inner] = False
    for i in range(1, steps):
        u, up, new = out[i], out[i - 1], out[i + 1]
        f = None
        if force is not None:
            f = np.asarray(force(u), dtype=np.float64)
            if f.shape != u.shape:
                raise InputError(f"force: expected an array of shape {u.shape}, got {f.shape}")
        if periodic:
            acc = c2 * _laplacian_periodic(u, h)
            if f is not None:
                acc += f
            new[...] = 2.0 * u - up + dt2 * acc
        else:
            acc = c2 * _laplacian_interior(u, h)
            if f is not None:
                acc += f[inner]
            new[inner] = 2.0 * u[inner] - up[inner] + dt2 * acc
            new[edge] = (bvals[i + 1] if bvals is not None else u1)[edge]
    if not is_da:
        return out
    assert isinstance(psi0, xr.DataArray)
    t0 = 0.0
    t_attrs = _time_attrs()
    if "t" in psi0.coords and psi0["t"].ndim == 0:
        t0 = float(psi0["t"].values)
        t_attrs.update(psi0["t"].attrs)
    coord_attrs: dict[str, dict[str, Any]] = {"t": t_attrs}
    coords: dict[str, Any] = {}
    for d in psi0.dims:
        if d in psi0.coords:
            coords[str(d)] = psi0[d].values
            coord_attrs[str(d)] = dict(psi0[d].attrs)
        if periodic:
            coord_attrs.setdefault(str(d), {}).update(
                {"periodic": "true", "period": float(psi0.sizes[d] * h[list(psi0.dims).index(d)])})
    attrs = dict(psi0.attrs)
    attrs["source"] = (f"latticedft.systems.leapfrog: explicit leapfrog of psi_tt = c^2 Laplacian psi"
                       f"{' + force(psi)' if force is not None else ''}, c={c!r}, dt={dt!r}, spacing={h}, "
                       f"boundary={boundary}")
    return make_field(out, ("t", *(str(d) for d in psi0.dims)), spacing=(dt, *h), origin=(t0, *[0.0] * u0.ndim),
                      coords=coords, name=str(psi0.name) if psi0.name is not None else "psi",
                      attrs=attrs, coord_attrs=coord_attrs)


# ----------------------------------------------------------------------------
# Klein–Gordon benchmark
# ----------------------------------------------------------------------------


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
    return make_field(u, ("t", "x"), spacing=(dt, dx),
                      coord_attrs={"x": {"periodic": "true", "period": nx * dx}},
                      attrs={"long_name": "Klein-Gordon field u", "units": "1",
                             "source": f"latticedft.systems.klein_gordon: explicit scheme of u_tt = u_xx - u, "
                                       f"periodic, nx={nx}, dx={dx!r}, dt={dt!r}"})


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
        f.attrs["source"] += (f"; klein_gordon_training_set seed={int(seed)} member {m} of {n}, "
                              f"Fourier amplitudes N(0,1) exp(-{decay:g} k^4), u1 = Taylor step from v0")
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


# ----------------------------------------------------------------------------
# Sine-Gordon, exact
# ----------------------------------------------------------------------------


def _sg_lattice(xlim: tuple[float, float], nx: int, nt: int, dt: float, t0: float
                ) -> tuple[_FloatArray, _FloatArray, float, float]:
    try:
        xa, xb = (float(v) for v in xlim)
    except (TypeError, ValueError):
        raise InputError(f"xlim: expected (x_min, x_max), got {xlim!r}") from None
    if not (math.isfinite(xa) and math.isfinite(xb) and xb > xa):
        raise InputError(f"xlim: expected finite x_min < x_max, got {xlim!r}")
    nx = _check_count(nx, "nx", 3)
    nt = _check_count(nt, "nt", 2)
    dt = _check_positive(dt, "dt")
    t0 = _check_finite(t0, "t0")
    dx = (xb - xa) / (nx - 1)
    return t0 + dt * np.arange(nt, dtype=np.float64), xa + dx * np.arange(nx, dtype=np.float64), dt, dx


def _check_speed(velocity: float) -> float:
    v = _check_finite(velocity, "velocity")
    if not -1.0 < v < 1.0:
        raise InputError(f"velocity: expected |velocity| < 1 (the speed of light), got {velocity!r}")
    return v


def sine_gordon_breather(
    omega: float,
    velocity: float = 0.0,
    x0: float = 0.0,
    *,
    phase: float = 0.0,
    xlim: tuple[float, float] = (-20.0, 20.0),
    nx: int = 201,
    nt: int = 101,
    dt: float = 0.05,
    t0: float = 0.0,
) -> xr.DataArray:
    r"""Exact (moving) breather of the sine-Gordon equation ``psi_tt - psi_xx + sin psi = 0``.

    At rest, with frequency :math:`0 < \omega < 1`,

    .. math:: \psi_0(t, x) = 4\arctan\left[\frac{\sqrt{1-\omega^2}}{\omega}
              \frac{\cos(\omega t + \phi)}{\cosh(\sqrt{1-\omega^2}\,x)}\right];

    the moving breather is its Lorentz boost
    ``psi(t, x) = psi_0(gamma (t - v (x-x0)), gamma (x - x0 - v t))``,
    ``gamma = 1/sqrt(1 - v^2)``. Its energy
    (:func:`sine_gordon_energy`) is ``16 gamma sqrt(1 - omega^2)``.

    Sampled at ``t_i = t0 + i*dt`` and ``x_j = x_min + j*dx`` with
    ``dx = (x_max - x_min)/(nx - 1)``.

    Examples
    --------
    >>> b = sine_gordon_breather(0.5, velocity=0.2, nx=81, nt=3)
    >>> b.dims, b.shape
    (('t', 'x'), (3, 81))
    """
    omega = _check_finite(omega, "omega")
    if not 0.0 < omega < 1.0:
        raise InputError(f"omega: expected 0 < omega < 1, got {omega!r}")
    v = _check_speed(velocity)
    x0 = _check_finite(x0, "x0")
    phase = _check_finite(phase, "phase")
    t, x, dt, dx = _sg_lattice(xlim, nx, nt, dt, t0)
    gamma = 1.0 / math.sqrt(1.0 - v * v)
    T, X = np.meshgrid(t, x - x0, indexing="ij")
    tau = gamma * (T - v * X)
    xi = gamma * (X - v * T)
    kappa = math.sqrt(1.0 - omega * omega)
    psi = 4.0 * np.arctan(kappa / omega * np.cos(omega * tau + phase) / np.cosh(kappa * xi))
    return make_field(psi, ("t", "x"), spacing=(dt, dx), origin=(t[0], x[0]),
                      attrs={"long_name": "sine-Gordon field", "units": "1",
                             "source": f"latticedft.systems.sine_gordon_breather: exact breather, "
                                       f"omega={omega!r}, velocity={v!r}, x0={x0!r}, phase={phase!r}"})


def kink_antikink(
    velocity: float,
    *,
    xlim: tuple[float, float] = (-20.0, 20.0),
    nx: int = 401,
    nt: int = 201,
    dt: float = 0.05,
    t0: float = -5.0,
) -> xr.DataArray:
    r"""Exact kink–antikink collision of the sine-Gordon equation ``psi_tt - psi_xx + sin psi = 0``.

    .. math:: \psi(t, x) = 4\arctan\frac{\sinh(\gamma v t)}{v\cosh(\gamma x)},
              \qquad \gamma = \frac{1}{\sqrt{1 - v^2}},\ 0 < v < 1.

    A kink and an antikink approach with speed `v`, pass through each other
    at ``t = 0`` and separate (the field is ``-2 pi`` between them before the
    collision and ``+2 pi`` after). Energy ``16 gamma``. Sampled at
    ``t_i = t0 + i*dt`` (default: ``-5 .. 5``) and
    ``x_j = x_min + j*dx``.

    Examples
    --------
    >>> kk = kink_antikink(0.5, nx=41, nt=3, t0=-1.0, dt=1.0)
    >>> kk.shape, float(kk.sel(t=0.0).max())
    ((3, 41), 0.0)
    """
    v = _check_speed(velocity)
    if v <= 0.0:
        raise InputError(f"velocity: expected 0 < velocity < 1, got {velocity!r}")
    t, x, dt, dx = _sg_lattice(xlim, nx, nt, dt, t0)
    gamma = 1.0 / math.sqrt(1.0 - v * v)
    psi = 4.0 * np.arctan(np.outer(np.sinh(gamma * v * t), 1.0 / (v * np.cosh(gamma * x))))
    return make_field(psi, ("t", "x"), spacing=(dt, dx), origin=(t[0], x[0]),
                      attrs={"long_name": "sine-Gordon field", "units": "1",
                             "source": f"latticedft.systems.kink_antikink: exact collision solution, "
                                       f"velocity={v!r}"})


def sine_gordon_energy(psi: xr.DataArray) -> xr.DataArray:
    r"""Energy of a sine-Gordon field sample, slice by slice.

    .. math:: E(t) = \int \left[\tfrac12\psi_t^2 + \tfrac12\psi_x^2 + 1 - \cos\psi\right] dx,

    approximated on the lattice with second-order differences
    (:func:`numpy.gradient`: centred inside, one-sided at the first and last
    time slice and at non-periodic x ends) and the trapezoidal rule in x. If
    the ``x`` coordinate is marked ``periodic = "true"`` the x differences
    wrap around and the sum runs over all sites. Accurate to ``O(dt^2 + dx^2)``
    (plus the field's tails outside the window).

    Parameters
    ----------
    psi
        DataArray ``psi(t, x)`` with uniform ``t`` and ``x`` coordinates.

    Returns
    -------
    xarray.DataArray
        ``energy(t)``.

    Examples
    --------
    >>> e = sine_gordon_energy(sine_gordon_breather(0.6, nx=1601, nt=5, dt=0.01))
    >>> bool(abs(float(e[2]) - 16 * 0.8) < 1e-3)  # exact: 16 sqrt(1 - omega^2)
    True
    """
    if not isinstance(psi, xr.DataArray) or psi.dims != ("t", "x"):
        raise InputError(f"psi: expected a DataArray with dims ('t', 'x'), got "
                         f"{psi.dims if isinstance(psi, xr.DataArray) else type(psi).__name__}")
    for d in ("t", "x"):
        if d not in psi.coords:
            raise InputError(f"psi: needs a {d!r} coordinate to read the spacing")
    dt = _uniform_spacing(psi["t"].values, "t")
    dx = _uniform_spacing(psi["x"].values, "x")
    u = _as_real_array(psi, "psi")
    ut = np.gradient(u, dt, axis=0)
    if str(psi["x"].attrs.get("periodic", "")).lower() == "true":
        ux = (np.roll(u, -1, axis=1) - np.roll(u, 1, axis=1)) / (2.0 * dx)
        dens = 0.5 * ut**2 + 0.5 * ux**2 + 1.0 - np.cos(u)
        e = dens.sum(axis=1) * dx
    else:
        ux = np.gradient(u, dx, axis=1)
        dens = 0.5 * ut**2 + 0.5 * ux**2 + 1.0 - np.cos(u)
        e = trapezoid(dens, dx=dx, axis=1)
    return xr.DataArray(np.ascontiguousarray(e), dims=("t",), coords={"t": psi["t"]}, name="energy",
                        attrs={"long_name": "sine-Gordon energy", "units": "1"})


# ----------------------------------------------------------------------------
# Energies of wave-type fields (invariants of served fields)
# ----------------------------------------------------------------------------


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
    >>> psi = wave_string([(1, 1.0)], nx=401, nt=5)
    >>> bool(abs(float(field_energy(psi)[2]) - np.pi**2 / 4) < 1e-4)  # exact: (k pi)^2 A^2 / 4
    True
    """
    if not isinstance(psi, xr.DataArray) or psi.ndim not in (2, 3) or psi.dims[0] != "t":
        raise InputError(f"psi: expected a DataArray psi(t, x) or psi(t, y, x), got "
                         f"{psi.dims if isinstance(psi, xr.DataArray) else type(psi).__name__}")
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
        if str(psi[psi.dims[k]].attrs.get("periodic", "")).lower() == "true":
            da, db = np.roll(a, -1, axis=k) - a, np.roll(b, -1, axis=k) - b
        else:
            da, db = np.diff(a, axis=k), np.diff(b, axis=k)
        e = e + (c * c / (2.0 * h[k] ** 2)) * (da * db).sum(axis=axes)
    e = e * math.prod(h[1:])
    out = np.concatenate([e[:1], 0.5 * (e[:-1] + e[1:]), e[-1:]])
    return xr.DataArray(out, dims=("t",), coords={"t": psi["t"]}, name="energy",
                        attrs={"long_name": "discrete field energy", "units": "1"})


def wave_energy(psi: xr.DataArray) -> xr.DataArray:
    """Energy of the wave equation ``psi_tt = Laplacian(psi)`` (``c = 1``): :func:`field_energy`.

    For the ``invariant = "latticedft.systems:wave_energy"`` key of a case
    (string or membrane).
    """
    return field_energy(psi, c=1.0, mass=0.0)


def klein_gordon_energy(psi: xr.DataArray) -> xr.DataArray:
    """Energy of ``u_tt = u_xx - u`` (the Klein–Gordon benchmark): :func:`field_energy` with ``mass = 1``."""
    return field_energy(psi, c=1.0, mass=1.0)
