"""The field exact-step corrections benchmark: its measure of the unheld truncation and its exact-step
coefficients (the benchmark itself runs for minutes: docs/discovery.md).

No timing is asserted.
"""

from __future__ import annotations

import numpy as np
import pytest
import sympy

from benchmarks import field_corrections as fc
from latticedft import systems


@pytest.mark.parametrize("periodic", [True, False])
def test_unheld_share_of_a_linear_mode_is_its_dispersion_ratio(periodic: bool):
    # one mode of the lattice Klein-Gordon equation: Lap^2 psi = lam_x^2 psi and the fourth time difference
    # is lam_t^2 psi, exactly, with lam the symbols of the second differences
    dt, dx, nx, m2 = 0.05, 0.1, 40, 1.0
    kappa = 2 * np.pi * 3 / (nx * dx)
    lam_x = (2 / dx * np.sin(kappa * dx / 2)) ** 2
    omega = np.sqrt(m2 + lam_x)
    lam_t = (2 / dt * np.sin(omega * dt / 2)) ** 2
    t, x = dt * np.arange(60), dx * np.arange(nx)
    values = np.cos(omega * t)[:, None] * np.cos(kappa * x)[None, :]
    field = systems.make_field(values, ("t", "x"), spacing=(dt, dx))
    assert fc.unheld_share(field, periodic) == pytest.approx(lam_x**2 / lam_t**2, rel=1e-6)


def test_exact_step_coefficients_follow_from_the_potential():
    # L = v^2/2 + cx g^2 + c2 q^2 + c4 q^4, V = -(c2 q^2 + c4 q^4): the held correction per h dx is
    # -h^2/24 V'^2 + h^2/12 V'' (v^2 - g^2)
    q, v, g = sympy.symbols("q v g")
    h, c2, c4, cx = 0.05, -0.4, -0.07, -0.45
    pot = -(c2 * q**2 + c4 * q**4)
    want = v**2 / 2 + cx * g**2 - pot - h**2 / 24 * sympy.diff(pot, q) ** 2
    want += h**2 / 12 * sympy.diff(pot, q, 2) * (v**2 - g**2)
    names = {"Dtq**2": v**2, "Dxq**2": g**2, "q**2": q**2, "q**4": q**4, "q**6": q**6}
    names |= {"Dtq**2*q**2": v**2 * q**2, "Dxq**2*q**2": g**2 * q**2}
    got = sum(c * names[k] for k, c in fc.exact_step(h, c2, c4, cx).items())
    residue = sympy.Poly(sympy.expand(got - want), q, v, g).coeffs()
    assert max((abs(float(c)) for c in residue), default=0.0) < 1e-15
    assert "Dxq**2*q**2" not in fc.exact_step(h, gradient=False)
