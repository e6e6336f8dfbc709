"""n-D slice-Newton with the polynomial's numpy closed forms equals the torch route.

``CellDerivatives`` evaluates a linear model that offers ``numpy_derivatives``
in numpy (per-variable powers, only the monomials needed, many cells at once);
the gradients and Hessian blocks are checked against autograd, and whole
served fields and a non-convergence report against the torch closed forms.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import latticedft as ldft
from latticedft import _action, systems
from latticedft._action import CellDerivatives, cell_derivatives, numpy_closed_forms
from latticedft._errors import ServeError
from latticedft._lattice import as_lattice_field, gather_cells

H = 0.05
DT = 0.4 * H


def _sine_gordon(ndim: int, n: int, nt: int) -> np.ndarray:
    """A periodic sine-Gordon field at rest at t = 0 (leapfrog), ``(nt, n, ..., n)``."""
    x = np.arange(n) / n
    u = 0.8 * np.ones([n] * ndim)
    for k in range(ndim):
        shape = [1] * ndim
        shape[k] = n
        u = u * (np.sin if k % 2 == 0 else np.cos)(2 * np.pi * x).reshape(shape)
    out = np.empty((nt, *u.shape))
    out[0] = out[1] = u
    c = (DT / H) ** 2
    for i in range(1, nt - 1):
        b = out[i]
        lap = -2 * ndim * b
        for k in range(ndim):
            lap = lap + np.roll(b, 1, k) + np.roll(b, -1, k)
        out[i + 1] = 2 * b - out[i - 1] + c * lap - DT**2 * np.sin(b)
    return out


def _field(u: np.ndarray):
    ndim = u.ndim - 1
    dims = ("t", *"zyx"[3 - ndim :])
    attrs = {d: {"periodic": "true", "period": u.shape[1] * H} for d in dims[1:]}
    return systems.make_field(u, dims, spacing=(DT, *[H] * ndim), coord_attrs=attrs)


@pytest.fixture(scope="module", params=[1, 2], ids=["1+1d", "2+1d"])
def learned(request):
    """The sine-Gordon case's polynomial class learned on a small periodic field of the dimension."""
    ndim = request.param
    n = {1: 32, 2: 10}[ndim]
    model = ldft.PolynomialLagrangian(orders=(2, 12), time_symmetric=True)
    ldft.learn(model, _field(_sine_gordon(ndim, n, 14)), progress=False)
    return ndim, model


def _cells(model, ndim: int, n: int, seed: int) -> torch.Tensor:
    """Cells of a perturbed field (inside the training range, off the training data)."""
    u = _sine_gordon(ndim, n, 2)
    u = u + 0.01 * np.random.default_rng(seed).standard_normal(u.shape)
    f = as_lattice_field(_field(u), source="init", min_slices=2)
    return gather_cells(f.values, model.stencil, f.boundary)


def _all_pairs(model) -> list[tuple[int, int]]:
    k = model.stencil.size
    return [(a, b) for a in range(k) for b in range(k)]


@pytest.mark.parametrize("n", [3, 40], ids=["few-cells", "many-cells"])
def test_gradients_and_blocks_equal_autograd(learned, n):
    ndim, model = learned
    cells = _cells(model, ndim, n, seed=n)[0]  # the cells anchored on the first slice
    assert cells.shape[:-2].numel() == n**ndim
    pairs = _all_pairs(model)
    fn = numpy_closed_forms(model, cells, pairs)
    assert fn is not None
    grad, blocks = fn(cells.numpy().reshape(-1, *cells.shape[-2:]))
    g_ad, b_ad = cell_derivatives(model, cells, pairs, create_graph=True)  # reverse-mode autograd
    g_ad = g_ad.detach().numpy()
    scale = np.abs(g_ad).max()
    assert np.abs(grad.reshape(g_ad.shape) - g_ad).max() <= 1e-11 * scale
    for p, blk in zip(pairs, blocks):
        ref = b_ad[p].detach().numpy()
        assert np.abs(blk.reshape(ref.shape) - ref).max() <= 1e-11 * max(np.abs(ref).max(), 1.0)
    ev = CellDerivatives(model, cells)  # the route serving takes
    assert ev._numpy
    grad_only = numpy_closed_forms(model, cells, ())(cells.numpy().reshape(-1, *cells.shape[-2:]))[0]
    assert np.array_equal(ev.grad.numpy(), grad_only.reshape(g_ad.shape))
    assert np.abs(grad_only.reshape(g_ad.shape) - g_ad).max() <= 1e-11 * scale
    ev_blocks = ev.blocks(pairs)
    for p, blk in zip(pairs, blocks):
        assert np.array_equal(ev_blocks[p].numpy(), blk.reshape(ev_blocks[p].shape))


def test_vector_field_and_the_term_by_term_route_equal_autograd():
    """Two components in 2+1D: six variables, a folded table too large for one product (term by term)."""
    u = _sine_gordon(2, 6, 3)
    f = _field(np.stack([u, 0.5 * u**2], axis=-1))
    data = as_lattice_field(f, source="field")
    model = ldft.PolynomialLagrangian(orders=(2, 12))  # 13 * 13 * 3**4 powers: above the folded limit
    model.bind(data.ndim, data.ncomp, data.spacing, data.components)
    cells = gather_cells(data.values, model.stencil, data.boundary)
    model.prepare([cells])
    with torch.no_grad():
        model.coef.copy_(torch.from_numpy(np.random.default_rng(1).standard_normal(model.n_terms)))
    pairs = _all_pairs(model)
    fn = numpy_closed_forms(model, cells, pairs)
    assert fn is not None
    grad, blocks = fn(cells.numpy().reshape(-1, *cells.shape[-2:]))
    g_ad, b_ad = cell_derivatives(model, cells, pairs, create_graph=True)
    g_ad = g_ad.detach().numpy()
    assert np.abs(grad.reshape(g_ad.shape) - g_ad).max() <= 1e-11 * np.abs(g_ad).max()
    for p, blk in zip(pairs, blocks):
        ref = b_ad[p].detach().numpy()
        assert np.abs(blk.reshape(ref.shape) - ref).max() <= 1e-11 * np.abs(ref).max()


def test_rebuilt_after_the_coefficients_change(learned):
    ndim, model = learned
    cells = _cells(model, ndim, 4, seed=3)
    before = CellDerivatives(model, cells).grad.clone()
    saved = model.coef.detach().clone()
    try:
        with torch.no_grad():
            model.coef.mul_(2.0)
        after = CellDerivatives(model, cells).grad
        assert torch.allclose(after, 2 * before, rtol=1e-12, atol=0)
    finally:
        with torch.no_grad():
            model.coef.copy_(saved)
    assert torch.equal(CellDerivatives(model, cells).grad, before)


def _serve_both(monkeypatch, model, init, **kw):
    out = []
    for torch_route in (False, True):
        with monkeypatch.context() as mp:
            if torch_route:
                mp.setattr(_action, "numpy_closed_forms", lambda *a: None)
            out.append(ldft.serve(model, init, progress=False, **kw))
    return out


def test_served_fields_equal_the_torch_route(monkeypatch, learned):
    ndim, model = learned
    n = {1: 300, 2: 16}[ndim]  # more cells per slice than the cells-last threshold
    init = _field(_sine_gordon(ndim, n, 2))
    fast, slow = _serve_both(monkeypatch, model, init, slices=12, affine=False)
    assert fast.complete and slow.complete
    a, b = fast.field.values, slow.field.values
    assert np.abs(a - b).max() <= 1e-12 * np.abs(b).max()
    assert (fast.newton_iterations, fast.slice_solver) == (slow.newton_iterations, slow.slice_solver)


def test_non_convergence_is_reported_as_by_the_torch_route(monkeypatch, learned):
    ndim, model = learned
    init = _field(_sine_gordon(ndim, {1: 300, 2: 16}[ndim], 2))
    errs = []
    for torch_route in (False, True):
        with monkeypatch.context() as mp:
            if torch_route:
                mp.setattr(_action, "numpy_closed_forms", lambda *a: None)
            with pytest.raises(ServeError) as info:
                ldft.serve(model, init, slices=12, affine=False, max_newton=1, progress=False)
            errs.append(info.value)
    fast, slow = errs
    assert str(fast) == str(slow) and "Newton did not converge in 1 iterations" in str(fast)
    assert (fast.slice, fast.site) == (slow.slice, slow.site)
    assert fast.residual == pytest.approx(slow.residual, rel=1e-6)
    assert fast.result.slices == slow.result.slices and not fast.result.complete


def test_a_model_on_another_device_or_precision_keeps_torch(learned):
    ndim, model = learned
    cells = _cells(model, ndim, 4, seed=5)
    assert numpy_closed_forms(model, cells.to(torch.float32), []) is None
    analytic = ldft.AnalyticLagrangian(lambda c, h: (c[..., 1, 0] - c[..., 0, 0]) ** 2, name="free")
    assert numpy_closed_forms(analytic, cells, []) is None
