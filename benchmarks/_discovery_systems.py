"""The systems of the discovery benchmark: data, the true discrete ``L_d`` and the leapfrog of the true equation.

Each :class:`System` holds its training fields, a test field that goes beyond them (larger amplitude, longer
time or a larger lattice), the true discrete Lagrangian written in the symbols of the first-order stencil
(``u{point}_{component}``, :mod:`latticedft._symbolic`) and the explicit leapfrog of the true equation at the
data's own steps, in numpy.

- ODE systems (one or a few degrees of freedom) are defined by their continuous Lagrangian ``L(q, v)`` (sympy).
  Their data are DOP853 solutions (``rtol = atol = 1e-12``) sampled at the lattice times. The true ``L_d`` is the
  trapezoid rule ``h (L(u0, v) + L(u1, v)) / 2`` with ``v = (u1 - u0) / h``; with a constant mass its discrete
  Euler-Lagrange equation is the Stormer-Verlet (leapfrog) scheme. The leapfrog baseline is the central difference
  ``q[k+1] - 2 q[k] + q[k-1] = h^2 a(q[k], (q[k+1] - q[k-1]) / (2 h))``: explicit where the acceleration does
  not depend on the velocity, a fixed-point solve of the velocity term where it does (second order either way).
- Field systems ``psi_tt = Laplacian(psi) + f(psi)`` on a lattice: their data are the lattice equation (the
  three-point Laplacian) stepped with a time step ten times finer than the data's and sampled; the true ``L_d``
  is ``(D_t psi)^2 / 2 - sum_k (D_k psi)^2 / 2 - V(psi)`` at the cell's base point, whose discrete
  Euler-Lagrange equation is the explicit leapfrog :func:`latticedft.systems.leapfrog`.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import sympy
import xarray as xr
from scipy.integrate import solve_ivp

from latticedft import systems
from latticedft._layout import PERIODIC_ATTR, periodic_attr
from latticedft._symbolic import SymbolicLd, cell_symbols

from ._terms import del_equations, neighbour

__all__ = [
    "System",
    "SYSTEMS",
    "build",
    "chosen",
    "ode_ld",
    "ode_leapfrog",
    "OdeSpec",
    "variational_data",
    "variational_served",
]

Accel = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass
class OdeSpec:
    """A system of ``m`` degrees of freedom: ``L(q, v)`` in sympy (symbols ``q0..``, ``v0..``) and its
    acceleration (numpy, derived from ``L``): ``accel(q, v)`` free, ``forced(q, v, f)`` with generalised forces
    ``f`` on the right of the Euler-Lagrange equations."""

    lagrangian: Any
    q: tuple[Any, ...]
    v: tuple[Any, ...]
    forced: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
    velocity_dependent: bool
    accel_exprs: tuple[Any, ...]

    def accel(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The free acceleration."""
        return self.forced(q, v, np.zeros(len(self.q)))


@dataclass
class System:
    """One row of the discovery table."""

    name: str
    train: list[xr.DataArray]
    test: xr.DataArray
    #: served slices of the test (its first two and, on Dirichlet axes, its boundary strips given)
    slices: int
    #: the true discrete ``L_d`` on the first-order stencil of the data's lattice
    true_ld: SymbolicLd
    #: ``(first slice, second slice, slices) -> (slices, ...)`` values of the leapfrog of the true equation
    leapfrog: Callable[[xr.DataArray, int], np.ndarray]
    boundary: str | None = None
    #: report the error after these steps too (Kepler: 50 and 200)
    at: tuple[int, ...] = ()
    #: what the training covers and what the test asks beyond it
    range_note: str = ""
    #: the ODE spec (peers fit ODE systems only) and the test's exact initial state
    ode: OdeSpec | None = None
    test_state: tuple[np.ndarray, np.ndarray] | None = None
    train_states: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    #: the key of :data:`SYSTEMS` it was built from
    key: str = ""


# ----------------------------------------------------------------------------------------------------------
# ODE systems
# ----------------------------------------------------------------------------------------------------------


def ode_spec(m: int, lagrangian: Callable[[tuple[Any, ...], tuple[Any, ...]], Any]) -> OdeSpec:
    """The spec of ``L = lagrangian(q, v)``: its Euler-Lagrange equations ``d/dt dL/dv - dL/dq = f`` solved
    for the accelerations."""
    q = sympy.symbols(f"q0:{m}", real=True)
    v = sympy.symbols(f"v0:{m}", real=True)
    a = sympy.symbols(f"a0:{m}", real=True)
    f = sympy.symbols(f"f0:{m}", real=True)
    L = lagrangian(q, v)
    eqs = []
    for i in range(m):
        p = sympy.diff(L, v[i])
        dpdt = sum(sympy.diff(p, q[j]) * v[j] + sympy.diff(p, v[j]) * a[j] for j in range(m))
        eqs.append(sympy.expand(dpdt - sympy.diff(L, q[i]) - f[i]))
    sol = sympy.solve(eqs, a, dict=True)[0]
    exprs = tuple(sympy.simplify(sol[a[i]]) for i in range(m))
    fn = sympy.lambdify([q, v, f], list(exprs), "numpy")
    depends = any(e.has(*v) for e in exprs)

    def forced(qv: np.ndarray, vv: np.ndarray, fv: np.ndarray) -> np.ndarray:
        return np.array(fn(tuple(qv), tuple(vv), tuple(fv)), dtype=float).reshape(m)

    free = tuple(e.subs({s: 0 for s in f}) for e in exprs)
    return OdeSpec(L, q, v, forced, depends, free)


def ode_ld(spec: OdeSpec, h: float, rule: str = "trapezoid") -> SymbolicLd:
    """The trapezoid discrete Lagrangian of ``spec`` in ``u{p}_{c}`` (stencil offsets ``(0,), (1,)``); ``rule =
    "midpoint"``: ``h L((u0 + u1) / 2, v)`` instead."""
    m = len(spec.q)
    (u0, u1) = cell_symbols(2, m)
    vel = [(u1[c] - u0[c]) / h for c in range(m)]
    points = [[(a + b) / 2 for a, b in zip(u0, u1)]] if rule == "midpoint" else [u0, u1]
    parts = [
        spec.lagrangian.subs({**dict(zip(spec.q, u)), **dict(zip(spec.v, vel))}, simultaneous=True) for u in points
    ]
    return SymbolicLd(sympy.expand(h * sum(parts) / len(parts)), ((0,), (1,)), m, (h,))


def ode_field(spec: OdeSpec, q0: Sequence[float], v0: Sequence[float], n: int, h: float) -> xr.DataArray:
    """The exact motion from ``(q0, v0)`` at ``n`` times ``0, h, ..`` (DOP853, ``rtol = atol = 1e-12``)."""
    m = len(spec.q)

    def rhs(_: float, y: np.ndarray) -> np.ndarray:
        return np.concatenate([y[m:], spec.accel(y[:m], y[m:])])

    t = h * np.arange(n)
    sol = solve_ivp(rhs, (0.0, t[-1]), [*q0, *v0], t_eval=t, method="DOP853", rtol=1e-12, atol=1e-12)
    if not sol.success or sol.y.shape[1] != n:
        raise RuntimeError(f"reference solve failed: {sol.message}")
    values = sol.y[:m].T
    if m == 1:
        return systems.make_field(values[:, 0], ("t",), spacing=h)
    return systems.make_field(values, ("t",), spacing=h, components=[f"q{c}" for c in range(m)])


def ode_leapfrog(accel: Accel, velocity_dependent: bool, q_a: np.ndarray, q_b: np.ndarray, slices: int, h: float):
    """The central-difference leapfrog of ``q'' = a(q, q')`` from two slices: ``(slices, m)`` positions.

    ``q[k+1] = 2 q[k] - q[k-1] + h^2 a(q[k], (q[k+1] - q[k-1]) / (2 h))``: explicit (Stormer-Verlet) when
    ``a`` does not depend on the velocity, else solved by fixed-point iteration (to round-off)."""
    out = np.empty((slices, len(q_a)))
    out[0], out[1] = q_a, q_b
    for k in range(1, slices - 1):
        prev, cur = out[k - 1], out[k]
        nxt = 2 * cur - prev + h * h * accel(cur, (cur - prev) / h)
        if velocity_dependent:
            for _ in range(100):
                new = 2 * cur - prev + h * h * accel(cur, (nxt - prev) / (2 * h))
                done = np.max(np.abs(new - nxt)) <= 1e-15 * (1.0 + np.max(np.abs(new)))
                nxt = new
                if done:
                    break
        out[k + 1] = nxt
    return out


def _ode_system(
    name: str,
    spec: OdeSpec,
    h: float,
    train: list[tuple[Sequence[float], Sequence[float], int]],
    test: tuple[Sequence[float], Sequence[float], int],
    note: str,
    at: tuple[int, ...] = (),
) -> System:
    fields = [ode_field(spec, q0, v0, n, h) for q0, v0, n in train]
    test_field = ode_field(spec, test[0], test[1], test[2], h)

    def leapfrog(ref: xr.DataArray, slices: int) -> np.ndarray:
        vals = np.asarray(ref.values, dtype=float).reshape(ref.sizes["t"], -1)
        out = ode_leapfrog(spec.accel, spec.velocity_dependent, vals[0], vals[1], slices, h)
        return out.reshape((slices, *ref.shape[1:]))

    return System(
        name,
        fields,
        test_field,
        test[2],
        ode_ld(spec, h),
        leapfrog,
        at=at,
        range_note=note,
        ode=spec,
        test_state=(np.asarray(test[0], float), np.asarray(test[1], float)),
        train_states=[(np.asarray(q0, float), np.asarray(v0, float)) for q0, v0, _ in train],
    )


def oscillator_sin(quick: bool) -> System:
    """Paper Example 1, ``L = (1 + sin q) q'^2 - pi^2/400 q^2``, dt = 1: trained from 1.2 over 51 slices (the
    paper), tested from 1.2 over 201 (four times as long; a larger amplitude nears the singular mass at
    ``-pi/2``, where the leapfrog itself fails at dt = 1)."""
    spec = ode_spec(1, lambda q, v: (1 + sympy.sin(q[0])) * v[0] ** 2 - sympy.pi**2 / 400 * q[0] ** 2)
    n = 101 if quick else 201
    note = f"51 -> {n} slices"
    return _ode_system("oscillator (paper Ex. 1)", spec, 1.0, [([1.2], [0.0], 51)], ([1.2], [0.0], n), note)


def oscillator_wells(quick: bool) -> System:
    """Paper Example 2, ``L = q'^2/2 + 0.015 (cos(q^2 - 1) + 0.2 q)``, dt = 1: trained from 1.7 (51 slices),
    tested from 1.75 over 151."""
    spec = ode_spec(1, lambda q, v: v[0] ** 2 / 2 + sympy.Rational(15, 1000) * (sympy.cos(q[0] ** 2 - 1) + q[0] / 5))
    n = 101 if quick else 151
    return _ode_system(
        "oscillator (paper Ex. 2)",
        spec,
        1.0,
        [([1.7], [0.0], 51)],
        ([1.75], [0.0], n),
        f"1.7 -> 1.75, 51 -> {n} slices",
    )


KEPLER_GM = 0.40038


def kepler(quick: bool) -> System:
    """Kepler from one orbit (GM = 0.40038, q0 = (1, 0), v0 = (0, 0.6), h = 0.1, 51 samples); test from
    q0 = (1.1, -0.01), v0 = (0, 0.6), errors after 50 and 200 steps."""
    gm = sympy.Float(KEPLER_GM)
    spec = ode_spec(2, lambda q, v: (v[0] ** 2 + v[1] ** 2) / 2 + gm / sympy.sqrt(q[0] ** 2 + q[1] ** 2))
    return _ode_system(
        "Kepler, one orbit",
        spec,
        0.1,
        [((1.0, 0.0), (0.0, 0.6), 51)],
        ((1.1, -0.01), (0.0, 0.6), 201),
        "1 orbit, 51 slices -> another",
        at=(50, 200),
    )


def charged_particle(quick: bool) -> System:
    """A charged particle in a uniform field B = 1, ``L = |v|^2/2 + (x v_y - y v_x)/2``, h = 0.1: trained on
    speed 1 (101 slices), tested at speed 2.06 over 301."""
    spec = ode_spec(2, lambda q, v: (v[0] ** 2 + v[1] ** 2) / 2 + (q[0] * v[1] - q[1] * v[0]) / 2)
    n = 151 if quick else 301
    return _ode_system(
        "charged particle, B = 1",
        spec,
        0.1,
        [((0.0, 0.0), (1.0, 0.0), 101), ((0.5, 0.0), (0.0, 0.7), 101)],
        ((0.0, 0.0), (2.0, 0.5), n),
        f"speeds 1 and 0.7 -> 2.06, {n} slices",
    )


def pendulum(quick: bool) -> System:
    """The pendulum ``L = q'^2/2 + cos q``, dt = 0.1: trained at amplitudes 2.0 and 2.6 rad (101 slices each),
    tested at 2.9 over 301."""
    spec = ode_spec(1, lambda q, v: v[0] ** 2 / 2 + sympy.cos(q[0]))
    n = 151 if quick else 301
    return _ode_system(
        "pendulum", spec, 0.1, [([2.0], [0.0], 101), ([2.6], [0.0], 101)], ([2.9], [0.0], n), "2.0, 2.6 rad -> 2.9 rad"
    )


def double_pendulum(quick: bool) -> System:
    """The double pendulum (unit masses and lengths, g = 1), h = 0.1: trained from two starts (151 slices each),
    tested from a larger one over 301."""

    def lag(q: tuple[Any, ...], v: tuple[Any, ...]) -> Any:
        kin = v[0] ** 2 + v[1] ** 2 / 2 + v[0] * v[1] * sympy.cos(q[0] - q[1])
        return kin + 2 * sympy.cos(q[0]) + sympy.cos(q[1])

    spec = ode_spec(2, lag)
    n = 151 if quick else 301
    return _ode_system(
        "double pendulum",
        spec,
        0.1,
        [((0.5, 0.0), (0.0, 0.0), 151), ((0.3, -0.6), (0.0, 0.0), 151)],
        ((0.8, -0.9), (0.0, 0.0), n),
        "starts 0.5, 0.6 rad -> 0.9 rad",
    )


# ----------------------------------------------------------------------------------------------------------
# Field systems
# ----------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FieldEq:
    """``psi_tt = Laplacian(psi) + force(psi)`` with ``force = -V'`` (``potential`` in sympy of ``x``)."""

    potential: Callable[[Any], Any]
    force: Callable[[np.ndarray], np.ndarray]


def field_ld(eq: FieldEq, spacing: Sequence[float]) -> SymbolicLd:
    """``(D_t psi)^2/2 - sum_k (D_k psi)^2/2 - V(psi)`` at the base point, on the first-order stencil."""
    n = len(spacing)
    u = [s[0] for s in cell_symbols(n + 1, 1)]
    expr = (u[1] - u[0]) ** 2 / (2 * spacing[0] ** 2)
    expr -= sum((u[k + 1] - u[0]) ** 2 / (2 * spacing[k] ** 2) for k in range(1, n))
    expr -= eq.potential(u[0])
    offsets = tuple(tuple(1 if j == k else 0 for j in range(n)) for k in range(-1, n))
    return SymbolicLd(sympy.expand(expr), offsets, 1, tuple(float(s) for s in spacing))


def _fine_field(eq: FieldEq, psi0: np.ndarray, spacing: Sequence[float], n: int, boundary: str, refine: int = 10):
    """The lattice equation from ``psi0`` at rest, stepped at ``dt / refine`` and sampled every ``refine``."""
    dt, h = spacing[0] / refine, list(spacing[1:])
    two = systems.leapfrog(psi0, psi0, 2, dt, h, force=eq.force, boundary=boundary)
    psi1 = 0.5 * (psi0 + np.asarray(two)[2])  # psi0 + dt^2 a(psi0) / 2: at rest at t = 0
    fine = np.asarray(systems.leapfrog(psi0, psi1, (n - 1) * refine, dt, h, force=eq.force, boundary=boundary))
    values = fine[::refine]
    dims = ("t", "x") if psi0.ndim == 1 else ("t", "y", "x")
    attrs = {}
    if boundary == "periodic":
        attrs = {
            d: {PERIODIC_ATTR: periodic_attr(True), "period": psi0.shape[i] * spacing[i + 1]}
            for i, d in enumerate(dims[1:])
        }
    return systems.make_field(values, dims, spacing=tuple(spacing), coord_attrs=attrs)


def _field_leapfrog(eq: FieldEq, boundary: str) -> Callable[[xr.DataArray, int], np.ndarray]:
    def run(ref: xr.DataArray, slices: int) -> np.ndarray:
        vals = np.asarray(ref.values, dtype=float)
        sp = [float(ref[d][1] - ref[d][0]) for d in ref.dims]
        bvals = vals[:slices] if boundary == "dirichlet" else None
        out = systems.leapfrog(
            vals[0], vals[1], slices - 1, sp[0], sp[1:], force=eq.force, boundary=boundary, boundary_values=bvals
        )
        return np.asarray(out)

    return run


def _smooth(shape: tuple[int, ...], seed: int) -> np.ndarray:
    """A smooth periodic field of unit maximum: a few low Fourier modes with random phases."""
    rng = np.random.default_rng(seed)
    grids = np.meshgrid(*[2 * np.pi * np.arange(s) / s for s in shape], indexing="ij")
    out = np.zeros(shape)
    for k in range(1, 3):
        for g in grids:
            out += rng.normal() * np.cos(k * g + rng.uniform(0, 2 * np.pi))
    return out / np.max(np.abs(out))


SINE_GORDON = FieldEq(lambda x: 1 - sympy.cos(x), lambda u: -np.sin(u))
PHI4 = FieldEq(lambda x: (x**2 - 1) ** 2 / 4, lambda u: u - u**3)
NLKG = FieldEq(lambda x: x**2 / 2 + sympy.Rational(3, 40) * x**4, lambda u: -u - 0.3 * u**3)


def _field_system(
    name: str,
    eq: FieldEq,
    shape: tuple[int, ...],
    spacing: tuple[float, ...],
    train: list[np.ndarray],
    n_train: int,
    test: np.ndarray,
    n_test: int,
    boundary: str,
    note: str,
) -> System:
    fields = [_fine_field(eq, f, spacing, n_train, boundary) for f in train]
    test_field = _fine_field(eq, test, spacing, n_test, boundary)
    return System(
        name,
        fields,
        test_field,
        n_test,
        field_ld(eq, spacing),
        _field_leapfrog(eq, boundary),
        boundary=boundary,
        range_note=note,
    )


def sine_gordon_1d(quick: bool) -> System:
    """Sine-Gordon 1+1D, periodic, 32 sites (dx = 0.5, dt = 0.1): trained at amplitudes 0.5 and 1 (40 slices),
    tested at 2 over 200."""
    nx, n = (24, 101) if quick else (32, 201)
    train = [a * _smooth((nx,), s) for a, s in ((0.5, 1), (1.0, 2))]
    return _field_system(
        "sine-Gordon 1+1D",
        SINE_GORDON,
        (nx,),
        (0.1, 0.5),
        train,
        40,
        2.0 * _smooth((nx,), 3),
        n,
        "periodic",
        "amplitude 1 -> 2",
    )


def phi4_1d(quick: bool) -> System:
    """Double-well phi^4 1+1D (``V = (psi^2 - 1)^2 / 4``), periodic, about the vacuum 1: trained at
    perturbations 0.2 and 0.4, tested at 0.8."""
    nx, n = (24, 101) if quick else (32, 201)
    train = [1 + a * _smooth((nx,), s) for a, s in ((0.2, 4), (0.4, 5))]
    return _field_system(
        "phi^4 1+1D",
        PHI4,
        (nx,),
        (0.1, 0.5),
        train,
        40,
        1 + 0.8 * _smooth((nx,), 6),
        n,
        "periodic",
        "perturbation 0.4 -> 0.8",
    )


def sine_gordon_2d(quick: bool) -> System:
    """Sine-Gordon 2+1D, periodic 12 x 12 (h = 0.5, dt = 0.1), trained on 30 slices at amplitude 0.4, tested on
    24 x 24 at amplitude 0.8 over 60 slices."""
    s, t, n = (8, 12, 30) if quick else (12, 24, 60)
    train = [0.4 * _smooth((s, s), 7)]
    return _field_system(
        "sine-Gordon 2+1D",
        SINE_GORDON,
        (s, s),
        (0.1, 0.5, 0.5),
        train,
        30,
        0.8 * _smooth((t, t), 8),
        n,
        "periodic",
        f"{s}^2 at 0.4 -> {t}^2 at 0.8",
    )


def phi4_2d(quick: bool) -> System:
    """Double-well phi^4 2+1D about the vacuum, periodic, trained at perturbation 0.3 on 12 x 12, tested at 0.6
    on 24 x 24."""
    s, t, n = (8, 12, 30) if quick else (12, 24, 60)
    train = [1 + 0.3 * _smooth((s, s), 9)]
    return _field_system(
        "phi^4 2+1D",
        PHI4,
        (s, s),
        (0.1, 0.5, 0.5),
        train,
        30,
        1 + 0.6 * _smooth((t, t), 10),
        n,
        "periodic",
        f"{s}^2 at 0.3 -> {t}^2 at 0.6",
    )


def nlkg_string(quick: bool) -> System:
    """``psi_tt = psi_xx - psi - 0.3 psi^3``, fixed ends, 41 sites (dx = 0.1, dt = 0.05): trained on four fields
    with ``|psi| <= 1.13`` (80 slices), tested on one of amplitude 5.5 over 400 slices."""
    nx = 41
    x = np.linspace(0.0, 4.0, nx)
    modes = [(1, 1.13), (2, 0.8), (1, 0.5), (3, 0.6)]
    train = [a * np.sin(k * np.pi * x / 4) for k, a in modes]
    test = 5.5 * np.sin(np.pi * x / 4)
    n = 100 if quick else 400
    return _field_system(
        "NLKG string", NLKG, (nx,), (0.05, 0.1), train, 80, test, n, "dirichlet", f"|psi| <= 1.13 -> 5.5, {n} slices"
    )


SYSTEMS: dict[str, Callable[[bool], System]] = {
    "oscillator-sin": oscillator_sin,
    "oscillator-wells": oscillator_wells,
    "kepler": kepler,
    "sine-gordon-1d": sine_gordon_1d,
    "phi4-1d": phi4_1d,
    "sine-gordon-2d": sine_gordon_2d,
    "phi4-2d": phi4_2d,
    "nlkg-string": nlkg_string,
    "charged-particle": charged_particle,
    "pendulum": pendulum,
    "double-pendulum": double_pendulum,
}


def _del_stepper(form: SymbolicLd) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """One step of the variational integrator of a closed-form ``L_d`` on the stencil ``(0,), (1,)``: the next
    slice from the last two, its DEL solved by Newton's method from the explicit guess (to round-off)."""
    m = form.m
    prev, cur, nxt = ([neighbour((k,), c) for c in range(m)] for k in (-1, 0, 1))
    eqs = del_equations(form)
    jac = sympy.Matrix(eqs).jacobian(nxt)
    f = sympy.lambdify([prev, cur, nxt], eqs, "numpy")
    j = sympy.lambdify([prev, cur, nxt], jac, "numpy")

    def step(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        x = 2 * b - a
        for _ in range(50):
            dx = np.linalg.solve(np.asarray(j(a, b, x), dtype=float), np.asarray(f(a, b, x), dtype=float))
            x = x - dx
            if np.max(np.abs(dx)) <= 1e-15 * (1.0 + np.max(np.abs(x))):
                break
        return x

    return step


def variational_served(form: SymbolicLd, ref: xr.DataArray, slices: int) -> np.ndarray:
    """The variational integrator of the closed-form ``L_d`` ``form`` (an ODE system's) from the first two slices
    of ``ref``: ``slices`` slices, shaped as ``ref``'s."""
    step = _del_stepper(form)
    first = np.asarray(ref.values, dtype=float).reshape(ref.sizes["t"], -1)
    q = np.empty((slices, first.shape[1]))
    q[:2] = first[:2]
    for k in range(1, slices - 1):
        q[k + 1] = step(q[k - 1], q[k])
    return q.reshape((slices, *ref.shape[1:]))


def variational_data(system: System) -> list[xr.DataArray]:
    """The training fields regenerated by the variational integrator of the true ``L_d`` at the data's own
    steps, from each field's first two slices (and boundary strips): data a first-order ``L_d`` of the library
    meets exactly. Fields: the explicit leapfrog (the DEL of :func:`field_ld`); ODE systems: the DEL of the
    trapezoid ``L_d`` solved step by step (it is the central-difference leapfrog only for a constant mass)."""
    out = []
    for f in system.train:
        nt = f.sizes["t"]
        values = system.leapfrog(f, nt) if system.ode is None else variational_served(system.true_ld, f, nt)
        out.append(f.copy(data=np.asarray(values, dtype=float).reshape(f.shape)))
    return out


def max_errors(pred: np.ndarray, ref: np.ndarray, slices: int, at: tuple[int, ...] = ()) -> list[float]:
    """Largest error over ``slices`` slices, then after each step count in ``at``; ``inf`` past a stop or a
    non-finite value."""
    pred = np.asarray(pred, dtype=float)[:slices]
    n = len(pred)
    err = np.abs(pred.reshape(n, -1) - ref[:n].reshape(n, -1)).max(axis=1) if n else np.zeros(0)
    good = len(err) if np.isfinite(err).all() else int(np.argmax(~np.isfinite(err)))
    err = np.concatenate([err[:good], np.full(slices - good, np.inf)])
    return [float(err.max())] + [float(err[: k + 1].max()) for k in at]


def chosen(parser: argparse.ArgumentParser, only: list[str]) -> tuple[str, ...]:
    """The system names of the ``--only`` arguments (each may hold several, comma-separated); an unknown one is
    the parser's error."""
    names = tuple(n for item in only for n in item.split(",") if n)
    unknown = [n for n in names if n not in SYSTEMS]
    if unknown:
        parser.error(f"unknown system {unknown[0]!r}; choose from {', '.join(SYSTEMS)}")
    return names


def build(name: str, quick: bool = False) -> System:
    """The system ``name`` (a key of :data:`SYSTEMS`)."""
    system = SYSTEMS[name](quick)
    system.key = name
    return system
