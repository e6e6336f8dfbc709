"""The explicit leapfrog scheme of ``psi_tt = c^2 Laplacian(psi) + f(psi)``: the reference numerics.

:func:`leapfrog` steps the standard second-order central-difference scheme
(the Störmer–Verlet / leapfrog scheme in time, the three-point Laplacian along
each spatial axis) in 1+1D or 2+1D, with a fixed (Dirichlet) frame or periodic
axes. It is the baseline and the numpy speed reference of served fields, and
the generator of the periodic Klein–Gordon data
(:func:`latticedft.systems.klein_gordon`). Its discrete energy is
:func:`latticedft.systems.field_energy`.

The function is split into its argument checks (:func:`_leapfrog_args`), the
stepping loop (:func:`_leapfrog_steps`, one :func:`_step` per slice), and the
DataArray output (:func:`_leapfrog_field`). What depends on the boundary kind
(which sites are stepped, the neighbours of a site) is the kind's own rule
from :mod:`latticedft._boundary`: a Dirichlet axis keeps its outer layer of
sites (the frame), a periodic axis wraps around.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import xarray as xr
from numpy.typing import ArrayLike, NDArray

from latticedft._boundary import KINDS, BoundaryKind, boundary_kinds, spatial_kind
from latticedft._errors import InputError
from latticedft._layout import PERIODIC_ATTR, periodic_attr
from latticedft.systems._fields import (
    _as_real_array,
    _check_count,
    _check_finite,
    _check_positive,
    _FloatArray,
    _per_dim,
    _time_attrs,
    _uniform_spacing,
    make_field,
)

__all__ = ["leapfrog"]

_Force = Callable[[_FloatArray], ArrayLike]


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

    This is exactly the scheme served by the discrete wave Lagrangian
    (:func:`latticedft.lagrangians.wave`, with ``f = 0``); it is stable for
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
    u0, u1, steps, dt, c, h, bvals = _leapfrog_args(psi0, psi1, steps, dt, spacing, c, boundary, boundary_values)
    out = _leapfrog_steps(u0, u1, steps, dt, h, c, force, spatial_kind(boundary), bvals)
    if not isinstance(psi0, xr.DataArray):
        return out
    return _leapfrog_field(out, psi0, dt, h, c, force, boundary)


# ----------------------------------------------------------------------------
# Argument checks
# ----------------------------------------------------------------------------


def _leapfrog_args(
    psi0: ArrayLike | xr.DataArray,
    psi1: ArrayLike | xr.DataArray,
    steps: int,
    dt: float,
    spacing: float | Sequence[float] | None,
    c: float,
    boundary: str,
    boundary_values: ArrayLike | xr.DataArray | None,
) -> tuple[_FloatArray, _FloatArray, int, float, float, list[float], _FloatArray | None]:
    """The checked arguments of :func:`leapfrog`: ``(u0, u1, steps, dt, c, spacing, boundary data)``."""
    u0 = _as_real_array(psi0, "psi0")
    u1 = _as_real_array(psi1, "psi1")
    if u0.ndim not in (1, 2):
        raise InputError(f"psi0: expected 1 or 2 spatial dims, got shape {u0.shape}")
    if u1.shape != u0.shape:
        raise InputError(f"psi1: expected shape {u0.shape} like psi0, got {u1.shape}")
    if isinstance(psi0, xr.DataArray) and ("t" in psi0.dims or "component" in psi0.dims):
        raise InputError(f"psi0: expected spatial dims only (one time slice), got dims {psi0.dims}")
    steps = _check_count(steps, "steps", 1)
    dt = _check_positive(dt, "dt")
    c = _check_finite(c, "c")
    kind = spatial_kind(boundary)
    h = _leapfrog_spacing(psi0, spacing, u0.ndim)
    bvals = None
    if boundary_values is not None:
        if not kind.given_edges:
            framed = " or ".join(f"boundary={k!r}" for k in boundary_kinds() if KINDS[k].given_edges)
            raise InputError.at("boundary_values", f"only used with {framed}")
        bvals = _as_real_array(boundary_values, "boundary_values")
        if bvals.shape != (steps + 1, *u0.shape):
            raise InputError(f"boundary_values: expected shape {(steps + 1, *u0.shape)}, got {bvals.shape}")
    return u0, u1, steps, dt, c, h, bvals


def _leapfrog_spacing(
    psi0: ArrayLike | xr.DataArray, spacing: float | Sequence[float] | None, ndim: int
) -> list[float]:
    """The grid spacing per spatial axis: given, or read from the coordinates of a DataArray `psi0`."""
    if spacing is None:
        if not isinstance(psi0, xr.DataArray):
            raise InputError("spacing: required for numpy input (or pass DataArrays with coordinates)")
        missing = [d for d in psi0.dims if d not in psi0.coords]
        if missing:
            raise InputError(f"spacing: not given and psi0 has no coordinate for {missing}")
        return [_uniform_spacing(psi0[d].values, str(d)) for d in psi0.dims]
    h = _per_dim(spacing, ndim, "spacing")
    if any(v <= 0 for v in h):
        raise InputError(f"spacing: expected positive numbers, got {h}")
    return h


# ----------------------------------------------------------------------------
# The stepping loop and its boundary rules
# ----------------------------------------------------------------------------


def _leapfrog_steps(
    u0: _FloatArray,
    u1: _FloatArray,
    steps: int,
    dt: float,
    h: Sequence[float],
    c: float,
    force: _Force | None,
    kind: BoundaryKind,
    bvals: _FloatArray | None,
) -> _FloatArray:
    """Slices ``0 .. steps`` of the scheme from the first two, `u0` and `u1`, every spatial axis of `kind`.

    The interior sites (all of them on periodic axes) are stepped; the other
    sites (the outer layer of a Dirichlet frame) of slice ``i + 1`` are copied
    from ``bvals[i + 1]`` when given, else from `u1`.
    """
    out = np.empty((steps + 1, *u0.shape), dtype=np.float64)
    out[0] = u0
    out[1] = u1
    c2 = c * c
    dt2 = dt * dt
    kinds = (kind,) * u0.ndim
    inner = tuple(k.interior(n, 1) for k, n in zip(kinds, u0.shape))
    mask = np.ones(u0.shape, dtype=bool)
    mask[inner] = False
    edge = mask if mask.any() else None  # sites outside the interior, if any
    for i in range(1, steps):
        u, up, new = out[i], out[i - 1], out[i + 1]
        f = _force_values(force, u)
        frame = bvals[i + 1] if bvals is not None else u1
        _step(new, u, up, f, c2, dt2, h, kinds, inner, edge, frame)
    return out


def _force_values(force: _Force | None, u: _FloatArray) -> _FloatArray | None:
    """The on-site term ``force(u)`` as a float64 array of `u`'s shape (None without a force)."""
    if force is None:
        return None
    f = np.asarray(force(u), dtype=np.float64)
    if f.shape != u.shape:
        raise InputError(f"force: expected an array of shape {u.shape}, got {f.shape}")
    return f


def _step(
    new: _FloatArray,
    u: _FloatArray,
    up: _FloatArray,
    f: _FloatArray | None,
    c2: float,
    dt2: float,
    h: Sequence[float],
    kinds: Sequence[BoundaryKind],
    inner: tuple[slice, ...],
    edge: NDArray[np.bool_] | None,
    frame: _FloatArray,
) -> None:
    """One step: the interior of `new` from `u` and `up`, its other sites (if any) from `frame`."""
    acc = c2 * _laplacian(u, h, kinds, inner)
    if f is not None:
        acc += f[inner]
    new[inner] = 2.0 * u[inner] - up[inner] + dt2 * acc
    if edge is not None:
        new[edge] = frame[edge]


# ----------------------------------------------------------------------------
# Finite differences
# ----------------------------------------------------------------------------


def _laplacian(
    u: _FloatArray, h: Sequence[float], kinds: Sequence[BoundaryKind], inner: tuple[slice, ...]
) -> _FloatArray:
    """Three-point Laplacian of `u` at the interior sites ``u[inner]``, each axis's neighbours by its kind."""
    centre = u[inner]
    out = np.zeros(centre.shape)
    for ax, hk in enumerate(h):
        line = list(inner)
        line[ax] = slice(None)
        v = u[tuple(line)]  # interior along the other axes, whole along this one
        plus = kinds[ax].shifted(v, ax, 1, 1)
        minus = kinds[ax].shifted(v, ax, -1, 1)
        out += (plus - 2.0 * centre + minus) / (hk * hk)
    return out


# ----------------------------------------------------------------------------
# DataArray output
# ----------------------------------------------------------------------------


def _leapfrog_field(
    out: _FloatArray, psi0: xr.DataArray, dt: float, h: Sequence[float], c: float, force: _Force | None, boundary: str
) -> xr.DataArray:
    """`out` as a DataArray with dims ``("t", *psi0.dims)``, psi0's coordinates and attributes."""
    periodic = spatial_kind(boundary).wraps
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
                {PERIODIC_ATTR: periodic_attr(True), "period": float(psi0.sizes[d] * h[list(psi0.dims).index(d)])}
            )
    attrs = dict(psi0.attrs)
    attrs["source"] = (
        f"latticedft.systems.leapfrog: explicit leapfrog of psi_tt = c^2 Laplacian psi"
        f"{' + force(psi)' if force is not None else ''}, c={c!r}, dt={dt!r}, spacing={h}, "
        f"boundary={boundary}"
    )
    return make_field(
        out,
        ("t", *(str(d) for d in psi0.dims)),
        spacing=(dt, *h),
        origin=(t0, *[0.0] * psi0.ndim),
        coords=coords,
        name=str(psi0.name) if psi0.name is not None else "psi",
        attrs=attrs,
        coord_attrs=coord_attrs,
    )
