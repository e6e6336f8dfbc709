"""Closed forms of the polynomial model and of the known analytic L_d: the expression equals the model."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import latticedft as ldft
from latticedft import lagrangians


def _evaluate(model: ldft.AbstractLagrangian, cells: np.ndarray) -> np.ndarray:
    import sympy

    form = model.symbolic()
    assert form is not None
    fn = sympy.lambdify(form.flat_symbols(), form.expr, "numpy")
    return np.broadcast_to(np.asarray(fn(*cells.reshape(cells.shape[0], -1).T), dtype=np.float64), cells.shape[:1])


def _randomised(model: ldft.PolynomialLagrangian, seed: int) -> None:
    rng = np.random.default_rng(seed)
    with torch.no_grad():
        model.coef.copy_(torch.from_numpy(rng.standard_normal(model.n_terms)))
        model.center.copy_(torch.from_numpy(rng.uniform(-0.3, 0.3, model.center.numel())))
        model.halfwidth.copy_(torch.from_numpy(rng.uniform(0.5, 2.0, model.center.numel())))


@pytest.mark.parametrize(
    ("n", "m", "options"),
    [
        (1, 1, {"orders": (4, 8)}),
        (2, 1, {"orders": (2, 12), "time_symmetric": True}),
        (3, 1, {"orders": (2, 4), "basis": "monomial"}),
        (1, 2, {"orders": (2, 4), "parity": "even"}),
    ],
)
def test_polynomial_closed_form_equals_model(n: int, m: int, options: dict) -> None:
    model = ldft.PolynomialLagrangian(**options)
    assert model.symbolic() is None  # not bound yet
    model.bind(n, m, tuple([0.1] * n))
    _randomised(model, n + m)
    cells = np.random.default_rng(1).uniform(-1, 1, (32, model.stencil.size, m))
    want = model(torch.from_numpy(cells)).detach().numpy()
    got = _evaluate(model, cells)
    assert np.abs(got - want).max() <= 1e-12 * max(1.0, float(np.abs(want).max()))


def _sine_gordon() -> ldft.AnalyticLagrangian:
    def fn(c: torch.Tensor, h: tuple[float, ...]) -> torch.Tensor:
        u = c[..., 0, 0]
        return 0.5 * ((c[..., 1, 0] - u) / h[0]) ** 2 - 0.5 * ((c[..., 2, 0] - u) / h[1]) ** 2 - (1 - torch.cos(u))

    def closed(c: np.ndarray, h: tuple[float, ...]) -> object:
        import sympy

        u = c[0, 0]
        return 0.5 * ((c[1, 0] - u) / h[0]) ** 2 - 0.5 * ((c[2, 0] - u) / h[1]) ** 2 - (1 - sympy.cos(u))

    return ldft.AnalyticLagrangian(fn, closed_form=closed)


@pytest.mark.parametrize(
    ("name", "make", "n", "m"),
    [
        ("wave 2+1D", lambda: lagrangians.wave(0.7), 3, 1),
        ("wave, two components", lambda: lagrangians.wave(), 2, 2),
        ("harmonic Verlet", lambda: lagrangians.verlet(lambda q: 0.5 * q**2), 1, 1),
        ("Klein-Gordon", lambda: lagrangians.klein_gordon(1.5), 2, 1),
        ("Kepler", lambda: lagrangians.kepler(2.0), 1, 2),
        ("sine-Gordon", _sine_gordon, 2, 1),
    ],
)
def test_analytic_closed_form_equals_model(name: str, make, n: int, m: int) -> None:
    model = make()
    model.bind(n, m, tuple(0.1 + 0.05 * k for k in range(n)))
    cells = np.random.default_rng(2).uniform(0.3, 1.2, (32, model.stencil.size, m))
    want = model(torch.from_numpy(cells)).detach().numpy()
    got = _evaluate(model, cells)
    assert np.abs(got - want).max() <= 1e-12 * max(1.0, float(np.abs(want).max())), name


def test_analytic_calling_torch_has_no_closed_form() -> None:
    model = ldft.AnalyticLagrangian(lambda c, h: torch.cos(c[..., 0, 0]) + (c[..., 1, 0] - c[..., 0, 0]) ** 2)
    model.bind(1, 1, (0.1,))
    assert model.symbolic() is None


def test_analytic_closed_form_that_disagrees_is_refused() -> None:
    model = ldft.AnalyticLagrangian(lambda c, h: c[..., 1, 0] ** 2, closed_form=lambda c, h: c[1, 0] ** 3)
    model.bind(1, 1, (0.1,))
    assert model.symbolic() is None
