"""``latticedft.del_residual`` against the DEL equations written out by hand.

``EL_y = prod(h) * sum_a d_a L_d(cell y - s_a)`` on every interior site ``y``
(docs/mathematics.md, section 2). For the first-order stencil and the known
Lagrangians below, the sum is short enough to write out with numpy, site by
site, on a random field (no solution of anything: the residual of any field).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import latticedft as ldft
from latticedft import lagrangians, systems


def _residual(model, da):
    f = ldft.as_lattice_field(da)
    model.bind(f.ndim, f.ncomp, f.spacing, f.components)
    return ldft.del_residual(model, f).numpy()


def test_wave_1p1d_dirichlet_residual_by_hand():
    """Wave L_d, c = 0.7: EL_ij = dt dx [-2 (psi_{i+1,j} - 2 psi_ij + psi_{i-1,j}) / dt^2
    + 2 c^2 (psi_{i,j+1} - 2 psi_ij + psi_{i,j-1}) / dx^2] on sites 1..N-2 of both axes."""
    rng = np.random.default_rng(1)
    nt, nx, dt, dx, c = 7, 9, 0.05, 0.1, 0.7
    psi = rng.standard_normal((nt, nx))
    el = _residual(lagrangians.wave(c), systems.make_field(psi, ("t", "x"), spacing=(dt, dx)))
    assert el.shape == (nt - 2, nx - 2, 1)
    hand = np.zeros((nt - 2, nx - 2))
    for i in range(1, nt - 1):
        for j in range(1, nx - 1):
            d2t = (psi[i + 1, j] - 2 * psi[i, j] + psi[i - 1, j]) / dt**2
            d2x = (psi[i, j + 1] - 2 * psi[i, j] + psi[i, j - 1]) / dx**2
            hand[i - 1, j - 1] = dt * dx * (-2 * d2t + 2 * c**2 * d2x)
    np.testing.assert_allclose(el[..., 0], hand, rtol=1e-12, atol=1e-12 * np.abs(hand).max())


def test_wave_1p1d_periodic_residual_by_hand():
    """Periodic in x: every x site is interior and the x neighbours wrap around."""
    rng = np.random.default_rng(2)
    nt, nx, dt, dx = 6, 8, 0.05, 0.1
    psi = rng.standard_normal((nt, nx))
    da = systems.make_field(psi, ("t", "x"), spacing=(dt, dx))
    f = ldft.as_lattice_field(da, boundary="periodic")
    model = lagrangians.wave(1.0)
    model.bind(2, 1, f.spacing)
    el = ldft.del_residual(model, f).numpy()
    assert el.shape == (nt - 2, nx, 1)
    hand = np.zeros((nt - 2, nx))
    for i in range(1, nt - 1):
        for j in range(nx):
            d2t = (psi[i + 1, j] - 2 * psi[i, j] + psi[i - 1, j]) / dt**2
            d2x = (psi[i, (j + 1) % nx] - 2 * psi[i, j] + psi[i, (j - 1) % nx]) / dx**2
            hand[i - 1, j] = dt * dx * (-2 * d2t + 2 * d2x)
    np.testing.assert_allclose(el[..., 0], hand, rtol=1e-12, atol=1e-12 * np.abs(hand).max())


@pytest.mark.parametrize("mass", [1.0, 2.5])
def test_kepler_vector_residual_by_hand(mass):
    """Störmer–Verlet L_d of the Kepler problem, m = 2 components:
    EL_i = -h [mass (q_{i+1} - 2 q_i + q_{i-1}) / h^2 + q_i / |q_i|^3] on sites 1..N-2."""
    rng = np.random.default_rng(3)
    n, h = 10, 0.05
    q = rng.uniform(0.5, 1.5, size=(n, 2))
    model = lagrangians.verlet(lambda x: -1.0 / torch.sqrt((x * x).sum(-1)), mass=mass)
    el = _residual(model, systems.make_field(q, ("t",), spacing=h, components=["x", "y"]))
    assert el.shape == (n - 2, 2)
    hand = np.zeros((n - 2, 2))
    for i in range(1, n - 1):
        accel = (q[i + 1] - 2 * q[i] + q[i - 1]) / h**2
        hand[i - 1] = -h * (mass * accel + q[i] / np.linalg.norm(q[i]) ** 3)
    np.testing.assert_allclose(el, hand, rtol=1e-12, atol=1e-12 * np.abs(hand).max())
