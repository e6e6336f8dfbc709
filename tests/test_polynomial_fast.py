"""The polynomial model's closed-form derivatives equal automatic differentiation.

The exact solve builds its residual and gauge matrices from
``feature_derivatives`` (``derivatives_of_features``): the polynomial's closed form, or the linear-model
default (forward-mode AD of ``features``); serving uses
``fast_derivatives``. Both closed forms are checked here against the AD
routes they replace, on the model variants whose chain rule differs.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import latticedft as ldft
from latticedft import systems
from latticedft._action import cell_derivatives
from latticedft._lattice import gather_cells
from latticedft._learn._data import as_fields
from latticedft._learn._exact import gauge_matrix, residual_matrix
from latticedft._learn._gauge import gauge_named

from helpers import membrane_field, oscillator_data, wave_field


class _JvpOnly(ldft.PolynomialLagrangian):
    """The same model without the closed form: the linear-model default, forward-mode AD of ``features``."""

    derivatives_of_features = ldft.LinearLagrangian.derivatives_of_features


def _kepler():
    return systems.kepler_orbit(1.0, 1.1, dt=0.05, n=60)


CASES = {
    "1d-scalar": (lambda: systems.oscillator_sin(1.2, n=51, dt=1.0), {"orders": (4, 8)}),
    "1d-vector": (_kepler, {"orders": (2, 4)}),
    "1+1d": (lambda: wave_field(nt=20), {"orders": (4, 4)}),
    "time-symmetric": (lambda: oscillator_data()[1], {"orders": (4, 8), "time_symmetric": True}),
    "monomial": (lambda: systems.oscillator_sin(1.2, n=51, dt=1.0), {"orders": (4, 8), "basis": "monomial"}),
    "full-cell-1+1d": (lambda: wave_field(nt=20), {"orders": (2, 2), "stencil": ldft.Stencil.full_cell(2)}),
    "2+1d": (lambda: membrane_field(n=8, nt=8), {"orders": (2, 2)}),
    "degree-16": (lambda: systems.oscillator_sin(1.2, n=51, dt=1.0), {"orders": (2, 16)}),
}


def _bound_pair(case: str):
    """The model and its AD-only twin, bound and scaled on the case's data (coefficients irrelevant)."""
    make, opts = CASES[case]
    fields = as_fields(make(), None)
    models = []
    for cls in (ldft.PolynomialLagrangian, _JvpOnly):
        m = cls(**opts)
        f0 = fields[0]
        m.bind(f0.ndim, f0.ncomp, f0.spacing, f0.components)
        m.prepare([gather_cells(f.values, m.stencil, f.periodic) for f in fields])
        models.append(m)
    return models, fields


def _rel(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(np.abs(a - b).max() / np.abs(b).max())


@pytest.mark.parametrize("case", list(CASES))
def test_closed_form_residual_and_gauge_matrices_equal_jvp(case):
    (fast, slow), fields = _bound_pair(case)
    assert type(fast).derivatives_of_features is not type(slow).derivatives_of_features
    for f in fields:
        r_fast, r_slow = residual_matrix(fast, f), residual_matrix(slow, f)
        assert r_fast.shape == r_slow.shape and np.abs(r_slow).max() > 0
        assert _rel(r_fast, r_slow) < 1e-12
    for gauge in ("unit-mass", "trace"):
        (g_fast, v_fast), (g_slow, v_slow) = (gauge_matrix(m, fields, gauge_named(gauge)) for m in (fast, slow))
        assert g_fast.shape == g_slow.shape and np.abs(g_slow).max() > 0
        assert _rel(g_fast, g_slow) < 1e-12
        np.testing.assert_array_equal(v_fast, v_slow)


@pytest.mark.parametrize("case", ["1d-vector", "full-cell-1+1d", "2+1d"])
def test_feature_derivatives_every_pair_equal_jvp(case):
    (model, _), fields = _bound_pair(case)
    x = gather_cells(fields[0].values, model.stencil, fields[0].periodic)
    k, m = x.shape[-2:]
    pairs = [(a, b) for a in range(k) for b in range(k)]
    d, blocks = model.feature_derivatives(x, pairs)
    c = model.n_terms
    assert d.shape == (*x.shape[:-2], k, m, c)

    def unit(a, i):
        t = torch.zeros_like(x)
        t[..., a, i] = 1.0
        return t

    for a in range(k):
        for i in range(m):
            ref = torch.func.jvp(model.features, (x,), (unit(a, i),))[1]
            assert _rel(d[..., a, i, :], ref) < 1e-12
    for a, b in pairs:
        assert blocks[(a, b)].shape == (*x.shape[:-2], m, m, c)
        for i in range(m):
            first = unit(a, i)

            def dphi(y, t=first):
                return torch.func.jvp(model.features, (y,), (t,))[1]

            for j in range(m):
                ref = torch.func.jvp(dphi, (x,), (unit(b, j),))[1]
                got = blocks[(a, b)][..., i, j, :]
                scale = float(ref.abs().max())
                if scale == 0:  # e.g. no term couples these two points
                    assert float(got.abs().max()) == 0
                else:
                    assert float((got - ref).abs().max()) / scale < 1e-12


def _cells_with_zeros(model, fields):
    """Training cells plus cells where every scaled variable is exactly 0 (vanishing factors)."""
    x = gather_cells(fields[0].values, model.stencil, fields[0].periodic)
    x = x.reshape(-1, *x.shape[-2:])[:40]
    mean = model.center[: model.m]
    flat = torch.ones(3, *x.shape[-2:], dtype=x.dtype) * mean  # all points equal: differences 0, mean = center
    return torch.cat([x, flat])


@pytest.mark.parametrize("case", list(CASES))
def test_fast_derivatives_equal_autograd(case):
    (model, _), fields = _bound_pair(case)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        model.coef.copy_(torch.randn(model.n_terms, generator=gen, dtype=torch.float64))
    x = _cells_with_zeros(model, fields)
    k = x.shape[-2]
    pairs = [(a, b) for a in range(k) for b in range(k)]
    grad, blocks = model.fast_derivatives(x, pairs)
    g_ref, b_ref = cell_derivatives(model, x, pairs, create_graph=True)  # autograd (the closed form is skipped)
    assert _rel(grad, g_ref.detach()) < 1e-12
    for pr in pairs:
        assert blocks[pr].shape == b_ref[pr].shape
        assert _rel(blocks[pr], b_ref[pr].detach()) < 1e-12
    grad_only, none = model.fast_derivatives(x, [])
    assert none == {} and _rel(grad_only, g_ref.detach()) < 1e-12


def test_chunked_evaluation_equals_one_pass():
    (model, _), fields = _bound_pair("1+1d")
    with torch.no_grad():
        model.coef.copy_(torch.linspace(-1, 1, model.n_terms, dtype=torch.float64))
    x = gather_cells(fields[0].values, model.stencil, fields[0].periodic)
    pr = [(model.stencil.anchor, model.stencil.forward), (0, 0)]
    whole = model.feature_derivatives(x, pr), model.fast_derivatives(x, pr)
    with ldft.set_options(poly_chunk_elements=5000):  # many chunks of a few cells
        parts = model.feature_derivatives(x, pr), model.fast_derivatives(x, pr)
    for (d0, b0), (d1, b1) in zip(whole, parts):  # equal up to the round-off of differently batched products
        assert d0.shape == d1.shape and _rel(d1, d0) < 1e-14
        for key in pr:
            assert b0[key].shape == b1[key].shape and _rel(b1[key], b0[key]) < 1e-14


@pytest.mark.parametrize("basis", ["legendre", "monomial"])
def test_vandermonde_tables_equal_recurrence(basis):
    model = ldft.PolynomialLagrangian(orders=(4, 12), basis=basis)
    model.bind(1, 1, (0.1,))
    z = torch.linspace(-1.2, 1.2, 241, dtype=torch.float64)[:, None]
    for fast, slow in zip(model._tables(z, 2), model._tables_recurrence(z, 2)):
        assert _rel(fast, slow) < 1e-13


def test_learned_results_match_jvp_route():
    data = systems.oscillator_sin(1.2, n=51, dt=1.0)  # the paper's Example 1
    reports = [ldft.learn(cls(orders=(4, 8)), data, progress=False) for cls in (ldft.PolynomialLagrangian, _JvpOnly)]
    fast, slow = reports
    assert fast.gauge_residual < 1e-12 and slow.gauge_residual < 1e-12
    assert fast.rel_res < 1e-9 and abs(fast.rel_res - slow.rel_res) < 1e-3 * slow.rel_res
    assert abs(fast.hessian_min_sv - slow.hessian_min_sv) < 1e-8


def test_state_and_model_file_unchanged(tmp_path):
    model = ldft.PolynomialLagrangian(orders=(4, 8))
    data = systems.oscillator_sin(1.2, n=51, dt=1.0)
    ldft.learn(model, data, progress=False)
    x = gather_cells(as_fields(data, None)[0].values, model.stencil, (False,))
    before = model.fast_derivatives(x, [(0, 1)])  # fills the caches
    assert set(model.state_dict()) == {"coef", "exponents", "center", "halfwidth", "feature_range"}  # no caches
    loaded = ldft.load_model(ldft.save_model(model, tmp_path / "m.pt"))
    after = loaded.fast_derivatives(x, [(0, 1)])
    assert torch.equal(before[0], after[0]) and torch.equal(before[1][(0, 1)], after[1][(0, 1)])
    # the cached chain-rule matrices follow in-place changes of the scaling (a new prepare)
    model.prepare([2 * x])
    _, ref = cell_derivatives(model, x, [(0, 1)], create_graph=True)
    _, new = model.fast_derivatives(x, [(0, 1)])
    assert not torch.allclose(new[(0, 1)], before[1][(0, 1)])
    assert _rel(new[(0, 1)], ref[(0, 1)].detach()) < 1e-12
