"""Tests of latticedft.systems: the reference fields obey their equations and the layout."""

from __future__ import annotations

import math

import numpy as np
import pytest
import xarray as xr

from latticedft import InputError
from latticedft import systems as S

AXES = {"t": "T", "x": "X", "y": "Y"}


def assert_layout(
    da: xr.DataArray, dims: tuple[str, ...], components: list[str] | None = None, name: str = "psi"
) -> None:
    """The field-file layout of docs/design.md."""
    assert isinstance(da, xr.DataArray)
    assert da.name == name
    full = dims + (("component",) if components is not None else ())
    assert da.dims == full
    assert da.dtype == np.float64
    assert da.values.flags["C_CONTIGUOUS"]
    assert np.all(np.isfinite(da.values))
    for d in dims:
        c = da[d]
        assert c.dtype == np.float64
        v = c.values
        if v.size >= 2:
            h = np.diff(v)
            assert h[0] > 0
            np.testing.assert_allclose(h, h[0], rtol=1e-12, atol=1e-14 * np.abs(v).max())
        for key in ("units", "long_name", "axis"):
            assert key in c.attrs, (d, key)
        assert c.attrs["axis"] == AXES[d]
    if components is not None:
        assert da["component"].values.tolist() == components
    for key in ("long_name", "units", "source"):
        assert isinstance(da.attrs.get(key), str) and da.attrs[key], key
    assert da.attrs["source"].startswith("latticedft.systems.")


def second_difference(a: np.ndarray, h: float, axis: int) -> np.ndarray:
    """Centred second difference along `axis`, interior points only (other axes untouched)."""
    n = a.shape[axis]
    sl = lambda s: tuple(s if k == axis else slice(None) for k in range(a.ndim))  # noqa: E731
    return (a[sl(slice(2, n))] - 2 * a[sl(slice(1, n - 1))] + a[sl(slice(0, n - 2))]) / h**2


def interior(a: np.ndarray) -> np.ndarray:
    return a[(slice(1, -1),) * a.ndim]


# ---------------------------------------------------------------------------- make_field


def test_make_field_layout_and_coords():
    f = S.make_field(
        np.arange(12.0).reshape(3, 4),
        ("t", "x"),
        spacing=(0.5, 0.25),
        origin=(1.0, -1.0),
        attrs={"units": "m", "source": "latticedft.systems.make_field test"},
    )
    assert_layout(f, ("t", "x"))
    assert f["t"].values.tolist() == [1.0, 1.5, 2.0]
    assert f["x"].values.tolist() == [-1.0, -0.75, -0.5, -0.25]
    g = S.make_field(
        np.zeros((2, 3, 2), dtype=np.float32),
        ("t", "x"),
        coords={"x": [0, 2, 4]},
        spacing=1.0,
        components=["a", "b"],
        coord_attrs={"x": {"units": "km"}},
    )
    assert g.dtype == np.float64 and g.dims == ("t", "x", "component")
    assert g["x"].attrs["units"] == "km" and g["x"].attrs["axis"] == "X"


@pytest.mark.parametrize(
    "kwargs, arg",
    [
        (dict(values=np.zeros((3, 4)), dims=("t",), spacing=1.0), "values"),
        (dict(values=np.zeros((3, 4)), dims=("t", "x")), "spacing"),
        (dict(values=np.zeros((3, 4)), dims=("t", "x"), spacing=(1.0, -1.0)), "spacing"),
        (dict(values=np.zeros((3, 4)), dims=("t", "x"), spacing=1.0, coords={"x": [0, 1, 3, 4]}), "coordinate 'x'"),
        (dict(values=np.zeros((3, 2)), dims=("t", "component"), spacing=1.0), "dims"),
        (dict(values=np.full((3,), np.nan), dims=("t",), spacing=1.0), "values"),
        (dict(values=np.zeros((3, 2)), dims=("t",), spacing=1.0, components=["x"]), "components"),
    ],
)
def test_make_field_rejects(kwargs, arg):
    with pytest.raises(InputError, match=arg):
        S.make_field(**kwargs)


# ---------------------------------------------------------------------------- oscillators


@pytest.mark.parametrize("psi0", [1.2, -0.6, 0.1])
def test_oscillator_sin_conserves_energy(psi0):
    psi, dpsi = S.oscillator_sin(psi0, return_velocity=True)
    assert_layout(psi, ("t",))
    assert_layout(dpsi, ("t",), name="dpsi")
    assert psi.shape == (51,) and psi["t"].values[-1] == 50.0
    assert psi.values[0] == psi0 and dpsi.values[0] == 0.0
    e = S.oscillator_sin_energy(psi.values, dpsi.values)
    assert np.max(np.abs(e - e[0])) <= 1e-9 * e[0]
    assert np.max(np.abs(psi.values)) <= abs(psi0) * (1 + 1e-9)  # turning points at +-|psi0|


def test_oscillator_sin_obeys_ode():
    # fine sampling: the second difference of the samples satisfies the ODE to O(dt^2)
    dt = 1e-3
    psi, dpsi = S.oscillator_sin(1.2, n=2001, dt=dt, return_velocity=True)
    p, v = psi.values, dpsi.values
    acc = second_difference(p, dt, 0)
    res = 2 * (np.sin(p[1:-1]) + 1) * acc + v[1:-1] ** 2 * np.cos(p[1:-1]) + np.pi**2 / 200 * p[1:-1]
    assert np.max(np.abs(res)) < 1e-7
    np.testing.assert_allclose(np.gradient(p, dt)[1:-1], v[1:-1], atol=1e-7)


def test_oscillator_sin_rejects_singular_energy():
    with pytest.raises(InputError, match="psi0"):
        S.oscillator_sin(1.7)
    with pytest.raises(InputError, match="n"):
        S.oscillator_sin(0.5, n=1)
    with pytest.raises(InputError, match="dt"):
        S.oscillator_sin(0.5, dt=0.0)


@pytest.mark.parametrize("psi0", [1.7, 0.8, -0.7])
def test_oscillator_wells_conserves_energy(psi0):
    psi, dpsi = S.oscillator_wells(psi0, return_velocity=True)
    assert_layout(psi, ("t",))
    e = S.oscillator_wells_energy(psi.values, dpsi.values)
    assert np.max(np.abs(e - e[0])) <= 1e-9 * abs(e[0])


def test_wells_sign_relation_is_newton():
    # psi'' - 0.03[sin(1 - psi^2) psi + 0.1] = 0 is exactly psi'' = -V'(psi)
    q = np.linspace(-2.0, 2.0, 401)
    h = 1e-5
    dV = (S.wells_potential(q + h) - S.wells_potential(q - h)) / (2 * h)
    rhs = 0.03 * (np.sin(1 - q**2) * q + 0.1)
    np.testing.assert_allclose(-dV, rhs, atol=1e-10)
    # and the energy check of the ODE solution would fail for the opposite sign
    assert not np.allclose(dV, rhs, atol=1e-3)


def test_oscillator_wells_paper_wells():
    big = S.oscillator_wells(1.7, n=401, dt=0.5)
    assert big.min() < -1.3 and big.max() == 1.7  # the large well
    right = S.oscillator_wells(0.8, n=401, dt=0.5)
    assert right.min() > -0.1 and right.max() < 1.5
    left = S.oscillator_wells(-0.7, n=401, dt=0.5)
    assert left.min() > -1.3 and left.max() < -0.1


def test_xarray_energy_input():
    psi, dpsi = S.oscillator_wells(1.7, return_velocity=True)
    e = S.oscillator_wells_energy(psi, dpsi)
    assert isinstance(e, xr.DataArray) and e.dims == ("t",)


# ---------------------------------------------------------------------------- Kepler


def test_gm_is_one_in_paper_units():
    gm = 4 * math.pi**2 * (S.KEPLER_TIME_UNIT_DAYS / 365.256363) ** 2
    assert abs(gm - 1.0) < 5e-4 and gm == S.GM_SUN_KEPLER_UNITS
    assert abs(float(S.kepler_period(1.0)) * S.KEPLER_TIME_UNIT_DAYS - 365.25) < 0.2


def test_planets_and_aphelion():
    assert list(S.PLANETS) == ["Mercury", "Venus", "Earth", "Mars", "Ceres", "Jupiter"]
    r, v = S.planet_aphelion("Earth")
    assert abs(r - 1.0167) < 1e-4 and abs(v - 0.98) < 5e-3
    r, v = S.planet_aphelion("Mercury")
    assert abs(r - 0.4667) < 1e-4 and abs(v - 1.30) < 6e-3
    for name, p in S.PLANETS.items():
        r, v = S.planet_aphelion(name)
        # vis-viva at aphelion
        assert abs(v * v - (2 / r - 1 / p.a)) < 1e-13
        assert 0 <= p.e < 0.21 and 0.3 < p.a < 5.3


@pytest.mark.parametrize("name", list(S.PLANETS))
def test_planet_orbit_conservation(name):
    p = S.PLANETS[name]
    r0, v0 = S.planet_aphelion(name)
    orbit = S.planet_orbit(name)
    assert_layout(orbit, ("t",), components=["x", "y"])
    assert orbit.attrs["planet"] == name and orbit["t"].attrs["units"] == "58.14 days"
    n = orbit.sizes["t"]
    assert n == round(2 * math.pi * p.a**1.5 / 0.05) + 1
    pos, vel = S.kepler_orbit(r0, v0, n=n, return_velocity=True)
    xr.testing.assert_identical(pos.drop_attrs(), orbit.drop_attrs())
    e = S.kepler_energy(pos, vel)
    ang = S.kepler_angular_momentum(pos, vel)
    assert isinstance(e, xr.DataArray) and e.dims == ("t",)
    np.testing.assert_allclose(e, -0.5 / p.a, rtol=1e-10)
    np.testing.assert_allclose(ang, r0 * v0, rtol=1e-10)
    rad = np.hypot(pos.values[:, 0], pos.values[:, 1])
    assert rad.max() <= p.a * (1 + p.e) * (1 + 1e-10)
    assert rad.min() >= p.a * (1 - p.e) * (1 - 1e-6) and rad.min() < p.a * (1 - p.e) + 0.01


@pytest.mark.parametrize("r0, v0", [(1.0, 1.0), (1.0167, 1.13), (0.4667, 1.80)])
def test_kepler_period_closes_orbit(r0, v0):
    a = -0.5 / (0.5 * v0**2 - 1 / r0)
    period = float(S.kepler_period(a))
    assert abs(period - 2 * np.pi * a**1.5) < 1e-12
    orbit = S.kepler_orbit(r0, v0, dt=period / 400, n=401)
    np.testing.assert_allclose(orbit.values[-1], [r0, 0.0], atol=1e-9)
    # halfway: perihelion/aphelion on the negative x axis at r = a(1 -+ e)
    assert abs(-orbit.values[200, 0] - (2 * a - r0)) < 1e-9
    # the default length of a bound orbit is one period
    assert S.kepler_orbit(r0, v0, dt=0.05).sizes["t"] == round(period / 0.05) + 1


def test_kepler_escape_and_truncation():
    r0 = 1.0167
    vp = float(S.escape_speed(r0))
    assert abs(vp - math.sqrt(2 / r0)) < 1e-15
    pos, vel = S.kepler_orbit(r0, 1.40, dt=0.05, t_end=200.0, r_max=4.0, return_velocity=True)
    rad = np.hypot(pos.values[:, 0], pos.values[:, 1])
    assert rad.max() <= 4.0 and rad.max() > 4.0 - 0.05 * 1.4  # stopped at the first crossing
    assert pos.sizes["t"] < 4001
    assert float(S.kepler_energy(pos, vel)[0]) == pytest.approx(0.5 * 1.4**2 - 1 / r0, rel=1e-14)
    full = S.kepler_orbit(r0, 1.40, dt=0.05, t_end=200.0)
    assert full.sizes["t"] == 4001
    np.testing.assert_allclose(full.values[: pos.sizes["t"]], pos.values, rtol=0, atol=1e-9)
    assert S.kepler_orbit(r0, 1.0, dt=0.05, n=7).sizes["t"] == 7


@pytest.mark.parametrize(
    "kwargs, arg",
    [
        (dict(r0=1.0, v0=1.5), "n"),  # unbound and no length
        (dict(r0=1.0, v0=1.0, n=5, t_end=1.0), "n, t_end"),
        (dict(r0=-1.0, v0=1.0), "r0"),
        (dict(r0=1.0, v0=1.0, r_max=0.5), "r_max"),
        (dict(r0=1.0, v0=1.0, dt=-0.1), "dt"),
    ],
)
def test_kepler_rejects(kwargs, arg):
    with pytest.raises(InputError, match=arg):
        S.kepler_orbit(**kwargs)


def test_planet_orbit_names():
    assert S.planet_orbit("jupiter", periods=0.1).attrs["planet"] == "Jupiter"
    with pytest.raises(InputError, match="name"):
        S.planet_orbit("Pluto")
    with pytest.raises(InputError, match="periods"):
        S.planet_orbit("Earth", periods=0)


# ---------------------------------------------------------------------------- wave equation, exact

MODES = [(1, 1.0), (2, 0.3, 0.7), (5, -0.05, 2.0)]


def wave_residual(h: float) -> float:
    c, length = 1.3, 2.0
    nx = int(round(length / h)) + 1
    f = S.wave_string(MODES, c=c, length=length, nx=nx, nt=41, dt=h / 2, t0=0.3)
    u = f.values
    res = second_difference(u, h / 2, 0)[:, 1:-1] - c**2 * second_difference(u, h, 1)[1:-1]
    return float(np.max(np.abs(res)))


def test_wave_string_satisfies_pde_and_fixed_ends():
    f = S.wave_string(MODES, c=1.3, length=2.0, nx=41, nt=11)
    assert_layout(f, ("t", "x"))
    assert f["x"].values[-1] == pytest.approx(2.0, abs=1e-14)
    assert np.all(f.values[:, 0] == 0.0) and np.all(f.values[:, -1] == 0.0)
    # exact solution: the finite-difference residual is O(h^2) and drops 4x per halving
    r1, r2 = wave_residual(0.02), wave_residual(0.01)
    assert r2 < 0.02 and 3.5 < r1 / r2 < 4.5
    # t = 0 value
    x = f["x"].values
    u0 = (
        np.sin(np.pi * x / 2)
        + 0.3 * np.sin(2 * np.pi * x / 2) * np.cos(0.7)
        - 0.05 * np.sin(5 * np.pi * x / 2) * np.cos(2.0)
    )
    np.testing.assert_allclose(f.values[0], u0, atol=1e-14)


def test_wave_membrane_satisfies_pde():
    def residual(h):
        lx, ly = 1.0, 0.5
        f = S.wave_membrane(
            [(1, 1, 1.0), (2, 3, 0.2, 0.4)],
            c=0.8,
            length_x=lx,
            length_y=ly,
            nx=int(round(lx / h)) + 1,
            ny=int(round(ly / h)) + 1,
            nt=9,
            dt=h / 2,
        )
        u = f.values
        lap = second_difference(u, h, 1)[:, :, 1:-1] + second_difference(u, h, 2)[:, 1:-1, :]
        utt = second_difference(u, h / 2, 0)[:, 1:-1, 1:-1]
        return f, float(np.max(np.abs(utt - 0.64 * lap[1:-1])) / np.max(np.abs(utt)))

    f, r1 = residual(0.02)
    _, r2 = residual(0.01)
    assert_layout(f, ("t", "y", "x"))
    assert 3.5 < r1 / r2 < 4.5 and r2 < 5e-3  # relative to max |psi_tt|
    u = f.values
    assert not np.any(u[:, 0]) and not np.any(u[:, -1]) and not np.any(u[:, :, 0]) and not np.any(u[:, :, -1])


@pytest.mark.parametrize("modes", [[], [(0, 1.0)], [(1.5, 1.0)], [(1,)], "abc"])
def test_wave_string_rejects_modes(modes):
    with pytest.raises(InputError, match="modes"):
        S.wave_string(modes)


# ---------------------------------------------------------------------------- leapfrog


def test_leapfrog_courant_one_is_exact_1d():
    # c dt = dx: leapfrog reproduces the continuous solution on the lattice
    c, length, nx = 1.0, 1.0, 51
    dx = length / (nx - 1)
    exact = S.wave_string(MODES, c=c, length=length, nx=nx, nt=301, dt=dx / c)
    u = S.leapfrog(exact.values[0], exact.values[1], 300, dx / c, dx, c=c)
    assert isinstance(u, np.ndarray) and u.shape == exact.shape
    np.testing.assert_allclose(u, exact.values, rtol=0, atol=1e-11)


def test_leapfrog_dirichlet_boundary_values_and_dataarray():
    # a travelling wave through a window with time-dependent Dirichlet data, Courant 1
    nx, dx = 41, 0.025
    x = dx * np.arange(nx)
    t = dx * np.arange(121)
    exact = np.sin(2 * np.pi * (x[None] - t[:, None])) + 0.5 * np.cos(3 * (x[None] + t[:, None]))
    f = S.make_field(
        exact, ("t", "x"), spacing=dx, attrs={"units": "1", "source": "latticedft.systems.make_field test"}
    )
    u = S.leapfrog(f.isel(t=0), f.isel(t=1), 120, dx, boundary_values=f)
    assert isinstance(u, xr.DataArray)
    assert_layout(u, ("t", "x"))
    np.testing.assert_allclose(u.values, exact, atol=1e-11)
    np.testing.assert_array_equal(u["x"].values, f["x"].values)
    # a scalar t coordinate on psi0 sets the first time
    v = S.leapfrog(f.isel(t=2), f.isel(t=3), 4, dx)
    np.testing.assert_allclose(v["t"].values, f["t"].values[2:7], atol=1e-15)
    # without boundary_values the outer layer stays at psi1's values
    w = S.leapfrog(exact[0], exact[1], 10, dx, dx)
    assert np.all(w[2:, 0] == exact[1, 0]) and np.all(w[2:, -1] == exact[1, -1])


def test_leapfrog_periodic_wraps():
    # Courant 1 on a periodic ring: a right-moving wave is shifted one site per step
    nx = 32
    dx = 1.0 / nx
    x = dx * np.arange(nx)
    g = lambda s: np.exp(np.sin(2 * np.pi * s)) + 0.3 * np.cos(6 * np.pi * s)  # noqa: E731
    u = S.leapfrog(g(x), g(x - dx), 2 * nx, dx, dx, boundary="periodic")
    for i in (1, 5, nx - 1, nx, 2 * nx):
        np.testing.assert_allclose(u[i], np.roll(g(x), i), atol=1e-11)
    # the same without wrap-around would differ at the edges
    d = S.leapfrog(g(x), g(x - dx), 5, dx, dx, boundary="dirichlet")
    assert np.max(np.abs(d[5] - u[5])) > 1e-3


def test_leapfrog_2d_converges_to_membrane():
    errs = []
    for n in (17, 33):
        h = 1.0 / (n - 1)
        dt = 0.4 * h
        nt = int(round(0.5 / dt)) + 1
        exact = S.wave_membrane([(1, 1, 1.0), (2, 1, 0.3)], nx=n, ny=n, nt=nt, dt=dt)
        u = S.leapfrog(exact.isel(t=0), exact.isel(t=1), nt - 1, dt)
        assert u.dims == ("t", "y", "x")
        errs.append(float(np.max(np.abs(u.values - exact.values))))
    # psi1 from the exact solution: the global error is O(h^2)
    assert errs[1] < 2e-3 and 3.0 < errs[0] / errs[1] < 5.0


def test_leapfrog_periodic_2d_and_force():
    rng = np.random.default_rng(3)
    u0 = rng.standard_normal((6, 8))
    u1 = u0 + 0.01 * rng.standard_normal((6, 8))
    dt, h = 0.1, (0.5, 0.4)
    u = S.leapfrog(u0, u1, 5, dt, h, c=0.7, force=np.sin, boundary="periodic")
    lap = sum(
        (np.roll(u[1:-1], -1, ax) - 2 * u[1:-1] + np.roll(u[1:-1], 1, ax)) / hk**2 for ax, hk in ((1, h[0]), (2, h[1]))
    )
    res = (u[2:] - 2 * u[1:-1] + u[:-2]) / dt**2 - 0.49 * lap - np.sin(u[1:-1])
    assert np.max(np.abs(res)) < 1e-11


def test_leapfrog_sine_gordon_force_follows_breather():
    b = S.sine_gordon_breather(0.6, velocity=0.3, xlim=(-25.0, 25.0), nx=1001, nt=201, dt=0.025)
    u = S.leapfrog(b.isel(t=0), b.isel(t=1), 200, 0.025, force=lambda p: -np.sin(p), boundary_values=b)
    assert np.max(np.abs(u.values - b.values)) < 2e-3


@pytest.mark.parametrize(
    "kwargs, arg",
    [
        (dict(psi0=np.zeros(5), psi1=np.zeros(6), steps=3, dt=0.1, spacing=0.1), "psi1"),
        (dict(psi0=np.zeros(5), psi1=np.zeros(5), steps=3, dt=0.1), "spacing"),
        (dict(psi0=np.zeros(5), psi1=np.zeros(5), steps=0, dt=0.1, spacing=0.1), "steps"),
        (dict(psi0=np.zeros(5), psi1=np.zeros(5), steps=3, dt=0.1, spacing=0.1, boundary="open"), "boundary"),
        (dict(psi0=np.zeros((2, 2, 2)), psi1=np.zeros((2, 2, 2)), steps=3, dt=0.1, spacing=0.1), "psi0"),
        (
            dict(psi0=np.zeros(5), psi1=np.zeros(5), steps=3, dt=0.1, spacing=0.1, boundary_values=np.zeros((3, 5))),
            "boundary_values",
        ),
        (dict(psi0=np.zeros(5), psi1=np.zeros(5), steps=3, dt=0.1, spacing=0.1, force=lambda u: u[:2]), "force"),
    ],
)
def test_leapfrog_rejects(kwargs, arg):
    with pytest.raises(InputError, match=arg):
        S.leapfrog(**kwargs)


# ---------------------------------------------------------------------------- Klein-Gordon


def kg_scheme_residual(f: xr.DataArray, dt: float = 0.025, dx: float = 0.05) -> float:
    u = f.values
    lhs = (u[2:] - 2 * u[1:-1] + u[:-2]) / dt**2
    uc = u[1:-1]
    rhs = (np.roll(uc, -1, axis=1) - 2 * uc + np.roll(uc, 1, axis=1)) / dx**2 - uc
    return float(np.max(np.abs(lhs - rhs)) / max(np.max(np.abs(lhs)), 1.0))


def test_klein_gordon_test_field_obeys_scheme():
    f = S.klein_gordon_test_field(steps=200)
    assert_layout(f, ("t", "x"))
    assert f.shape == (201, 20)
    assert f["x"].attrs["periodic"] == "true" and f["x"].attrs["period"] == pytest.approx(1.0)
    np.testing.assert_allclose(f["x"].values, 0.05 * np.arange(20))
    np.testing.assert_allclose(f.values[0], np.sin(4 * np.pi * f["x"].values), atol=1e-15)
    np.testing.assert_array_equal(f.values[0], f.values[1])
    assert kg_scheme_residual(f) < 1e-12


def test_klein_gordon_training_set():
    data = S.klein_gordon_training_set()
    assert len(data) == 80
    for f in data:
        assert f.shape == (21, 20)
        assert kg_scheme_residual(f) < 1e-12
    assert_layout(data[0], ("t", "x"))
    again = S.klein_gordon_training_set(n=2, steps=20, seed=0)
    np.testing.assert_array_equal(again[0].values, data[0].values)
    other = S.klein_gordon_training_set(n=2, steps=20, seed=1)
    assert not np.allclose(other[0].values, data[0].values)
    # smooth: only wavenumbers 0 and 1 carry visible amplitude (exp(-2 k^4) decay)
    spec = np.abs(np.fft.rfft(np.stack([f.values[0] for f in data]), axis=1)) / 20
    assert np.max(spec[:, 2:]) < 1e-12 and np.max(spec[:, 1]) > 0.05
    # u1 from a second-order Taylor step: the slices differ by O(dt)
    assert max(float(np.max(np.abs(f.values[1] - f.values[0]))) for f in data) < 0.2


def test_klein_gordon_rejects():
    with pytest.raises(InputError, match="u0"):
        S.klein_gordon(np.zeros((2, 3)), np.zeros((2, 3)), 3)
    with pytest.raises(InputError, match="u1"):
        S.klein_gordon(np.zeros(5), np.zeros(4), 3)
    with pytest.raises(InputError, match="seed"):
        S.klein_gordon_training_set(n=1, seed=1.5)


# ---------------------------------------------------------------------------- sine-Gordon


def sg_residual(f: xr.DataArray) -> float:
    u = f.values
    dt = float(f["t"][1] - f["t"][0])
    dx = float(f["x"][1] - f["x"][0])
    res = second_difference(u, dt, 0)[:, 1:-1] - second_difference(u, dx, 1)[1:-1] + np.sin(u[1:-1, 1:-1])
    return float(np.max(np.abs(res)))


@pytest.mark.parametrize("omega, v", [(0.5, 0.0), (0.8, 0.4), (0.3, -0.6)])
def test_breather_satisfies_sine_gordon(omega, v):
    def make(h):
        return S.sine_gordon_breather(
            omega, velocity=v, x0=1.0, phase=0.3, xlim=(-10.0, 10.0), nx=int(round(20 / h)) + 1, nt=21, dt=h, t0=0.5
        )

    f1, f2 = make(0.02), make(0.01)
    assert_layout(f1, ("t", "x"))
    r1, r2 = sg_residual(f1), sg_residual(f2)
    assert r2 < 5e-3 and 3.5 < r1 / r2 < 4.5


def test_kink_antikink_satisfies_sine_gordon():
    def make(h):
        return S.kink_antikink(
            0.5, xlim=(-10.0, 10.0), nx=int(round(20 / h)) + 1, nt=int(round(4 / h)) + 1, dt=h, t0=-2.0
        )

    f1, f2 = make(0.04), make(0.02)
    assert_layout(f1, ("t", "x"))
    r1, r2 = sg_residual(f1), sg_residual(f2)
    assert r2 < 5e-3 and 3.5 < r1 / r2 < 4.5
    # -2 pi between the kinks before the collision, +2 pi after, 0 at the edges
    kk = S.kink_antikink(0.5, xlim=(-60.0, 60.0), t0=-20.0, dt=40.0, nt=2)
    assert kk.sel(x=0.0).values.tolist() == pytest.approx([-2 * np.pi, 2 * np.pi], abs=1e-4)
    assert np.max(np.abs(kk.values[:, [0, -1]])) < 1e-6


def test_sine_gordon_energy():
    omega, v = 0.6, 0.5
    gamma = 1 / math.sqrt(1 - v * v)
    b = S.sine_gordon_breather(omega, velocity=v, xlim=(-30.0, 30.0), nx=2401, nt=41, dt=0.02)
    e = S.sine_gordon_energy(b)
    assert e.dims == ("t",) and e.sizes["t"] == 41
    np.testing.assert_allclose(e.values[1:-1], 16 * gamma * math.sqrt(1 - omega**2), rtol=2e-3)
    kk = S.kink_antikink(0.5, xlim=(-30.0, 30.0), nx=2401, nt=41, dt=0.02, t0=-0.4)
    ek = S.sine_gordon_energy(kk)
    np.testing.assert_allclose(ek.values[1:-1], 16 / math.sqrt(0.75), rtol=2e-3)
    # a periodic field: the energy of a spatially constant field at rest is the on-site term only
    f = S.make_field(np.full((3, 10), 0.5), ("t", "x"), spacing=0.1, coord_attrs={"x": {"periodic": "true"}})
    np.testing.assert_allclose(S.sine_gordon_energy(f).values, (1 - math.cos(0.5)) * 1.0, rtol=1e-14)
    with pytest.raises(InputError, match="psi"):
        S.sine_gordon_energy(np.zeros((3, 3)))  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "call, arg",
    [
        (lambda: S.sine_gordon_breather(1.2), "omega"),
        (lambda: S.sine_gordon_breather(0.5, velocity=1.0), "velocity"),
        (lambda: S.kink_antikink(0.0), "velocity"),
        (lambda: S.kink_antikink(0.5, xlim=(1.0, -1.0)), "xlim"),
        (lambda: S.kink_antikink(0.5, nx=2), "nx"),
    ],
)
def test_sine_gordon_rejects(call, arg):
    with pytest.raises(InputError, match=arg):
        call()


def test_field_energy_string_membrane_and_klein_gordon():
    # standing mode of a string: E = (k pi / L)^2 A^2 L / 4 (c = 1)
    s = S.wave_string([(2, 0.5, 0.3)], nx=801, nt=9)
    e = S.wave_energy(s)
    assert e.dims == ("t",) and e.sizes["t"] == 9
    np.testing.assert_array_equal(e["t"].values, s["t"].values)
    np.testing.assert_allclose(e.values, (2 * np.pi) ** 2 * 0.25 / 4, rtol=1e-4)
    # membrane mode (k, l) on the unit square: E = omega^2 A^2 / 8
    m = S.wave_membrane([(1, 2, 0.3)], nx=201, ny=201, nt=5)
    np.testing.assert_allclose(S.wave_energy(m).values, np.pi**2 * 5 * 0.09 / 8, rtol=1e-3)
    # the explicit scheme conserves the discrete energy exactly: periodic Klein-Gordon, fixed-frame membrane
    ek = S.klein_gordon_energy(S.klein_gordon_test_field(steps=400)).values
    assert np.ptp(ek) < 1e-12 * ek[0]
    m0 = S.wave_membrane([(1, 1, 1.0), (3, 2, 0.2)], nx=21, ny=21, nt=2)
    lf = S.leapfrog(m0.isel(t=0, drop=True), m0.isel(t=1, drop=True), steps=300, dt=float(m0.t[1]))
    ew = S.wave_energy(lf).values
    assert np.ptp(ew) < 1e-12 * ew[0]
    with pytest.raises(InputError, match="psi"):
        S.field_energy(np.zeros((3, 3)))  # type: ignore[arg-type]
