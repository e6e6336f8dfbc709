"""The served map is a variational integrator: it preserves the discrete symplectic form."""

from __future__ import annotations

import numpy as np
import torch

import latticedft as ldft
from latticedft import lagrangians

from helpers import oscillator_data, quartic, series


def _canonical_map(model, q_prev, q_now, n_steps):
    """(q_i, p_i) -> (q_{i+n}, p_{i+n}) through serving; p_i = h dL/dq_i(q_{i-1}, q_i) (discrete Legendre)."""
    h = model.spacing[0]

    def momentum(qa, qb):
        cell = torch.tensor(np.stack([qa, qb])[None], dtype=torch.float64, requires_grad=True)
        (g,) = torch.autograd.grad(model(cell).sum(), cell)
        return h * g[0, 1].numpy()

    comps = None if q_now.size == 1 else ["x", "y"][: q_now.size]
    vals = np.stack([q_prev, q_now]) if comps else np.array([q_prev[0], q_now[0]])
    out = ldft.serve(model, series(vals, h, components=comps), slices=n_steps + 2).field.values.reshape(n_steps + 2, -1)
    return (q_now, momentum(q_prev, q_now)), (out[-1], momentum(out[-2], out[-1]))


def _jacobian(model, q_prev, q_now, n_steps, eps=1e-6):
    """Finite-difference Jacobian of the canonical n-step map, in (q, p) coordinates, via (q_prev, q_now)."""
    m = q_now.size
    base = np.concatenate([q_prev, q_now])

    def both(x):
        (q0, p0), (q1, p1) = _canonical_map(model, x[:m], x[m:], n_steps)
        return np.concatenate([q0, p0]), np.concatenate([q1, p1])

    cols_in, cols_out = [], []
    for k in range(2 * m):
        d = np.zeros(2 * m)
        d[k] = eps
        a_in, a_out = both(base + d)
        b_in, b_out = both(base - d)
        cols_in.append((a_in - b_in) / (2 * eps))
        cols_out.append((a_out - b_out) / (2 * eps))
    d_in = np.stack(cols_in, 1)  # d(q_i, p_i) / d(q_prev, q_now)
    d_out = np.stack(cols_out, 1)
    return d_out @ np.linalg.inv(d_in)


def test_one_step_map_of_learned_scalar_theory_has_unit_determinant():
    _, data = oscillator_data()
    model = ldft.PolynomialLagrangian(orders=(4, 4))
    ldft.learn(model, data)
    for n in (1, 25):
        jac = _jacobian(model, np.array([0.9]), np.array([0.88]), n)
        assert abs(np.linalg.det(jac) - 1) < 1e-7


def test_learned_map_is_symplectic_not_just_volume_preserving_m2():
    dt = 0.05
    kep = lagrangians.kepler()
    kep.bind(1, 2, (dt,), ("x", "y"))
    omega = np.block([[np.zeros((2, 2)), np.eye(2)], [-np.eye(2), np.zeros((2, 2))]])
    for n in (1, 40):
        jac = _jacobian(kep, np.array([1.0, 0.0]), np.array([0.9988, 0.0498]), n)
        np.testing.assert_allclose(jac.T @ omega @ jac, omega, atol=2e-7)


def test_a_non_variational_map_fails_the_check():
    """The test above can fail: an explicit Euler step of the oscillator is not symplectic."""
    h = 0.1

    def euler(q, p):
        return q + h * p, p - h * (q + q**3)

    eps = 1e-6
    q, p = 0.9, 0.1
    jac = np.array(
        [
            [(euler(q + eps, p)[i] - euler(q - eps, p)[i]) / (2 * eps) for i in range(2)],
            [(euler(q, p + eps)[i] - euler(q, p - eps)[i]) / (2 * eps) for i in range(2)],
        ]
    ).T
    assert abs(np.linalg.det(jac) - 1) > 1e-3


def test_energy_error_stays_bounded_over_long_runs():
    _, data = oscillator_data()
    model = ldft.PolynomialLagrangian(orders=(4, 4))
    ldft.learn(model, data)
    q = ldft.serve(model, data[1].isel(t=slice(0, 2)), slices=3000).field.values
    h = 0.1
    p = (q[2:] - q[:-2]) / (2 * h)
    e = 0.5 * p**2 + quartic(torch.tensor(q[1:-1])).numpy()
    assert np.ptp(e[-600:]) < 2 * np.ptp(e[:600]) + 1e-12  # oscillates, does not drift
