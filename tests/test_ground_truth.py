"""Known discrete Lagrangians serve known schemes exactly (docs/mathematics.md, section 9)."""

from __future__ import annotations

import numpy as np
import pytest

import latticedft as ldft
from latticedft import lagrangians
from latticedft.testing import assert_fields_close

from helpers import leapfrog_of, membrane_field, quartic, series, wave_field


@pytest.mark.parametrize("boundary", ["dirichlet", "periodic"])
def test_wave_serves_leapfrog_1p1d(boundary):
    field = wave_field()
    out = ldft.serve(lagrangians.wave(1.0), field, boundary=boundary)
    assert out.complete
    assert_fields_close(out.field, field.copy(data=leapfrog_of(field, boundary=boundary)), atol=1e-13)
    assert out.newton_iterations <= 2 * (field.sizes["t"] - 2)  # linear DEL: one Newton step per slice


@pytest.mark.parametrize("boundary", ["dirichlet", "periodic"])
def test_wave_serves_leapfrog_2p1d(boundary):
    field = membrane_field()
    out = ldft.serve(lagrangians.wave(1.0), field, boundary=boundary)
    assert_fields_close(out.field, field.copy(data=leapfrog_of(field, boundary=boundary)), atol=1e-13)


def test_wave_with_other_speed_and_mixed_boundaries():
    field = membrane_field(n=10, nt=12)
    c = 0.7
    out = ldft.serve(lagrangians.wave(c), field, boundary={"x": "periodic", "y": "dirichlet"})
    # reference: leapfrog periodic in x, Dirichlet in y, written out by hand
    v = field.values.copy()
    dt = float(field.t[1] - field.t[0])
    dy, dx = float(field.y[1] - field.y[0]), float(field.x[1] - field.x[0])
    p = np.full_like(v, np.nan)
    p[:2] = v[:2]
    p[:, 0], p[:, -1] = v[:, 0], v[:, -1]
    for i in range(1, v.shape[0] - 1):
        u = p[i]
        lap = (np.roll(u, -1, 1) - 2 * u + np.roll(u, 1, 1)) / dx**2
        lap[1:-1] += (u[2:] - 2 * u[1:-1] + u[:-2]) / dy**2
        p[i + 1, 1:-1] = (2 * u - p[i - 1] + c**2 * dt**2 * lap)[1:-1]
    assert_fields_close(out.field, field.copy(data=p), atol=1e-13)


def test_verlet_serves_stormer_verlet():
    dt = 0.07
    osc = lagrangians.verlet(quartic)
    out = ldft.serve(osc, series([1.0, 0.99], dt), slices=300)
    q = np.zeros(300)
    q[:2] = 1.0, 0.99
    for i in range(1, 299):
        q[i + 1] = 2 * q[i] - q[i - 1] - dt**2 * (q[i] + q[i] ** 3)
    assert_fields_close(out.field, series(q, dt), atol=1e-12)


def test_kepler_verlet_vector_field():
    dt = 0.05
    init = series([[1.0, 0.0], [1.0 - 0.5 * dt**2, dt]], dt, components=["x", "y"])
    out = ldft.serve(lagrangians.kepler(), init, slices=400)
    q = np.zeros((400, 2))
    q[:2] = init.values
    for i in range(1, 399):
        r = np.linalg.norm(q[i])
        q[i + 1] = 2 * q[i] - q[i - 1] - dt**2 * q[i] / r**3
    assert out.field.dims == ("t", "component")
    assert list(out.field.component.values) == ["x", "y"]
    assert_fields_close(out.field, series(q, dt, components=["x", "y"]), atol=1e-11)


def test_served_field_keeps_layout_and_coordinates():
    field = wave_field(nt=10)
    out = ldft.serve(lagrangians.wave(1.0), field, slices=8)
    assert_fields_close(out.field, field.isel(t=slice(0, 8)), atol=1e-2)  # coords identical, values near the truth
    assert out.field.name == "psi"
